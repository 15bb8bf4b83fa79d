"""aocontrol: adaptive-optics control toolbox.

Layers (imports point down only)::

    study     cases, compare, sweep, cli, plot          (aocontrol.study)
    sim       atmosphere, modes, WFS, DM, loop, science (aocontrol.sim)
    control   plant, controllers, synthesis, analysis,  (aocontrol.plant, .controllers,
              io (AOT telemetry, RTC export)             .synthesis, .analysis, .io)

Conventions: discrete time at ``fs`` [Hz]; public frequencies in Hz; one-sided PSDs
[units^2/Hz] (``scipy.signal.welch`` density); wavefronts as optical path in nm; modal
telemetry shaped ``(n_frames, n_modes)``; randomness only through a passed
``numpy.random.Generator`` or seed.
"""

from aocontrol._deprecation import module_aliases
from aocontrol._version import __version__
from aocontrol.controllers import load_controller
from aocontrol.plant import frequency_response, loop_plant, measured_plant

__all__ = [
    "frequency_response",
    "loop_plant",
    "measured_plant",
    "load_controller",
    "__version__",
]

# load_result lives in the study layer (results files of simulator runs): reached from there,
# so that the top package imports nothing above the control layer.
__getattr__ = module_aliases("aocontrol", {"load_result": "aocontrol.study.results:load_result"})
