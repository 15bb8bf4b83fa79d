"""Wavefront sensors: diffractive pyramid, Shack-Hartmann, calibration, linear modal model.

The diffractive models (:class:`PyramidWFS`, :class:`ShackHartmannWFS`) take OPD maps in nm on
a :class:`~aocontrol.sim.pupil.Pupil` grid and return signal vectors; they serve to calibrate
(interaction matrix, reconstructor, optical gains, noise propagation per mode) the
:class:`LinearModalSensor` (alias ``LinearModalWFS``) that the fast modal loop uses:
``measurement = gain * residual + noise``.
"""

from aocontrol.sim.wfs.calibration import (
    LinearModalSensor,
    LinearModalWFS,
    WFSCalibration,
    calibrate,
    fitting_residual_screens,
    interaction_matrix,
    noise_propagation,
    optical_gains,
    reconstructor,
    white_noise_propagation,
)
from aocontrol.sim.wfs.pyramid import PyramidWFS, default_modulation_points
from aocontrol.sim.wfs.shack_hartmann import ShackHartmannWFS

__all__ = [
    "PyramidWFS",
    "ShackHartmannWFS",
    "default_modulation_points",
    "interaction_matrix",
    "reconstructor",
    "optical_gains",
    "noise_propagation",
    "white_noise_propagation",
    "fitting_residual_screens",
    "calibrate",
    "WFSCalibration",
    "LinearModalSensor",
    "LinearModalWFS",
]
