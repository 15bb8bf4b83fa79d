"""The runner of the simulator: the one chunked driver of one or two stages.

Each stage's per-frame state is a :class:`~aocontrol.sim._stage_run._StageRun` (see
:mod:`aocontrol.sim._stage_run`); :func:`drive` is the one chunked driver (chunks, progress,
the end-of-run checks, the controllers' reset) shared by :func:`run_loop` (one stage) and
:func:`~aocontrol.sim._cascade.run_cascade` (two stages on the fast clock), which differ only
in how a chunk's disturbance reaches the stages.

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
import os
from collections.abc import Callable
from typing import Any

import numpy as np

from aocontrol._blas import blas_threads
from aocontrol._validation import check_int
from aocontrol.sim._phase_maps import shape_synthesizer
from aocontrol.sim._result import TELEMETRY, LoopResult
from aocontrol.sim._sources import DisturbanceSource, check_rate
from aocontrol.sim._stage import Stage
from aocontrol.sim._stage_run import _StageRun
from aocontrol.sim.science import LongExposure

__all__ = ["run_loop", "drive", "engine_blas_threads", "ENV_BLAS_THREADS"]

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
