"""The runner of the simulator: per-frame state of a stage and the one chunked driver.

:class:`_StageRun` is the mutable per-run state created from a frozen
:class:`~aocontrol.sim._stage.Stage` (the sensor's run state, controller state, the plant's
delay line, DM saturation counters, the optical-gain tracker, telemetry buffers, statistics,
divergence guards); :meth:`_StageRun.step` advances one frame of the stage's own rate: the
sensor reads the residual of the previous frame through the sensor protocol
(:mod:`aocontrol.sim.wfs.sensors`, the same call for every kind of sensor), the controller
steps, the DM moves. :func:`drive` is the one chunked driver (chunks, progress, the end-of-run
checks, the controllers' reset) shared by :func:`run_loop` (one stage) and
:func:`~aocontrol.sim._cascade.run_cascade` (two stages on the fast clock), which differ only
in how a chunk's disturbance reaches the stages.

Linear stages (a linear modal sensor, no optical-gain tracker, no DM clip, an
:class:`~aocontrol.controllers.IIRBank` without a command limit) run the frames of a chunk in
one fused loop (:meth:`_StageRun.run_frames`): the same operations as :meth:`_StageRun.step`
frame after frame, bit for bit, compiled with numba (:mod:`aocontrol.sim._fused`) or,
without numba, in numpy.

BLAS threads (engine setting): :func:`drive` runs a whole run with at most
:func:`engine_blas_threads` BLAS threads, 1 by default. The engine's products are small
(a frame's vectors) or medium (a chunk's projection, ~100 ms): a multithreaded OpenBLAS
spends more CPU on them than it saves in wall time, and much more on a machine shared with
other jobs (the default chosen by ``benchmarks/bench_cascade.py``, ``docs/benchmarks.md``).
On a machine with idle cores where wall time matters more than CPU, set the environment variable
``AOCONTROL_ENGINE_BLAS_THREADS`` to a number of threads, or to ``0`` to leave the BLAS's
own setting. The thread count changes the rounding of float32 products (the projection):
runs are reproducible for one setting, and agree across settings to the projection's
rounding (see :mod:`aocontrol.sim._projection`).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable
from typing import Any

import numpy as np

from aocontrol._validation import check_int
from aocontrol.controllers import IIRBank
from aocontrol.plant import z_inverse_coefficients
from aocontrol.sim import _fused
from aocontrol.sim._blas import blas_threads
from aocontrol.sim._phase_maps import shape_synthesizer
from aocontrol.sim._result import TELEMETRY, LoopDivergedError, LoopResult
from aocontrol.sim._sources import DisturbanceSource, check_rate
from aocontrol.sim._stage import Stage
from aocontrol.sim.science import LongExposure
from aocontrol.sim.wfs.sensors import LinearModalSensor

__all__ = ["run_loop", "drive", "engine_blas_threads", "ENV_BLAS_THREADS"]

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


#: Environment variable: BLAS threads of a run (module docstring); ``0`` leaves the BLAS's own.
ENV_BLAS_THREADS = "AOCONTROL_ENGINE_BLAS_THREADS"
_DEFAULT_BLAS_THREADS = 1


def engine_blas_threads() -> int | None:
    """BLAS threads of a run (``$AOCONTROL_ENGINE_BLAS_THREADS``, default 1), or ``None``.

    Returns
    -------
    int or None
        The limit :func:`drive` sets while a run goes; ``None`` (the variable set to ``0``)
        leaves the BLAS's own number of threads.

    Raises
    ------
    ValueError
        If the variable is not a whole number >= 0.
    """
    raw = os.environ.get(ENV_BLAS_THREADS)
    if raw is None:
        return _DEFAULT_BLAS_THREADS
    try:
        value = int(raw.strip())
    except ValueError:
        value = -1
    if value < 0:
        raise ValueError(
            f"${ENV_BLAS_THREADS} must be a whole number of threads >= 0 (0: the BLAS's own "
            f"setting), got {raw!r}"
        )
    return value or None


def closed_loop_pole_radius(stage: Stage, optical_gain: np.ndarray) -> np.ndarray | None:
    """Largest closed-loop pole modulus per mode of a linear stage, or ``None``.

    The loop of :func:`aocontrol.loop_plant` with the stage's latency, the sensor's optical
    gain and the controller's linear part (an :class:`~aocontrol.controllers.IIRBank`'s
    coefficients, else every mode's ``transfer_function``): the characteristic polynomial
    ``A_k + og B_g B_k`` in powers of ``z^-1``, roots from batched companion matrices.
    ``None`` when the controller has no transfer function. With model errors
    (:mod:`aocontrol.sim.model_errors`): the DM's response in the plant, each mode's own
    part of a mixing (its coupling to the others is not in a per-mode check), a drifting
    optical gain at both ends of its modulation.

    Parameters
    ----------
    stage : Stage
        Stage to check.
    optical_gain : ndarray (n_modes,)
        Sensor optical gains.

    Returns
    -------
    ndarray (n_modes,) or None
    """
    ctrl = stage.controller
    coeffs = _controller_coefficients(ctrl)
    if coeffs is None:
        return None
    k0, frac = stage.delay
    bg = np.zeros(k0 + 3)
    bg[k0 + 1] = 1.0 - frac
    bg[k0 + 2] = frac
    ah = np.array([1.0])
    gain = np.asarray(optical_gain, dtype=float)
    dm = stage.dm
    if dm.response is not None:  # the true plant is G H (aocontrol.sim.model_errors)
        bh, ah = dm.response.coefficients(stage.fs)
        bg = np.convolve(bg, bh)
    if dm.mixing is not None:  # per mode: the diagonal of the mixing (the coupling apart)
        gain = gain * np.diag(dm.mixing)
    err = stage.optical_gain_error
    if err is None:
        return _radius(coeffs, bg, ah, gain)
    # Drifting gains: the loop at both ends of the modulation (a frozen-gain check).
    factors = np.broadcast_to(err.factor, (ctrl.n_modes,))
    return np.maximum(
        _radius(coeffs, bg, ah, gain * factors * (1.0 - err.drift)),
        _radius(coeffs, bg, ah, gain * factors * (1.0 + err.drift)),
    )


def _radius(coeffs: tuple, bg: np.ndarray, ah: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Largest root modulus per mode of ``A_k A_h + gain B_g B_k`` (powers of ``z^-1``)."""
    b, a = coeffs
    n = a.shape[0]
    length = max(a.shape[1] + ah.size - 1, bg.size + b.shape[1] - 1)
    char = np.zeros((n, length))
    # A_k A_h and B_g B_k per mode (shared A_h, B_g): convolutions as sums of shifted copies.
    for i, h in enumerate(ah):
        if h:
            char[:, i : i + a.shape[1]] += h * a
    for i, g in enumerate(bg):
        if g:
            char[:, i : i + b.shape[1]] += (gain * g)[:, None] * b
    # Trim trailing zero columns (common to every mode) and normalise.
    nz = np.flatnonzero(np.any(char != 0, axis=0))
    char = char[:, : nz[-1] + 1] / char[:, :1]
    order = char.shape[1] - 1
    if order == 0:
        return np.zeros(n)
    comp = np.zeros((n, order, order))
    comp[:, 0, :] = -char[:, 1:]
    if order > 1:
        idx = np.arange(order - 1)
        comp[:, idx + 1, idx] = 1.0
    return np.abs(np.linalg.eigvals(comp)).max(axis=1)


