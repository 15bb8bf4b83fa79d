"""The controllers of the case comparison: what a design receives, and the registry.

A controller joins :func:`aocontrol.study.compare.compare_case` (and the CLI and sweeps) through
:func:`register_controller` with a :class:`ControllerSpec`, whose ``design`` maps
:class:`DesignInputs` (everything from the calibration telemetry, nothing from the simulator's
hidden disturbance) to a :class:`~aocontrol.controllers.ControllerBank`. Built in: the
reference integrator ``reference`` (also reachable by its alias ``integrator``,
:data:`CONTROLLER_ALIASES`: one controller, one spec, one name in the results), ``omgi``,
``datadriven``, ``lqg`` and ``mpc``.
Re-exported by :mod:`aocontrol.study.compare`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aocontrol.controllers import ControllerBank, Integrator
from aocontrol.synthesis import TelemetryPSD, datadriven, lqg, mpc, optimal_modal_gain

__all__ = [
    "CONTROLLERS",
    "CONTROLLER_ALIASES",
    "controller_names",
    "get_controller",
    "MODULUS_MARGIN",
    "MPC_HORIZON",
    "ControllerSpec",
    "DesignInputs",
    "register_controller",
]

#: Modulus margin of the designed controllers (the paper's robustness constraint).
MODULUS_MARGIN = 0.5


@dataclass(frozen=True, eq=False)
class DesignInputs:
    """What a controller factory receives (all from telemetry, none from the simulator).

    Parameters
    ----------
    plant : control.TransferFunction
        Stage-2 loop plant.
    freqs : ndarray, shape (n_f,)
        Frequencies [Hz] of the PSDs.
    psd : ndarray, shape (n_modes, n_f)
        Pseudo-open-loop disturbance PSD, one-sided [nm^2/Hz].
    noise_psd : ndarray, shape (n_modes,)
        White noise level, one-sided [nm^2/Hz].
    fs : float
        Stage-2 rate [Hz].
    n_modes : int
    reference_gain : float
        Gain of the reference integrator (scanned, or the case's).
    telemetry : TelemetryPSD or None
        The full estimate (pseudo-open loop included).
    stroke : ndarray of shape (n_modes,) or None
        Per-mode command bound [nm] implied by the stage-2 DM's actuator stroke
        (:func:`aocontrol.sim.dm.modal_stroke`; ``None``: unlimited); the MPC's command limit.
    """

    plant: Any
    freqs: np.ndarray
    psd: np.ndarray
    noise_psd: np.ndarray
    fs: float
    n_modes: int
    reference_gain: float
    telemetry: TelemetryPSD | None = None
    stroke: np.ndarray | None = None


@dataclass(frozen=True)
class ControllerSpec:
    """A controller of the comparison: a name and a factory.

    Parameters
    ----------
    name : str
        Registry name.
    design : callable
        ``design(inputs: DesignInputs) -> ControllerBank`` with ``inputs.n_modes`` modes at
        ``inputs.fs``.
    needs_telemetry : bool
        Whether the design needs the calibration run (False for the reference).
    parameters : dict
        JSON-serialisable design parameters (recorded in the settings).
    """

    name: str
    design: Callable[[DesignInputs], ControllerBank]
    needs_telemetry: bool = True
    parameters: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name must be a non-empty str, got {self.name!r}")
        if not callable(self.design):
            raise TypeError(f"design must be callable, got {type(self.design).__name__}")


def _reference(inp: DesignInputs) -> ControllerBank:
    return Integrator(inp.reference_gain, fs=inp.fs, n_modes=inp.n_modes)


def _omgi(inp: DesignInputs) -> ControllerBank:
    return optimal_modal_gain(
        inp.plant, inp.freqs, inp.psd, inp.noise_psd, modulus_margin=MODULUS_MARGIN
    )


def _datadriven(inp: DesignInputs) -> ControllerBank:
    res = datadriven(
        inp.plant,
        inp.freqs,
        inp.psd,
        order=5,
        noise_psd=inp.noise_psd,
        modulus_margin=MODULUS_MARGIN,
        progress=False,
    )
    return res.controller


def _lqg(inp: DesignInputs) -> ControllerBank:
    # AR(2) turbulence + up to 2 resonances per mode fitted to the telemetry PSD, minimum
    # variance (no control weight: the fractional latencies of the cases are not 0.5 frame).
    return lqg(inp.plant, inp.freqs, inp.psd, noise_psd=inp.noise_psd, n_vibrations=2)


def _mpc(inp: DesignInputs) -> ControllerBank:
    # The LQG's model and estimator, horizon 10 frames, each mode's command limited to the
    # bound the DM's actuator stroke implies for it alone (inp.stroke, from m2c); modes
    # combined may still reach the stroke at an actuator, where the DM clips.
    return mpc(
        inp.plant,
        inp.freqs,
        inp.psd,
        noise_psd=inp.noise_psd,
        horizon=MPC_HORIZON,
        stroke=inp.stroke,
        n_vibrations=2,
    )


#: MPC prediction horizon [frames] in the comparison.
MPC_HORIZON = 10

#: Registered controllers (name -> spec); see :func:`register_controller`.
CONTROLLERS: dict[str, ControllerSpec] = {}


def register_controller(spec: ControllerSpec, *, replace: bool = False) -> None:
    """Add a controller to :data:`CONTROLLERS`.

    Parameters
    ----------
    spec : ControllerSpec
    replace : bool
        Allow replacing an existing name.

    Raises
    ------
    ValueError
        The name is taken and ``replace`` is False.
    """
    if not isinstance(spec, ControllerSpec):
        raise TypeError(f"spec must be a ControllerSpec, got {type(spec).__name__}")
    if spec.name in CONTROLLERS and not replace:
        raise ValueError(f"controller {spec.name!r} is already registered")
    CONTROLLERS[spec.name] = spec


#: Other names accepted for registered controllers (alias -> registered name). A run asked
#: for by its alias is the registered controller's: its results record the registered name.
CONTROLLER_ALIASES: dict[str, str] = {"integrator": "reference"}


def controller_names() -> tuple[str, ...]:
    """Every name a run may ask for: the registered names, then the aliases.

    Returns
    -------
    tuple of str
    """
    return (*CONTROLLERS, *(a for a in CONTROLLER_ALIASES if a not in CONTROLLERS))


def get_controller(name: str) -> ControllerSpec:
    """The registered spec of ``name`` (a registered name or an alias).

    Parameters
    ----------
    name : str
        E.g. ``"reference"`` or its alias ``"integrator"``.

    Returns
    -------
    ControllerSpec

    Raises
    ------
    ValueError
        An unknown name (the message lists the valid ones).
    """
    spec = CONTROLLERS.get(name) or CONTROLLERS.get(CONTROLLER_ALIASES.get(name, ""))
    if spec is None:
        raise ValueError(f"controller must be one of {sorted(controller_names())}, got {name!r}")
    return spec


register_controller(
    ControllerSpec("reference", _reference, needs_telemetry=False, parameters={"scan": True})
)
register_controller(ControllerSpec("omgi", _omgi, parameters={"modulus_margin": MODULUS_MARGIN}))
register_controller(
    ControllerSpec(
        "datadriven",
        _datadriven,
        parameters={"order": 5, "noise_term": True, "modulus_margin": MODULUS_MARGIN},
    )
)
register_controller(
    ControllerSpec("lqg", _lqg, parameters={"turbulence": "AR(2)", "n_vibrations": 2})
)
register_controller(
    ControllerSpec(
        "mpc",
        _mpc,
        parameters={"turbulence": "AR(2)", "n_vibrations": 2, "horizon": MPC_HORIZON},
    )
)
