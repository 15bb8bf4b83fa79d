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

from aocontrol.controllers import load_controller
from aocontrol.plant import frequency_response, loop_plant, measured_plant

#: The one source of the version: pyproject.toml reads it (``[tool.setuptools.dynamic]``),
#: results files and saved controllers record it.
__version__ = "0.1.0"
__all__ = [
    "frequency_response",
    "loop_plant",
    "measured_plant",
    "load_controller",
    "load_result",
    "__version__",
]


def __getattr__(name: str):
    # load_result lives in the study layer: imported on first use so that importing
    # aocontrol (the control layer) does not import the simulator or the study layer.
    if name == "load_result":
        from aocontrol.study.results import load_result

        return load_result
    raise AttributeError(f"module 'aocontrol' has no attribute {name!r}")
