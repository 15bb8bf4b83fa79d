"""The controller registry: a name -> a design on disturbance and noise PSDs.

Control layer: what a design receives (:class:`DesignInputs`: the plant, the PSDs estimated
from telemetry, the reference gain) and the designs themselves. One registry serves
:func:`aocontrol.synthesis.design_from_telemetry`, the CLI's ``design`` and the simulator's
comparison (:mod:`aocontrol.study.compare`, which re-exports it). Built in: the reference
integrator (alias ``integrator``), ``omgi``, ``datadriven``, ``datadriven-robust`` (certified
over :data:`ROBUST_SET`), ``datadriven-integral`` (a fixed pole at ``z = 1``), ``lqg``, ``mpc``
and ``eof`` (the multi-mode predictor, trained on the pseudo-open loop itself rather than on
PSDs).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from aocontrol._deprecation import DeprecatedAttribute, renamed_keyword
from aocontrol.analysis import UncertaintySet
from aocontrol.controllers import ControllerBank, Integrator
from aocontrol.plant import split_latency
from aocontrol.synthesis._datadriven import DataDrivenResult
from aocontrol.synthesis._dd_neighbours import datadriven_neighbours
from aocontrol.synthesis._eof import EOFResult, eof_from_pseudo_open_loop
from aocontrol.synthesis._lqg import lqg, plant_latency
from aocontrol.synthesis._modal_gain import optimal_modal_gain
from aocontrol.synthesis._mpc import mpc
from aocontrol.synthesis._telemetry import TelemetryPSD

__all__ = [
    "CONTROLLERS",
    "CONTROLLER_ALIASES",
    "controller_names",
    "get_controller",
    "MODULUS_MARGIN",
    "MPC_HORIZON",
    "EOF_HISTORY",
    "EOF_MAX_HISTORY",
    "EOF_REGRESSORS",
    "eof_default_history",
    "ControllerSpec",
    "DesignInputs",
    "register_controller",
]

#: Default modulus margin of the designed controllers (the paper's robustness constraint).
MODULUS_MARGIN = 0.5
#: Default MPC prediction horizon [frames].
MPC_HORIZON = 10
#: Shortest default history of the multi-mode predictor ``eof`` [frames of pseudo-open loop].
EOF_HISTORY = 5
#: Longest default history of ``eof`` [frames] (a noise-limited stage needs the longer filter:
#: docs/benchmarks.md, "Multi-mode (EOF) predictor").
EOF_MAX_HISTORY = 20
#: Regressors ``n_modes x history`` the default history keeps within: the training's cost
#: grows as their cube (540 modes x 5 frames trained in about 7 s on one core).
EOF_REGRESSORS = 2700


def eof_default_history(n_modes: int) -> int:
    """The registry's history for ``n_modes`` modes: the longest within
    :data:`EOF_REGRESSORS` regressors, between :data:`EOF_HISTORY` and
    :data:`EOF_MAX_HISTORY` frames (20 frames up to 135 modes, 5 from 540).

    Parameters
    ----------
    n_modes : int
        Controlled modes (>= 1).

    Returns
    -------
    int
    """
    if not (isinstance(n_modes, (int, np.integer)) and n_modes >= 1):
        raise ValueError(f"n_modes must be an integer >= 1, got {n_modes!r}")
    return int(max(EOF_HISTORY, min(EOF_MAX_HISTORY, EOF_REGRESSORS // int(n_modes))))


@renamed_keyword("stroke", "command_limit", "the per-mode bound on the modal command")
@dataclass(frozen=True, eq=False)
class DesignInputs:
    """What a controller design receives (all from telemetry, none from a simulator).

    Parameters
    ----------
    plant : control.TransferFunction
        Loop plant (command to measurement).
    freqs : ndarray, shape (n_f,)
        Frequencies [Hz] of the PSDs.
    psd : ndarray, shape (n_modes, n_f)
        Pseudo-open-loop disturbance PSD, one-sided [units^2/Hz].
    noise_psd : ndarray, shape (n_modes,)
        White noise level, one-sided [units^2/Hz].
    fs : float
        Loop rate [Hz].
    n_modes : int
    reference_gain : float
        Gain of the reference integrator (scanned, the case's or the user's).
    telemetry : TelemetryPSD or None
        The full estimate (pseudo-open loop included).
    command_limit : float or ndarray of shape (n_modes,) or None
        Per-mode bound on the modal command [units] (``None``: unlimited); the MPC's command
        limit (``stroke`` is its deprecated name). The simulator gives the bound its DM
        implies for each mode alone (:attr:`aocontrol.sim.dm.ModalDM.command_bound`, from
        ``m2c`` and the actuator stroke by :func:`aocontrol.sim.dm.modal_stroke`).
    modulus_margin : float, default :data:`MODULUS_MARGIN`
        Required modulus margin of the designs that take one.
    options : mapping, default empty
        Design options overriding the spec's defaults (names in
        :attr:`ControllerSpec.options`), e.g. ``{"order": 7}``.
    client : distributed.Client or None, default None
        A Dask cluster for the designs that run on one (:attr:`ControllerSpec.distributed`);
        ``None``: local processes.
    """

    plant: Any
    freqs: np.ndarray
    psd: np.ndarray
    noise_psd: np.ndarray
    fs: float
    n_modes: int
    reference_gain: float
    telemetry: TelemetryPSD | None = None
    command_limit: float | np.ndarray | None = None
    modulus_margin: float = MODULUS_MARGIN
    options: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    client: Any = None

    #: Deprecated name of :attr:`command_limit`.
    stroke = DeprecatedAttribute("command_limit", "the per-mode bound on the modal command")

    def option(self, name: str, default: Any) -> Any:
        """The option ``name`` if given, else ``default``."""
        return self.options.get(name, default)


def _no_details(design: Callable[[DesignInputs], ControllerBank]) -> Callable:
    def build(inp: DesignInputs) -> tuple[ControllerBank, None]:
        return design(inp), None

    return build


@dataclass(frozen=True)
class ControllerSpec:
    """A registered controller: a name and a design.

    Parameters
    ----------
    name : str
        Registry name.
    design : callable
        ``design(inputs: DesignInputs) -> ControllerBank`` with ``inputs.n_modes`` modes at
        ``inputs.fs``.
    needs_telemetry : bool
        Whether the design needs the PSDs (False for the reference integrator).
    parameters : dict
        JSON-serialisable description of the design (recorded in settings).
    options : tuple of str
        Names of the :attr:`DesignInputs.options` the design reads.
    design_with_details : callable, optional
        ``(inputs) -> (ControllerBank, details)`` when the synthesis has a result worth
        keeping (e.g. :class:`~aocontrol.synthesis.DataDrivenResult`); default ``design``
        with ``None``.
    distributed : bool, default False
        Whether the design runs its per-mode work on a Dask cluster
        (:attr:`DesignInputs.client`); the others refuse a client.
    """

    name: str
    design: Callable[[DesignInputs], ControllerBank]
    needs_telemetry: bool = True
    parameters: dict = field(default_factory=dict)
    options: tuple[str, ...] = ()
    design_with_details: Callable[[DesignInputs], tuple[ControllerBank, Any]] | None = None
    distributed: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name must be a non-empty str, got {self.name!r}")
        if not callable(self.design):
            raise TypeError(f"design must be callable, got {type(self.design).__name__}")

    def check_client(self, client: Any) -> None:
        """Refuse a Dask ``client`` (not None) for a design that does not run on one.

        Raises
        ------
        ValueError
            ``client`` is given and the design is not :attr:`distributed`.
        """
        if client is not None and not self.distributed:
            runs = [name for name, spec in CONTROLLERS.items() if spec.distributed]
            raise ValueError(
                f"controller {self.name!r} does not run on a Dask client; client is for {runs}"
            )

    def build(self, inputs: DesignInputs) -> tuple[ControllerBank, Any]:
        """Run the design: ``(bank, details)`` (``details`` may be ``None``)."""
        unknown = sorted(set(inputs.options) - set(self.options))
        if unknown:
            raise ValueError(
                f"options {unknown} are not options of controller {self.name!r}; expected "
                f"some of {list(self.options)}"
            )
        self.check_client(inputs.client)
        fn = self.design_with_details or _no_details(self.design)
        return fn(inputs)


def _reference(inp: DesignInputs) -> ControllerBank:
    return Integrator(inp.reference_gain, fs=inp.fs, n_modes=inp.n_modes)


def _omgi(inp: DesignInputs) -> ControllerBank:
    return optimal_modal_gain(
        inp.plant, inp.freqs, inp.psd, inp.noise_psd, modulus_margin=inp.modulus_margin
    )


def _datadriven_details(
    inp: DesignInputs, **structure: object
) -> tuple[ControllerBank, DataDrivenResult]:
    # Option "stride" > 1: the cold design of every stride-th mode, the others warm-started
    # from their nearest designed mode (datadriven_neighbours; it changes results, within the
    # tolerance its docstring measures). Default 1: the cold bank.
    res = datadriven_neighbours(
        inp.plant,
        inp.freqs,
        inp.psd,
        stride=inp.option("stride", 1),
        order=inp.option("order", 5),
        noise_psd=inp.noise_psd,
        modulus_margin=inp.modulus_margin,
        progress=inp.option("progress", False),
        n_jobs=inp.option("n_jobs", None),
        client=inp.client,
        **structure,
    )
    return res.controller, res


#: The uncertainty set of the robust data-driven design (``"datadriven-robust"``): the loop
#: gain within +-30 % (optical gains, a DM's gain) and the latency within +-0.3 frame.
ROBUST_SET = UncertaintySet(gain=(0.7, 1.3), latency=(-0.3, 0.3))


def _datadriven_robust_details(inp: DesignInputs) -> tuple[ControllerBank, DataDrivenResult]:
    gain = tuple(inp.option("gain_interval", ROBUST_SET.gain))
    latency = tuple(inp.option("latency_interval", ROBUST_SET.latency))
    uset = UncertaintySet(gain=gain, latency=latency)
    return _datadriven_details(inp, uncertainty=uset)


def _datadriven_integral_details(inp: DesignInputs) -> tuple[ControllerBank, DataDrivenResult]:
    return _datadriven_details(inp, fixed_denominator=[1.0, -1.0])


def _datadriven(inp: DesignInputs) -> ControllerBank:
    return _datadriven_details(inp)[0]


def _lqg(inp: DesignInputs) -> ControllerBank:
    # AR(2) turbulence + up to 2 resonances per mode fitted to the telemetry PSD, minimum
    # variance by default (no control weight: the fractional latencies of the cases are not
    # 0.5 frame).
    return lqg(
        inp.plant,
        inp.freqs,
        inp.psd,
        noise_psd=inp.noise_psd,
        n_vibrations=inp.option("n_vibrations", 2),
        control_weight=inp.option("control_weight", 0.0),
        n_jobs=inp.option("n_jobs", 1),
    )


def _mpc(inp: DesignInputs) -> ControllerBank:
    # The LQG's model and estimator, horizon 10 frames, each mode's command limited to
    # inp.command_limit (from the simulator: the bound its DM implies for the mode alone,
    # ModalDM.command_bound); modes combined may still reach the stroke at an actuator, where
    # the DM clips.
    return mpc(
        inp.plant,
        inp.freqs,
        inp.psd,
        noise_psd=inp.noise_psd,
        horizon=inp.option("horizon", MPC_HORIZON),
        command_limit=inp.command_limit,
        n_vibrations=inp.option("n_vibrations", 2),
    )


def _eof_details(inp: DesignInputs) -> tuple[ControllerBank, EOFResult]:
    # The multi-mode predictor from the telemetry's pseudo-open loop (not from the PSDs: it
    # needs the cross-mode correlations in time), its first k + 2 frames dropped (they need
    # commands before the record), at the plant's latency, certified at the design margin.
    # No command limit: like the other linear designs it leaves the stroke to the DM.
    if inp.telemetry is None:
        raise ValueError(
            "controller 'eof' needs telemetry (DesignInputs.telemetry with its pseudo-open "
            "loop): a multi-mode predictor is trained on the time series, not on PSDs"
        )
    latency = plant_latency(inp.plant)
    k0, _ = split_latency(latency)
    res = eof_from_pseudo_open_loop(
        inp.telemetry.pseudo_open_loop[k0 + 2 :],
        inp.fs,
        latency,
        history=inp.option("history", eof_default_history(inp.n_modes)),
        regularisation=inp.option("regularisation", None),
        modulus_margin=inp.modulus_margin,
    )
    return res.controller, res


def _eof(inp: DesignInputs) -> ControllerBank:
    return _eof_details(inp)[0]


#: Registered controllers (name -> spec); see :func:`register_controller`.
CONTROLLERS: dict[str, ControllerSpec] = {}


#: Other names of registered controllers: one controller, one spec, one name in the results.
CONTROLLER_ALIASES: dict[str, str] = {"integrator": "reference"}


def controller_names() -> tuple[str, ...]:
    """Every name a design or a run may ask for: the registered names, then the aliases.

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


