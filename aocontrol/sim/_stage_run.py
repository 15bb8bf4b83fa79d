"""The per-frame state of one stage during one run (private to the simulator's engine).

:class:`_StageRun` is the mutable per-run state created from a frozen
:class:`~aocontrol.sim._stage.Stage` (the sensor's run state, controller state, the plant's
delay line, DM saturation counters, the optical-gain tracker, telemetry buffers, statistics,
divergence guards); :meth:`_StageRun.step` advances one frame of the stage's own rate: the
sensor reads the residual of the previous frame through the sensor protocol
(:mod:`aocontrol.sim.wfs.sensors`, the same call for every kind of sensor), the controller
steps, the DM moves. The driver (:func:`aocontrol.sim._runner.drive`) runs the chunks.

Linear stages (a linear modal sensor, no optical-gain tracker, no DM clip, an
:class:`~aocontrol.controllers.IIRBank` without a command limit) run the frames of a chunk in
one fused loop (:meth:`_StageRun.run_frames`): the same operations as :meth:`_StageRun.step`
frame after frame, bit for bit, compiled with numba (:mod:`aocontrol.sim._fused`) or,
without numba, in numpy.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from aocontrol.controllers import IIRBank
from aocontrol.sim import _fused
from aocontrol.sim._closed_loop import closed_loop_pole_radius
from aocontrol.sim._result import LoopDivergedError, LoopResult
from aocontrol.sim._stage import Stage
from aocontrol.sim.wfs.sensors import LinearModalSensor

logger = logging.getLogger(__name__)

# A residual larger than this factor times the largest disturbance of any mode (or 10 sigma
# of the measurement noise, plus 1 nm) seen so far is taken as a diverging loop.
_DIVERGENCE_FACTOR = 1e3
# Same guard for the modes whose linear closed loop is unstable (pole outside the unit
# circle, checked before the run): they are known to diverge, so a residual 10 x the
# disturbance scale already proves it.
_UNSTABLE_FACTOR = 10.0
# Closed-loop pole radius above which a mode is linearly unstable (rounding of the
# eigenvalues of a companion matrix of a few dozen coefficients: ~1e-12).
_POLE_RADIUS_TOL = 1e-9
# Sustained growth, for loops the pole check cannot see (a controller without a transfer
# function): per mode, the ratio q of the residual energy to the disturbance-plus-noise
# energy over a chunk of the stage's frames. A stable loop keeps q below max |S|^2 (a few;
# ~11 for a modulus margin of 0.3) whatever the disturbance does; a diverging one makes q
# grow without bound. Reported when q grew by more than _GROWTH_FACTOR in each of
# _GROWTH_CHUNKS successive chunks and exceeds _GROWTH_RATIO.
_GROWTH_FACTOR = 2.0
_GROWTH_CHUNKS = 3
_GROWTH_RATIO = 30.0


class _StageRun:
    """Mutable state of one stage during one run (created by the runner from a Stage)."""

    def __init__(
        self,
        stage: Stage,
        *,
        n_frames: int,
        record: tuple[str, ...],
        settle: int,
        rng: np.random.Generator,
        pupil: Any = None,
        accumulate: bool = True,
    ) -> None:
        n = stage.n_modes
        self.stage = stage
        self.name = stage.name
        self.n = n
        self.ctrl = stage.controller
        self.k0, self.frac = stage.delay
        self.w0 = 1.0 - self.frac  # weight of the newer command in the delay line
        self.depth = self.k0 + 2
        self.hist = np.zeros((self.depth, n))  # ring buffer of commands, hist[k % depth]
        self.dm = stage.dm
        self.dm_state = self.dm.new_state(stage.fs)
        self.clip = self.dm.limited
        # Model errors (aocontrol.sim.model_errors): the mirror's response and mixing, the
        # sensor's true optical gains; none of them costs a nominal run anything.
        self.dm_dynamic = self.dm.dynamic
        self.og_error = stage.optical_gain_error
        self.fs = stage.fs
        self.record = record
        self.tele = {name: np.empty((n_frames, n), dtype=np.float32) for name in record}
        self.settle = settle
        self.accumulate = accumulate
        self.sum_e2 = np.zeros(n)
        self.sum_d2 = np.zeros(n)
        self.dmax = np.zeros(n)
        # The sensor's run state (sensor protocol): the one call per frame for every kind.
        self.sensor = stage.sensor.start(n, rng, pupil)
        self.needs_phase = bool(self.sensor.needs_phase)
        optical_gain = np.asarray(self.sensor.optical_gain, dtype=float)
        noise_std = np.asarray(self.sensor.noise_std, dtype=float)
        self.noisy = bool(np.any(noise_std > 0))
        self.tracker = (
            None if stage.gain_tracker is None else stage.gain_tracker.start(n, rng.spawn(1)[0])
        )
        self.e_prev = np.zeros(n)
        self.og = optical_gain
        self.noise_std = noise_std
        self.noise_scale = 10.0 * float(np.max(noise_std / optical_gain))
        self.noise_energy = (noise_std / optical_gain) ** 2
        self.k = 0
        self.limit = self.limit_unstable = self.limit_check = np.inf
        self.out: dict[str, np.ndarray] = {}
        self.out_m = self.out_u = self.out_y = self.out_e = None
        self.chunk_dm: np.ndarray | None = None
        self.energy: list[np.ndarray] = []
        radius = closed_loop_pole_radius(stage, optical_gain)
        self.radius = radius
        self.unstable = (
            np.zeros(n, dtype=bool) if radius is None else radius > 1.0 + _POLE_RADIUS_TOL
        )
        if self.unstable.any():
            logger.warning(
                "%s: the linear closed loop is unstable for modes %s (pole radius up to %.6g)",
                self.name,
                np.flatnonzero(self.unstable)[:10].tolist(),
                float(radius.max()),
            )
        self.ctrl.reset()
        # The frames of a chunk in one fused loop (run_frames): a linear sensor, no tracker,
        # no DM clip, a controller whose step is the plain IIR recursion.
        self.fusable = (
            type(stage.sensor) is LinearModalSensor  # its run: og e_prev + noise per chunk
            and self.tracker is None
            and not self.clip
            and not self.dm_dynamic
            and self.og_error is None
            and isinstance(self.ctrl, IIRBank)
            and self.ctrl._recursion_state() is not None
        )

    # -- chunk bookkeeping ------------------------------------------------------------------
    def begin_chunk(self, d: np.ndarray, m_chunk: int) -> None:
        """Update the divergence scale with the chunk's disturbance ``(m_chunk, n)``."""
        np.maximum(self.dmax, np.abs(d).max(axis=0), out=self.dmax)
        # Scale of a healthy residual: the largest disturbance or noise (through T) of any
        # mode (modes couple through stroke clipping and diffractive sensing).
        scale = self.dmax.max() + self.noise_scale
        self.sensor.begin_chunk(m_chunk)
        if self.tracker is not None:
            self.tracker.begin_chunk(m_chunk)
        self.limit = _DIVERGENCE_FACTOR * scale + 1.0
        self.limit_unstable = _UNSTABLE_FACTOR * scale + 1.0
        self.out = {
            name: np.empty((m_chunk, self.n)) for name in self.record if name != "disturbance"
        }
        self.out_m = self.out.get("measurements")
        self.out_u = self.out.get("commands")
        # The DM shapes and residuals are always kept for the chunk: the frames write their
        # rows in place (no per-frame copies), the statistics are computed per chunk and
        # ``chunk_dm`` holds the chunk's DM shapes for the caller (science).
        self.out_y = self.out.get("dm")
        if self.out_y is None:
            self.out_y = np.empty((m_chunk, self.n))
        self.chunk_dm = self.out_y
        self.out_e = self.out.get("residuals")
        if self.out_e is None:
            self.out_e = np.empty((m_chunk, self.n))
        # The per-frame check compares the residual energy with the smallest guard squared:
        # below it every mode is within the guard; above it the modes are checked one by one.
        limit = self.limit_unstable if self.unstable.any() else self.limit
        self.limit_check = limit * limit

    def end_chunk(self, d_rec: np.ndarray, first: int) -> None:
        """Store the chunk's telemetry (frames ``first...``), accumulate the statistics and
        check for sustained growth."""
        m = d_rec.shape[0]
        stop = first + m
        for name in self.record:
            self.tele[name][first:stop] = d_rec if name == "disturbance" else self.out[name]
        e = self.out_e[:m]
        start = max(self.settle - first, 0)
        if self.accumulate and start < m:
            self.sum_e2 = _sequential_sum(self.sum_e2, e[start:] ** 2)
            self.sum_d2 = _sequential_sum(self.sum_d2, d_rec[start:] ** 2)
        # Sustained growth of the residual relative to its input (see _GROWTH_FACTOR).
        e_energy = np.einsum("ij,ij->j", e, e)
        d_energy = np.einsum("ij,ij->j", d_rec, d_rec) + m * self.noise_energy + 1e-300
        self.energy.append(e_energy / d_energy)
        if len(self.energy) > _GROWTH_CHUNKS:
            q = np.array(self.energy[-_GROWTH_CHUNKS - 1 :])
            growing = np.all(q[1:] > _GROWTH_FACTOR * q[:-1], axis=0) & (q[-1] > _GROWTH_RATIO)
            if growing.any():
                raise LoopDivergedError(
                    self.k - 1,
                    np.flatnonzero(growing),
                    self.name,
                    f"grew relative to the disturbance by more than {_GROWTH_FACTOR:g}x in each "
                    f"of {_GROWTH_CHUNKS} successive chunks, to {float(q[-1].max()):.3g} x its "
                    "energy (sustained growth, a slowly diverging loop)",
                )
            del self.energy[0]

    # -- the frames of a chunk -------------------------------------------------------------
    def run_frames(
        self,
        d: np.ndarray,
        opd: Callable[[], np.ndarray],
        r: np.ndarray | None = None,
        offset: np.ndarray | None = None,
    ) -> None:
        """Frames ``0 ... len(d) - 1`` of the chunk, for a sensor that reads no map.

        The same as :meth:`step` frame after frame (``d``, ``r`` and ``offset`` give one row
        per frame); a linear stage (:attr:`fusable`) runs in one fused loop
        (:func:`aocontrol.sim._fused.run_chunk`), with the same values bit for bit.
        """
        if self.fusable and _fused.run_chunk(self, d if r is None else r, offset):
            return
        step = self.step
        for j in range(d.shape[0]):
            step(j, d[j], opd, None if r is None else r[j], None if offset is None else offset[j])

    # -- one frame of the stage's rate --------------------------------------------------------
    def step(
        self,
        j: int,
        d_j: np.ndarray,
        opd: Callable[[], np.ndarray],
        r_j: np.ndarray | None = None,
        offset: np.ndarray | None = None,
    ) -> np.ndarray:
        """Frame ``j`` of the chunk: the sensor reads the previous residual (``opd()`` forms
        its map on demand), then :meth:`frame`; returns the DM shape ``y``."""
        if self.og_error is None:
            m = self.sensor.read(j, self.e_prev, opd)
        else:
            # The true gains at this frame's time: on the signal of a modal sensor, on the
            # measurement of one that reads maps (a compensation error).
            g = self.og_error.gains(self.k / self.fs, self.n)
            if self.needs_phase:
                m = self.sensor.read(j, self.e_prev, opd) * g
            else:
                m = self.sensor.read(j, self.e_prev * g, opd)
        if self.tracker is not None:
            self.tracker.observe(m)
            m = m / self.tracker.gain
        self.e_prev, y = self.frame(m, d_j, j, r_j, offset)
        return y

    def frame(
        self,
        m: np.ndarray,
        d_j: np.ndarray,
        j: int,
        r_j: np.ndarray | None = None,
        offset: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Controller step, DM, residual of one frame; returns ``(e, y)``.

        ``d_j`` is the recorded disturbance; the residual is ``(r_j or d_j) - y`` with ``y``
        the DM shape: the delay line of the commands plus ``offset`` (dCAO), clipped by the
        DM (before the delay line without offset, on the total shape with one).
        """
        u = self.ctrl.step(m)
        if self.clip and offset is None:
            u = self.dm.clip(u, self.dm_state)
        k = self.k
        hist, depth = self.hist, self.depth
        hist[k % depth] = u
        # The DM shape and the residual are written in place in the chunk's rows: same
        # operations, in the same order, as ``y = w0 h[k - k0] + frac h[k - k0 - 1]``.
        y = self.out_y[j]
        if self.frac:
            np.multiply(hist[(k - self.k0) % depth], self.w0, out=y)
            y += self.frac * hist[(k - self.k0 - 1) % depth]
        else:
            y[...] = hist[(k - self.k0) % depth]
        if self.tracker is not None:  # the dither: an offset of the mirror (_gain_tracking)
            y += self.tracker.dither(j)
        if offset is not None:
            y += offset
            if self.clip:
                y[...] = self.dm.clip(y, self.dm_state)
        if self.dm_dynamic:
            self.dm.respond(y, self.dm_state)
        e = np.subtract(d_j if r_j is None else r_j, y, out=self.out_e[j])
        # One reduction per frame (NaN fails the comparison and is caught here too).
        if not e @ e < self.limit_check:
            self._diverged(k, np.abs(e))
        if self.out_m is not None:
            self.out_m[j] = m
        if self.out_u is not None:
            self.out_u[j] = u
        self.k = k + 1
        return e, y

    def _diverged(self, k: int, ae: np.ndarray) -> None:
        """Raise if a guard is exceeded (``ae`` the residual magnitudes of frame ``k``)."""
        if not np.all(ae < self.limit):
            raise LoopDivergedError(k, np.flatnonzero(~(ae < self.limit)), self.name)
        bad = self.unstable & ~(ae < self.limit_unstable)
        if bad.any():
            raise LoopDivergedError(
                k,
                np.flatnonzero(bad),
                self.name,
                f"exceeds {_UNSTABLE_FACTOR:g} x the disturbance and the linear closed "
                f"loop is unstable (pole radius {float(self.radius[bad].max()):.6g} > 1)",
            )

    def finish(self) -> None:
        """After the last frame: keep the controller's counters (the runner resets the
        controller), then report a linearly unstable mode that never tripped a guard."""
        self.controller_counters = controller_counters(self.ctrl)
        if self.unstable.any():
            raise LoopDivergedError(
                self.k - 1,
                np.flatnonzero(self.unstable),
                self.name,
                "stayed below the divergence guards, but the linear closed loop is unstable "
                f"(pole radius {float(self.radius.max()):.6g} > 1): a slowly diverging loop "
                "(or one held by the stroke); its statistics would be meaningless",
            )

    def result(
        self,
        fs: float,
        n_frames: int,
        n_stat: int,
        science: Any,
        metadata: dict | None,
    ) -> LoopResult:
        st = self.dm_state
        if st.saturation.any():
            logger.info("%s: DM saturated in %d mode-frames", self.name, int(st.saturation.sum()))
        return LoopResult(
            fs=fs,
            n_frames=n_frames,
            telemetry=self.tele,
            residual_variance=self.sum_e2 / n_stat,
            disturbance_variance=self.sum_d2 / n_stat,
            saturation=st.saturation,
            settle_frames=self.settle,
            science=science,
            metadata=dict(
                metadata or {},
                stage=self.name,
                latency_frames=self.stage.latency_frames,
                controller=repr(self.ctrl),
                controller_counters=getattr(self, "controller_counters", {}),
                **({} if self.tracker is None else self.tracker.metadata()),
            ),
            actuator_saturation=st.actuator_saturation,
        )


#: Counters a controller bank may keep, summed over modes into the result's metadata before
#: the runner resets the controller: frames rejected for a non-finite measurement (every bank),
#: clipped commands (IIRBank, LQGBank), QP solves and solver failures (MPCBank).
CONTROLLER_COUNTERS = ("n_rejected", "n_saturated", "n_solves", "n_solver_failures")


def controller_counters(ctrl: Any) -> dict[str, int]:
    """The counters of :data:`CONTROLLER_COUNTERS` that ``ctrl`` has, summed over modes."""
    out = {}
    for name in CONTROLLER_COUNTERS:
        value = getattr(ctrl, name, None)
        if value is not None:
            out[name] = int(np.sum(value))
    return out


def _sequential_sum(total: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``total + rows[0] + rows[1] + ...`` added row after row (as a per-frame ``+=``).

    A reduction along the first (outer) axis of a C-ordered array adds the rows in order,
    element by element (numpy's pairwise summation applies along the contiguous axis only):
    bit-identical to the per-frame sum (tested), and cheaper than ``cumsum``.
    """
    stacked = np.concatenate([total[None], rows])
    return np.add.reduce(stacked, axis=0)
