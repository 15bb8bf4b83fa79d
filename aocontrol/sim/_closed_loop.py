"""The linear closed loop of a stage, checked before a run: its largest pole modulus per mode.

Private module of the simulator (public as :func:`aocontrol.sim.loop.closed_loop_pole_radius`);
the stage's run state (:mod:`aocontrol.sim._stage_run`) takes a mode whose loop is unstable as
known to diverge.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from aocontrol.analysis import multimode_closed_loop_poles
from aocontrol.controllers import IIRBank, MultiModeBank
from aocontrol.plant import split_latency, z_inverse_coefficients
from aocontrol.sim._stage import Stage

logger = logging.getLogger(__name__)

#: Largest closed-loop state of a multi-mode loop checked before a run (dense eigenvalues,
#: O(dim^3): 1500 takes about 2 s on one core; a quick scene's 24 modes with 20 frames of
#: history are ~550, the full scale's 540 modes with 5 are ~3800 and are not checked).
MULTIMODE_MAX_STATE = 1500


def closed_loop_pole_radius(stage: Stage, optical_gain: np.ndarray) -> np.ndarray | None:
    """Largest closed-loop pole modulus per mode of a linear stage, or ``None``.

    The loop of :func:`aocontrol.loop_plant` with the stage's latency, the sensor's optical
    gain and the controller's linear part (an :class:`~aocontrol.controllers.IIRBank`'s
    coefficients, else every mode's ``transfer_function``): the characteristic polynomial
    ``A_k + og B_g B_k`` in powers of ``z^-1``, roots from batched companion matrices.
    ``None`` when the controller has no transfer function. A
    :class:`~aocontrol.controllers.MultiModeBank` couples the modes: the poles of its whole
    loop (:func:`aocontrol.analysis.multimode_closed_loop_poles`, the DM's response and
    mixing included), their largest modulus for every mode; 0 when the plant is the
    controller's model (structurally stable, certified at design), ``None`` when the state
    exceeds :data:`MULTIMODE_MAX_STATE`. With model errors
    (:mod:`aocontrol.sim.model_errors`): the DM's response in the plant, each mode's own
    part of a mixing (its coupling to the others is not in a per-mode check), a drifting
    optical gain at both ends of its modulation.

    Parameters
    ----------
    stage : Stage
        Stage to check.
    optical_gain : ndarray (n_modes,)
        Sensor optical gains.

    Returns
    -------
    ndarray (n_modes,) or None
    """
    ctrl = stage.controller
    if isinstance(ctrl, MultiModeBank):
        return _multimode_radius(stage, np.asarray(optical_gain, dtype=float))
    coeffs = _controller_coefficients(ctrl)
    if coeffs is None:
        return None
    k0, frac = stage.delay
    bg = np.zeros(k0 + 3)
    bg[k0 + 1] = 1.0 - frac
    bg[k0 + 2] = frac
    ah = np.array([1.0])
    gain = np.asarray(optical_gain, dtype=float)
    dm = stage.dm
    if dm.response is not None:  # the true plant is G H (aocontrol.sim.model_errors)
        bh, ah = dm.response.coefficients(stage.fs)
        bg = np.convolve(bg, bh)
    if dm.mixing is not None:  # per mode: the diagonal of the mixing (the coupling apart)
        gain = gain * np.diag(dm.mixing)
    err = stage.optical_gain_error
    if err is None:
        return _radius(coeffs, bg, ah, gain)
    # Drifting gains: the loop at both ends of the modulation (a frozen-gain check).
    factors = np.broadcast_to(err.factor, (ctrl.n_modes,))
    return np.maximum(
        _radius(coeffs, bg, ah, gain * factors * (1.0 - err.drift)),
        _radius(coeffs, bg, ah, gain * factors * (1.0 + err.drift)),
    )


def _multimode_radius(stage: Stage, optical_gain: np.ndarray) -> np.ndarray | None:
    """Largest pole modulus of a multi-mode loop, for every mode (or ``None``, too large)."""
    ctrl, dm = stage.controller, stage.dm
    n = ctrl.n_modes
    err = stage.optical_gain_error
    nominal = (
        stage.latency_frames == ctrl.latency_frames
        and np.all(optical_gain == 1.0)
        and dm.response is None
        and dm.mixing is None
        and err is None
    )
    if nominal:
        return np.zeros(n)
    dm_coefficients = None if dm.response is None else dm.response.coefficients(stage.fs)
    depth = split_latency(max(stage.latency_frames, ctrl.latency_frames))[0] + 2
    na = 0 if dm_coefficients is None else dm_coefficients[1].size - 1
    nb = 0 if dm_coefficients is None else dm_coefficients[0].size - 1
    dim = n * (ctrl.history - 1 + depth + nb + na)
    if dim > MULTIMODE_MAX_STATE:
        logger.info(
            "%s: no closed-loop pole check for a multi-mode loop of state %d > %d",
            stage.name,
            dim,
            MULTIMODE_MAX_STATE,
        )
        return None
    gains = [optical_gain]
    if err is not None:  # a drifting gain: the loop at both ends of the modulation
        factors = np.broadcast_to(err.factor, (n,))
        gains = [
            optical_gain * factors * (1.0 - err.drift),
            optical_gain * factors * (1.0 + err.drift),
        ]
    radius = max(
        float(
            np.abs(
                multimode_closed_loop_poles(
                    ctrl,
                    latency_frames=stage.latency_frames,
                    optical_gain=g,
                    mixing=dm.mixing,
                    dm_coefficients=dm_coefficients,
                )
            ).max()
        )
        for g in gains
    )
    return np.full(n, radius)


def _radius(coeffs: tuple, bg: np.ndarray, ah: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Largest root modulus per mode of ``A_k A_h + gain B_g B_k`` (powers of ``z^-1``)."""
    b, a = coeffs
    n = a.shape[0]
    length = max(a.shape[1] + ah.size - 1, bg.size + b.shape[1] - 1)
    char = np.zeros((n, length))
    # A_k A_h and B_g B_k per mode (shared A_h, B_g): convolutions as sums of shifted copies.
    for i, h in enumerate(ah):
        if h:
            char[:, i : i + a.shape[1]] += h * a
    for i, g in enumerate(bg):
        if g:
            char[:, i : i + b.shape[1]] += (gain * g)[:, None] * b
    # Trim trailing zero columns (common to every mode) and normalise.
    nz = np.flatnonzero(np.any(char != 0, axis=0))
    char = char[:, : nz[-1] + 1] / char[:, :1]
    order = char.shape[1] - 1
    if order == 0:
        return np.zeros(n)
    comp = np.zeros((n, order, order))
    comp[:, 0, :] = -char[:, 1:]
    if order > 1:
        idx = np.arange(order - 1)
        comp[:, idx + 1, idx] = 1.0
    return np.abs(np.linalg.eigvals(comp)).max(axis=1)


def _controller_coefficients(ctrl: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """``(b, a)`` in powers of ``z^-1``, shape ``(n_modes, n)``, of a linear controller bank.

    From the coefficients of an :class:`IIRBank`, else from ``transfer_function(mode)`` of
    every mode; ``None`` when the controller has no (causal, finite) transfer function.
    """
    if isinstance(ctrl, IIRBank):
        return ctrl.b, ctrl.a
    try:
        pairs = [z_inverse_coefficients(ctrl.transfer_function(i)) for i in range(ctrl.n_modes)]
    except (NotImplementedError, TypeError, ValueError, ArithmeticError) as exc:
        logger.info("no closed-loop pole check for %s: %s", type(ctrl).__name__, exc)
        return None
    bank = IIRBank.from_rows([bi for bi, _ in pairs], [ai for _, ai in pairs], ctrl.fs)
    return bank.b, bank.a
