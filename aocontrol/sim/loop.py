"""Modal time-domain AO loops with the control layer's timing: one stage or a two-stage cascade.

Timing of one stage (the plant of :func:`aocontrol.loop_plant`, so that the simulator's
rejection equals ``|S|^2`` of :mod:`aocontrol.analysis`): at frame ``k`` of the stage's rate

1. the WFS delivers ``m[k] = og * e[k-1] + n[k]`` (integration of the previous frame; a
   diffractive sensor measures the residual phase map of frame ``k-1`` instead, through the
   one sensor protocol of :mod:`aocontrol.sim.wfs.sensors`);
2. the controller computes ``u[k] = K(m)[k]`` (its own ``command_limit`` included, if any);
3. the DM applies ``y[k] = (1 - f) u[k - k0] + f u[k - k0 - 1]`` with
   ``(k0, f) = aocontrol.plant.split_latency(latency_frames)`` (linear interpolation of the
   commands, as COMPASS), the command clipped by the stage's DM
   (:class:`aocontrol.sim.dm.ModalDM`, the one owner of the stroke);
4. the residual is ``e[k] = d[k] - y[k]``.

Everything is modal (nm RMS per mode, shape ``(n_modes,)``) and vectorised over modes; the
only Python loop is over frames. Phase maps (nm OPD) are formed only for the frames that feed
the science camera: ``residual_map = phase[k] - DM shape``, which keeps the fitting error.

Engine: a frozen :class:`Stage` is the configuration (controller, sensor, basis, latency, DM
with its stroke, optional optical-gain tracker :class:`DitherGainTracker`); the runner creates
the per-run state (the sensor's run state, controller state, delay line, DM counters,
telemetry) and advances it one frame of the stage's rate. One chunked driver serves :func:`run_loop`
(one stage) and :func:`run_cascade` (two stages on the fast clock, stage 2's rate an integer
multiple of stage 1's, in the ``standalone`` or ``dcao`` scheme). A run uses at most
:func:`engine_blas_threads` BLAS threads (1 by default; ``$AOCONTROL_ENGINE_BLAS_THREADS``).
"""

from aocontrol.sim._cascade import UpstreamRecord, projection_matrix, run_cascade
from aocontrol.sim._closed_loop import closed_loop_pole_radius
from aocontrol.sim._gain_tracking import DitherGainTracker
from aocontrol.sim._result import TELEMETRY, CascadeResult, LoopDivergedError, LoopResult
from aocontrol.sim._runner import ENV_BLAS_THREADS, engine_blas_threads, run_loop
from aocontrol.sim._sources import (
    DisturbanceSource,
    ModalTimeSeries,
    PhaseDisturbance,
    PhaseSource,
    TurbulenceSource,
)
from aocontrol.sim._stage import DiffractiveSensor, Sensor, Stage
from aocontrol.sim.wfs.sensors import LinearModalSensor

__all__ = [
    "DisturbanceSource",
    "PhaseDisturbance",
    "ModalTimeSeries",
    "TurbulenceSource",
    "PhaseSource",
    "LinearModalSensor",
    "DiffractiveSensor",
    "Sensor",
    "Stage",
    "DitherGainTracker",
    "LoopResult",
    "CascadeResult",
    "LoopDivergedError",
    "TELEMETRY",
    "closed_loop_pole_radius",
    "engine_blas_threads",
    "ENV_BLAS_THREADS",
    "projection_matrix",
    "run_loop",
    "run_cascade",
    "UpstreamRecord",
]