def _controller_coefficients(ctrl: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """``(b, a)`` in powers of ``z^-1``, shape ``(n_modes, n)``, of a linear controller bank.

    From the coefficients of an :class:`IIRBank`, else from ``transfer_function(mode)`` of
    every mode; ``None`` when the controller has no (causal, finite) transfer function.
    """
    if isinstance(ctrl, IIRBank):
        return ctrl.b, ctrl.a
    try:
        pairs = [z_inverse_coefficients(ctrl.transfer_function(i)) for i in range(ctrl.n_modes)]
    except (NotImplementedError, TypeError, ValueError, ArithmeticError) as exc:
        logger.info("no closed-loop pole check for %s: %s", type(ctrl).__name__, exc)
        return None
    bank = IIRBank.from_rows([bi for bi, _ in pairs], [ai for _, ai in pairs], ctrl.fs)
    return bank.b, bank.a


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


def _check_common(
    n_frames: int, chunk: int, science_every: int, record: tuple[str, ...]
) -> tuple[int, int, int]:
    n_frames = check_int("n_frames", n_frames, minimum=1)
    chunk = check_int("chunk", chunk, minimum=1)
    science_every = check_int("science_every", science_every, minimum=1)
    bad = set(record) - set(TELEMETRY)
    if bad:
        raise ValueError(f"record must be a subset of {TELEMETRY}, got unknown {sorted(bad)}")
    return n_frames, chunk, science_every


def _settle(n_frames: int, settle_frames: int | None) -> int:
    settle = (
        max(20, n_frames // 100)
        if settle_frames is None
        else check_int("settle_frames", settle_frames, minimum=0)
    )
    if settle >= n_frames:
        raise ValueError(f"settle_frames={settle} must be < n_frames={n_frames}")
    return settle


def _check_finite_disturbance(d: np.ndarray, first: int, what: str = "disturbance") -> None:
    if not np.all(np.isfinite(d)):
        bad = ~np.isfinite(d)
        frame = first + int(np.flatnonzero(bad.any(axis=1))[0])
        modes = np.flatnonzero(bad.any(axis=0))
        raise ValueError(
            f"the {what} is not finite (NaN or inf) at frame {frame}, modes "
            f"{modes[:10].tolist()}{' ...' if modes.size > 10 else ''}: check the disturbance "
            "source (this is not a diverging loop)"
        )


class _ResidualMap:
    """The residual OPD map of the last frame, formed only when a sensor asks (callable).

    ``set(form, *args)`` after each frame (references only); calling the object returns
    ``pupil.to_map(form(*args))`` (valid pupil pixels to the map), or the flat map before the
    first frame.
    """

    def __init__(self, pupil: Any, n_valid: int) -> None:
        self.pupil = pupil
        self.n_valid = n_valid
        self.form: Callable[..., np.ndarray] | None = None
        self.args: tuple = ()

    def set(self, form: Callable[..., np.ndarray], *args: Any) -> None:
        self.form = form
        self.args = args

    def __call__(self) -> np.ndarray:
        if self.form is None:
            return self.pupil.to_map(np.zeros(self.n_valid))
        return self.pupil.to_map(self.form(*self.args))


def drive(
    n_frames: int,
    chunk: int,
    advance: Callable[[int, int], None],
    runs: tuple[_StageRun, ...],
    *,
    progress: bool = False,
    desc: str = "loop",
) -> None:
    """The one chunked driver: ``advance(first, m)`` for chunks of ``m <= chunk`` frames.

    Shows a progress bar when asked, runs the chunks with at most
    :func:`engine_blas_threads` BLAS threads, runs the end-of-run checks of every stage
    (:meth:`_StageRun.finish`) and resets every stage's controller, also on an error.

    Parameters
    ----------
    n_frames : int
        Frames of the driving clock.
    chunk : int
        Frames per call of ``advance``.
    advance : callable ``(first, m) -> None``
        Runs frames ``first ... first + m - 1``.
    runs : tuple of _StageRun
        The stages' run states.
    progress : bool
        Show a tqdm progress bar.
    desc : str
        Label of the progress bar.
    """
    threads = engine_blas_threads()
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_frames, desc=desc, unit="frame")
    k = 0
    limit = contextlib.nullcontext() if threads is None else blas_threads(threads)
    try:
        with limit:  # the engine's BLAS threads (module docstring)
            while k < n_frames:
                m = min(chunk, n_frames - k)
                advance(k, m)
                k += m
                if bar is not None:
                    bar.update(m)
        for run in runs:
            run.finish()
    finally:
        if bar is not None:
            bar.close()
        for run in runs:
            run.stage.controller.reset()


def science_frames(first: int, m: int, settle: int, every: int) -> np.ndarray:
    """Chunk rows (of frames ``first ... first + m - 1``) that feed the science camera: every
    ``every``-th frame of the clock, once settled."""
    frames = first + np.arange(m)
    return np.flatnonzero((frames >= settle) & (frames % every == 0))


def run_loop(
    stage: Stage,
    disturbance: DisturbanceSource,
    n_frames: int,
    *,
    rng: np.random.Generator | int | None = None,
    science: Any = None,
    basis: Any = None,
    science_every: int = 10,
    record: tuple[str, ...] = TELEMETRY,
    settle_frames: int | None = None,
    chunk: int = 1000,
    progress: bool = False,
    metadata: dict | None = None,
) -> LoopResult:
    """Run one AO stage in closed loop for ``n_frames`` frames.

    Parameters
    ----------
    stage : Stage
        The stage (controller, sensor, latency, DM stroke).
    disturbance : DisturbanceSource
        Modal disturbance (and phase maps when a science camera is used), at the stage's rate
        ``fs`` (checked when the source has a rate).
    n_frames : int
        Frames to run.
    rng : numpy.random.Generator or int
        Source of the measurement noise and of an optical-gain tracker's dither (required
        when the sensor is noisy or the stage tracks its optical gains).
    science : object with ``add(maps (n, n_pix, n_pix))`` and ``result()``, optional
        Long-exposure accumulator; fed every ``science_every`` frames with the residual phase
        ``phase - DM shape`` (needs ``basis`` and phase maps from the source).
    basis : object with ``synthesize(coeffs) -> (..., n_valid)`` and ``pupil``, optional
        Default ``stage.basis``. Needed for the science camera and for a sensor that reads
        phase maps (a :class:`~aocontrol.sim.wfs.DiffractiveSensor`, which measures the
        residual map ``phase - DM shape`` of every frame).
    science_every : int
        Frames between two science frames.
    record : tuple of str
        Telemetry to keep (float32), among ``disturbance, measurements, commands, dm,
        residuals``. Statistics are computed regardless.
    settle_frames : int, optional
        Frames excluded from the statistics (default: 1% of the run, at least 20).
    chunk : int
        Frames generated at once (memory vs. speed).
    progress : bool
        Show a tqdm progress bar.
    metadata : dict, optional
        Case/controller settings stored with the result.

    Returns
    -------
    LoopResult

    Raises
    ------
    LoopDivergedError
        If a residual blows up or grows steadily, or the linear closed loop of a mode is
        unstable (unstable controller), naming the stage, the frame and the modes.
    ValueError
        Bad arguments, a disturbance at another rate than the stage, or a disturbance that
        is not finite (named as such, with the frame and modes).
    """
    n_frames, chunk, science_every = _check_common(n_frames, chunk, science_every, record)
    if not isinstance(disturbance, DisturbanceSource):
        raise TypeError("disturbance must provide n_modes and next(n_frames)")
    n = stage.n_modes
    if disturbance.n_modes != n:
        raise ValueError(f"disturbance has {disturbance.n_modes} modes, the controller {n}")
    check_rate(disturbance, stage.fs, f"stage {stage.name!r}", required=False)
    basis = stage.basis if basis is None else basis
    if science is not None and basis is None:
        raise ValueError("a science camera needs basis= to form the DM shape")
    if basis is not None and stage.basis is None:
        stage.sensor.check(n, basis)
    run = _StageRun(
        stage,
        n_frames=n_frames,
        record=record,
        settle=0,
        rng=np.random.default_rng(rng),
        pupil=None if basis is None else basis.pupil,
    )
    if rng is None and (run.noisy or run.tracker is not None):
        raise ValueError(
            "rng is required with a noisy sensor or an optical-gain tracker (reproducibility)"
        )
    if run.needs_phase and basis is None:
        raise ValueError(
            "a sensor that reads phase maps (a DiffractiveSensor) needs basis= (or the "
            "stage's basis) to form the residual phase map"
        )
    settle = run.settle = _settle(n_frames, settle_frames)
    resid = None if basis is None else _ResidualMap(basis.pupil, basis.pupil.n_valid)
    synth = None if not run.needs_phase else shape_synthesizer(basis)

    def form(phase: np.ndarray, y: np.ndarray) -> np.ndarray:
        return phase - synth(y)  # float32 DM shape (aocontrol.sim._phase_maps)

    def advance(first: int, m_chunk: int) -> None:
        d, maps = disturbance.next(m_chunk)
        d = np.asarray(d, dtype=float)
        _check_finite_disturbance(d, first)
        if (science is not None or run.needs_phase) and maps is None:
            raise ValueError(
                "the disturbance source gives no phase maps (needed by the science camera "
                "and a sensor that reads phase maps)"
            )
        run.begin_chunk(d, m_chunk)
        if maps is not None and resid is not None and run.needs_phase:
            for j in range(m_chunk):
                y = run.step(j, d[j], resid)
                resid.set(form, maps[j], y)  # references only: the map formed if asked
        else:
            run.run_frames(d, resid)
        ys = run.chunk_dm  # the chunk's DM shapes (m_chunk, n)
        run.end_chunk(d, first)
        if science is not None:
            idx = science_frames(first, m_chunk, settle, science_every)
            if idx.size:
                res = maps[idx] - basis.synthesize(ys[idx])
                # The camera reads valid-pixel vectors as they are (no map round trip).
                science.add(res if isinstance(science, LongExposure) else basis.pupil.to_map(res))

    drive(n_frames, chunk, advance, (run,), progress=progress, desc=f"{stage.name} loop")
    result_science = science.result() if science is not None else None
    return run.result(stage.fs, n_frames, n_frames - settle, result_science, metadata)
