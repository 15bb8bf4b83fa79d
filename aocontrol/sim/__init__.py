"""Lightweight modal time-domain AO simulator (sim layer).

Imports from the control layer (plant, controllers, analysis), never from
:mod:`aocontrol.study`. Conventions: phase maps are optical path differences in nm on a
:class:`~aocontrol.sim.pupil.Pupil` grid, shape ``(..., n_pix, n_pix)``; modal coefficients in
nm RMS over the pupil; telemetry ``(n_frames, n_modes)``; randomness only through a passed
``numpy.random.Generator``.
"""

from aocontrol._deprecation import deprecated_names
from aocontrol.sim.atmosphere import Atmosphere, Layer
from aocontrol.sim.dm import SAXO_N_ACTUATORS, SAXO_PLUS_N_ACTUATORS, DeformableMirror, ModalDM
from aocontrol.sim.drift import Drift
from aocontrol.sim.loop import (
    CascadeResult,
    DiffractiveSensor,
    DitherGainTracker,
    LinearModalSensor,
    LoopDivergedError,
    LoopResult,
    ModalTimeSeries,
    PhaseSource,
    Stage,
    TurbulenceSource,
    run_cascade,
    run_loop,
)
from aocontrol.sim.modes import ModalBasis, fitting_error, kl_basis
from aocontrol.sim.noise import add_detector_noise, photons_per_frame, snr
from aocontrol.sim.profiles import (
    compress_profile,
    eso_atmosphere,
    eso_median_profile,
    scale_to_tau0,
)
from aocontrol.sim.pupil import Pupil, vlt_pupil
from aocontrol.sim.science import (
    LongExposure,
    ScienceCamera,
    ScienceResult,
    marechal_strehl,
    mean_contrast,
    opd_rms,
    opd_to_phase,
    radial_profile,
    strehl,
)
from aocontrol.sim.vibration import TiltVibration, VibrationPeak, VibrationPSD
from aocontrol.sim.wfs import (
    PyramidWFS,
    ShackHartmannWFS,
    WFSCalibration,
    calibrate,
    interaction_matrix,
    optical_gains,
    reconstructor,
)

__all__ = [
    "DiffractiveSensor",
    "DitherGainTracker",
    "Atmosphere",
    "Layer",
    "Drift",
    "eso_median_profile",
    "compress_profile",
    "scale_to_tau0",
    "eso_atmosphere",
    "LinearModalSensor",
    "LoopDivergedError",
    "LoopResult",
    "ModalTimeSeries",
    "Stage",
    "ModalDM",
    "TurbulenceSource",
    "run_loop",
    "run_cascade",
    "CascadeResult",
    "PhaseSource",
    "TiltVibration",
    "VibrationPSD",
    "VibrationPeak",
    "Pupil",
    "vlt_pupil",
    "DeformableMirror",
    "SAXO_N_ACTUATORS",
    "SAXO_PLUS_N_ACTUATORS",
    "ModalBasis",
    "kl_basis",
    "fitting_error",
    "ScienceCamera",
    "LongExposure",
    "ScienceResult",
    "opd_to_phase",
    "opd_rms",
    "marechal_strehl",
    "strehl",
    "radial_profile",
    "mean_contrast",
    "PyramidWFS",
    "ShackHartmannWFS",
    "WFSCalibration",
    "calibrate",
    "interaction_matrix",
    "reconstructor",
    "optical_gains",
    "photons_per_frame",
    "add_detector_noise",
    "snr",
]

#: Former names (with a ``DeprecationWarning``), removed in the release named.
__getattr__ = deprecated_names(
    __name__,
    {"LinearModalWFS": (LinearModalSensor, "aocontrol.sim.LinearModalSensor")},
    removed_in="0.2.0",
)
