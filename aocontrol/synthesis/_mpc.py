"""MPC design: the LQG design (disturbance model, Kalman predictor, regulator) plus limits.

PSDs are one-sided [units^2/Hz]. Control layer: imports nothing from :mod:`aocontrol.sim` or
:mod:`aocontrol.study`.
"""

from __future__ import annotations

from collections.abc import Sequence

import control

from aocontrol._deprecation import renamed_keyword
from aocontrol.controllers import MPCBank
from aocontrol.synthesis._armodel import DisturbanceModel
from aocontrol.synthesis._lqg import lqg

__all__ = ["mpc"]


@renamed_keyword("stroke", "command_limit", "the MPC's hard limit on its modal command")
def mpc(
    plant: control.TransferFunction,
    freqs: object,
    psd: object,
    *,
    noise_psd: object = 0.0,
    horizon: int = 10,
    command_limit: object = None,
    rate_limit: object = None,
    groups: Sequence[Sequence[int]] | None = None,
    control_weight: float = 0.0,
    model: DisturbanceModel | None = None,
    n_vibrations: int = 2,
    solver: str = "daqp",
    skip_inactive: bool = True,
) -> MPCBank:
    """MPC bank from disturbance and noise PSDs, with the disturbance model of :func:`lqg`.

    The model (AR(2) turbulence plus AR(2) resonances, fitted from ``psd`` unless ``model`` is
    given), the Kalman predictor and the regulator are those of
    :func:`aocontrol.synthesis.lqg` with the same arguments; the MPC adds the horizon and the
    hard limits (:class:`aocontrol.controllers.MPCBank`). With no active limit its command
    is the LQG command.

    Parameters
    ----------
    plant : control.TransferFunction
        Loop plant :func:`aocontrol.plant.loop_plant` (its latency, fractional included).
    freqs : array_like, shape (n_freqs,)
        Strictly increasing grid in ``[0, fs/2]`` [Hz].
    psd : array_like, shape (n_freqs,) or (n_modes, n_freqs)
        Disturbance PSD, one-sided [units^2/Hz].
    noise_psd : float or array_like, default 0.0
        White measurement-noise PSD, one-sided [units^2/Hz]: scalar or one level per mode.
    horizon : int, default 10
        Prediction horizon [frames], >= 1.
    command_limit : float or array_like of shape (n_modes,), optional
        Hard limit ``|u| <= command_limit`` on the modal command [units of the command]
        (see :class:`~aocontrol.controllers.MPCBank`; ``stroke`` is its deprecated name).
    rate_limit : float or array_like of shape (n_modes,), optional
        Hard limit on ``|u[j] - u[j-1]|`` [units per frame].
    groups : sequence of sequences of int, optional
        Modes solved as one QP (e.g. ``[[0, 1]]`` for tip and tilt).
    control_weight : float, default 0.0
        Weight ``rho`` of ``u^2`` in the stage cost (see :func:`lqg_state_space`).
    model : DisturbanceModel, optional
        A known disturbance model instead of the fit.
    n_vibrations : int, default 2
        Largest number of resonances fitted per mode.
    solver : {"daqp", "qpoases", "osqp"}, default "daqp"
        QP solver: DAQP (real time), or the casadi formulation with that plugin (the
        reference); see :class:`~aocontrol.controllers.MPCBank`.
    skip_inactive : bool, default True
        Apply the unconstrained optimum without a solve when it meets every limit.

    Returns
    -------
    MPCBank

    Raises
    ------
    ValueError, TypeError
        Bad inputs (those of :func:`lqg` and :class:`~aocontrol.controllers.MPCBank`).
    """
    bank = lqg(
        plant,
        freqs,
        psd,
        noise_psd=noise_psd,
        n_vibrations=n_vibrations,
        control_weight=control_weight,
        model=model,
    )
    return MPCBank(
        bank.state_space,
        horizon,
        command_limit=command_limit,
        rate_limit=rate_limit,
        groups=groups,
        solver=solver,
        skip_inactive=skip_inactive,
        model=bank.model,
    )