_REF = ControllerSpec("reference", _reference, needs_telemetry=False, parameters={"scan": True})
register_controller(_REF)
register_controller(ControllerSpec("omgi", _omgi, parameters={"modulus_margin": MODULUS_MARGIN}))
register_controller(
    ControllerSpec(
        "datadriven",
        _datadriven,
        parameters={"order": 5, "noise_term": True, "modulus_margin": MODULUS_MARGIN},
        options=("order", "n_jobs", "progress", "stride"),
        design_with_details=_datadriven_details,
        distributed=True,
    )
)
register_controller(
    ControllerSpec(
        "datadriven-robust",
        lambda inp: _datadriven_robust_details(inp)[0],
        parameters={
            "order": 5,
            "modulus_margin": MODULUS_MARGIN,
            "gain_interval": ROBUST_SET.gain,
            "latency_interval": ROBUST_SET.latency,
        },
        options=("order", "n_jobs", "progress", "stride", "gain_interval", "latency_interval"),
        design_with_details=_datadriven_robust_details,
        distributed=True,
    )
)
register_controller(
    ControllerSpec(
        "datadriven-integral",
        lambda inp: _datadriven_integral_details(inp)[0],
        parameters={"order": 5, "modulus_margin": MODULUS_MARGIN, "integral_action": True},
        options=("order", "n_jobs", "progress", "stride"),
        design_with_details=_datadriven_integral_details,
        distributed=True,
    )
)
register_controller(
    ControllerSpec(
        "lqg",
        _lqg,
        parameters={"turbulence": "AR(2)", "n_vibrations": 2},
        options=("n_vibrations", "control_weight", "n_jobs"),
    )
)
register_controller(
    ControllerSpec(
        "mpc",
        _mpc,
        parameters={"turbulence": "AR(2)", "n_vibrations": 2, "horizon": MPC_HORIZON},
        options=("n_vibrations", "horizon"),
    )
)
register_controller(
    ControllerSpec(
        "eof",
        _eof,
        parameters={
            "predictor": "multi-mode FIR on the pseudo-open loop",
            "history": f"{EOF_HISTORY} to {EOF_MAX_HISTORY} frames, the longest within "
            f"{EOF_REGRESSORS} regressors",
            "regularisation": "held-back telemetry",
            "modulus_margin": MODULUS_MARGIN,
        },
        options=("history", "regularisation"),
        design_with_details=_eof_details,
    )
)
