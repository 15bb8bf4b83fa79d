"""Controller synthesis: optimised modal gains, disturbance estimation from telemetry, the
data-driven controller, LQG and MPC, the multi-mode (EOF) predictor, the controller registry
and the telemetry-to-design pipeline (:func:`design_from_telemetry`).

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
PSDs are one-sided [units^2/Hz]; telemetry is shaped ``(n_frames, n_modes)``.
"""

from aocontrol.synthesis._arfit import fit_disturbance_model
from aocontrol.synthesis._armodel import DisturbanceModel, ar2_variance
from aocontrol.synthesis._datadriven import (
    GRID_DISAGREEMENT,
    DataDrivenError,
    DataDrivenResult,
    GridResolutionWarning,
    InitialPoleRadiusError,
    ModeReport,
    datadriven,
)
from aocontrol.synthesis._dd_assemble import REJECTED_WORSE
from aocontrol.synthesis._dd_neighbours import datadriven_neighbours, has_integrator
from aocontrol.synthesis._design_report import TelemetryDesign
from aocontrol.synthesis._eof import (
    REGULARISATION_GRID,
    EOFNotCertifiedError,
    EOFResult,
    eof_from_pseudo_open_loop,
    eof_min_frames,
    eof_predictor,
)
from aocontrol.synthesis._loop_check import (
    SCALE_LIMIT,
    SIGN_TOLERANCE,
    LoopTelemetryCheck,
    TelemetryCheckError,
    check_loop_telemetry,
)
from aocontrol.synthesis._lqg import lqg, lqg_from_telemetry, lqg_state_space, plant_latency
from aocontrol.synthesis._modal_gain import (
    ModalGainError,
    integrator_gain_limit,
    optimal_modal_gain,
)
from aocontrol.synthesis._mpc import mpc
from aocontrol.synthesis._pipeline import BOUNDS, design_from_telemetry
from aocontrol.synthesis._registry import (
    CONTROLLER_ALIASES,
    CONTROLLERS,
    EOF_HISTORY,
    EOF_MAX_HISTORY,
    EOF_REGRESSORS,
    MODULUS_MARGIN,
    MPC_HORIZON,
    ROBUST_SET,
    ControllerSpec,
    DesignInputs,
    controller_names,
    eof_default_history,
    get_controller,
    register_controller,
)
from aocontrol.synthesis._sensor_error import (
    SensorErrorPSD,
    sensor_error_psd,
    split_sensor_error,
)
from aocontrol.synthesis._telemetry import (
    ESTIMATORS,
    LoopTelemetry,
    TelemetryPSD,
    default_nperseg,
    disturbance_from_telemetry,
    pseudo_open_loop,
)

__all__ = [
    "BOUNDS",
    "REJECTED_WORSE",
    "CONTROLLERS",
    "CONTROLLER_ALIASES",
    "controller_names",
    "get_controller",
    "ControllerSpec",
    "DesignInputs",
    "ESTIMATORS",
    "SensorErrorPSD",
    "sensor_error_psd",
    "split_sensor_error",
    "LoopTelemetry",
    "LoopTelemetryCheck",
    "SCALE_LIMIT",
    "SIGN_TOLERANCE",
    "TelemetryCheckError",
    "check_loop_telemetry",
    "MODULUS_MARGIN",
    "EOF_HISTORY",
    "EOF_MAX_HISTORY",
    "EOF_REGRESSORS",
    "eof_default_history",
    "MPC_HORIZON",
    "ROBUST_SET",
    "default_nperseg",
    "design_from_telemetry",
    "register_controller",
    "DataDrivenError",
    "DataDrivenResult",
    "DisturbanceModel",
    "GRID_DISAGREEMENT",
    "GridResolutionWarning",
    "EOFNotCertifiedError",
    "EOFResult",
    "REGULARISATION_GRID",
    "eof_from_pseudo_open_loop",
    "eof_min_frames",
    "eof_predictor",
    "InitialPoleRadiusError",
    "ModalGainError",
    "ModeReport",
    "TelemetryDesign",
    "TelemetryPSD",
    "ar2_variance",
    "datadriven",
    "datadriven_neighbours",
    "has_integrator",
    "disturbance_from_telemetry",
    "fit_disturbance_model",
    "integrator_gain_limit",
    "lqg",
    "lqg_from_telemetry",
    "lqg_state_space",
    "mpc",
    "optimal_modal_gain",
    "plant_latency",
    "pseudo_open_loop",
]
