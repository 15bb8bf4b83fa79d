"""Wavefront sensors: diffractive pyramid, Shack-Hartmann, calibration, the loop's sensors.

The diffractive models (:class:`PyramidWFS`, :class:`ShackHartmannWFS`, both
:class:`WavefrontSensor`: one interface, defined once) take OPD maps in nm on a
:class:`~aocontrol.sim.pupil.Pupil` grid and return signal vectors; they serve to calibrate
(interaction matrix, reconstructor, optical gains, noise propagation per mode) the
:class:`LinearModalSensor` that the fast modal loop uses (``measurement = gain * residual +
noise``), or run in the loop themselves as a :class:`DiffractiveSensor`. Both implement the one
sensor protocol (:class:`Sensor`, :mod:`aocontrol.sim.wfs.sensors`). ``LinearModalWFS`` is a
deprecated alias of :class:`LinearModalSensor` (removed in 0.2.0).
"""

from aocontrol._deprecation import module_aliases
from aocontrol.sim.wfs._sensor import WavefrontSensor
from aocontrol.sim.wfs.calibration import (
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
from aocontrol.sim.wfs.sensors import DiffractiveSensor, LinearModalSensor, Sensor, SensorRun
from aocontrol.sim.wfs.shack_hartmann import ShackHartmannWFS, shack_hartmann_calibration

__all__ = [
    "WavefrontSensor",
    "PyramidWFS",
    "ShackHartmannWFS",
    "shack_hartmann_calibration",
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
    "DiffractiveSensor",
    "Sensor",
    "SensorRun",
]


# LinearModalWFS: deprecated alias of LinearModalSensor (warns on use).
__getattr__ = module_aliases(
    __name__, {"LinearModalWFS": "aocontrol.sim.wfs.sensors:LinearModalSensor"}
)
