"""Lightweight modal time-domain AO simulator (sim layer).

Imports from the control layer (plant, controllers, analysis), never from
:mod:`aocontrol.study`. Conventions: phase maps are optical path differences in nm on a
:class:`~aocontrol.sim.pupil.Pupil` grid, shape ``(..., n_pix, n_pix)``; modal coefficients in
nm RMS over the pupil; telemetry ``(n_frames, n_modes)``; randomness only through a passed
``numpy.random.Generator``.
"""

from aocontrol.sim.loop import (
    LinearModalSensor,
    LoopDivergedError,
    LoopResult,
    ModalTimeSeries,
    Stage,
    TurbulenceSource,
    run_loop,
)
from aocontrol.sim.pupil import Pupil, vlt_pupil

__all__ = [
    "LinearModalSensor",
    "LoopDivergedError",
    "LoopResult",
    "ModalTimeSeries",
    "Stage",
    "TurbulenceSource",
    "run_loop",
    "Pupil",
    "vlt_pupil"]
