"""The per-mode designs of the data-driven synthesis on a Dask cluster (private).

:func:`aocontrol.synthesis.datadriven` designs its modes in fixed chunks of neighbouring modes
(:func:`aocontrol.synthesis._dd_mode.chunks`): in this process, on a joblib process pool, or,
here, as tasks of a ``distributed.Client``. The three paths run the same chunks through the
same function (``_dd_mode._design_chunk``, passed in), so every mode gets the same inputs and
the same start (within a chunk a mode may start from the previous mode's design; the first
mode of a chunk never does): the banks are bit for bit the same, whatever the path and the
number of workers.

Failures. A mode whose design fails numerically is reported for that mode inside its task
(as on the other paths) and the chunk's other modes are kept. A task that raises (rare: the
per-mode errors are caught inside it) is retried :data:`TASK_RETRIES` times; a worker lost
while running a task (killed, out of memory) makes the scheduler run the task again on another
worker (up to Dask's ``distributed.scheduler.allowed-failures``, 3 by default), so its modes
are designed once, from the start of their chunk: a chunk's result arrives whole or not at
all, never twice. A task that still fails leaves its chunk's modes failed, with the reason,
and the other chunks' modes designed (:class:`~aocontrol.synthesis.DataDrivenError`); a
programming error (``TypeError``, ``ImportError`` of a worker without aocontrol...) is raised,
as on the other paths.

Threads. A worker process designs one chunk at a time (the compiled convex problems and the
BLAS thread limit are per process): a worker's threads beyond the first wait. Give workers
one thread each and as many processes as cores (``dask worker --nthreads 1 --nworkers N``,
``LocalCluster(threads_per_worker=1)``).

Memory. :func:`task_memory` estimates a worker's peak while it designs a chunk, and
:func:`check_memory` refuses a call whose estimate exceeds the smallest worker memory limit
before anything is designed (``MemoryError`` giving both figures).
"""

from __future__ import annotations

import logging
import threading
import uuid
from collections.abc import Callable
from typing import Any

import numpy as np

from aocontrol._validation import is_programming_error
from aocontrol.synthesis._dd_context import DesignContext

logger = logging.getLogger(__name__)

#: Times a task that raised is run again (a lost worker's task is rescheduled by Dask itself).
TASK_RETRIES = 2
#: Seconds to wait for a first worker of a cluster that has none yet.
WORKER_WAIT_S = 10.0

# Memory of a worker designing a chunk [bytes], from the peak resident size (ru_maxrss) of a
# process designing one chunk of the synthetic bank of benchmarks/bench_design_scaleout.py
# (1 kHz, one frame of latency, order 5, 32 modes, one of them trying the bound start):
# 302 MB at 257 frequencies, 419 MB at 4,097, 784 MB at 16,385; orders 3 and 12 and 8 modes
# per chunk at 257 frequencies: 301-302 MB. The terms below cover these with room:
# - a process with numpy, scipy, cvxpy, control and distributed imported and the convex
#   problems compiled;
_WORKER_BASE = 400e6
# - per mode of a chunk and per input frequency: the PSDs (the task's copy, the worker's
#   unpickled copy, the per-mode weights) and the bound start's target [bytes];
_PER_MODE_FREQ = 64.0
# - per input frequency, once per chunk: the interpolation from the input grid to the design
#   grid (n_grid + 24 rows of float64) and the fine-grid residual of each mode's order check;
_PER_FREQ = 8.0 * 96
# - per dense-grid point and controller parameter: the dense grid's rows (two complex
#   matrices, up to four structures cached) and the certifier's copies;
_PER_DENSE_PARAM = 16.0 * 2 * 4 * 2
# - a chunk with a mode that tries the margin-constrained bound as its start
#   (``bound_start``): the bound's factorisations and cutting-plane solves (FIR Youla
#   parameter of ``_dd_starts.BOUND_TAPS`` = 256 taps; Clarabel called directly, nothing
#   compiled: 0.33 GB for the whole process of a three-line mode's design, measured, where
#   cvxpy's compilation took 4.1 GB above the worker's base before issue 34) plus the
#   bound's response matrices, per input frequency [bytes].
_BOUND_START = 0.2e9
_BOUND_PER_FREQ = 16.0 * 256 * 6


def task_memory(ctx: DesignContext, n_modes: int, bound_start: bool) -> int:
    """Estimated peak memory of a worker designing one chunk [bytes].

    ``400 MB + 64 B x n_modes x n_freqs + 768 B x n_freqs + 128 B x n_dense x (2 q + 1)``,
    with ``n_freqs`` the input frequencies, ``n_dense`` the dense grid's points (about 15x
    the design grid's; 6,200 for ``n_grid = 64``) and ``2 q + 1`` the controller's
    parameters (order ``q``, the largest of ``order="auto"``); plus, for a chunk with a mode
    that tries the margin-constrained bound as its start, 0.2 GB and ``24.6 kB x n_freqs``
    (the bound's solves at 256 taps, measured). An estimate from measured peaks
    (``benchmarks/bench_design_scaleout.py`` prints the workers' own), not a guarantee.

    Parameters
    ----------
    ctx : DesignContext
        The call's shared context (grids, order).
    n_modes : int
        Modes in the chunk.
    bound_start : bool
        Whether a mode of the chunk tries the bound start.

    Returns
    -------
    int
    """
    n_freqs = ctx.input_freqs.size
    order = max((ctx.free_order, *ctx.auto_orders))
    n_params = 2 * order + 1
    total = _WORKER_BASE + _PER_MODE_FREQ * n_modes * n_freqs + _PER_FREQ * n_freqs
    total += _PER_DENSE_PARAM * ctx.dense_freqs.size * n_params
    if bound_start:
        total += _BOUND_START + _BOUND_PER_FREQ * n_freqs
    return int(total)


def _gb(n: float) -> str:
    return f"{n / 1e9:.2f} GB"


def check_client(client: Any) -> dict:
    """The workers of a connected client (address -> their information), or a clear error.

    Waits up to :data:`WORKER_WAIT_S` for a first worker.

    Raises
    ------
    TypeError
        ``client`` is not a ``distributed.Client``.
    ConnectionError
        The client is not connected to a running scheduler, or the cluster has no worker.
    """
    from distributed import Client

    if not isinstance(client, Client):
        raise TypeError(
            "client must be a distributed.Client (e.g. distributed.Client('tcp://host:8786', "
            f"timeout=5)) or None, got {type(client).__name__}"
        )
    if client.status != "running":
        raise ConnectionError(
            f"client: not connected to a Dask scheduler (status {client.status!r}); nothing "
            "was designed"
        )
    try:
        client.wait_for_workers(1, timeout=WORKER_WAIT_S)
        workers = client.scheduler_info(n_workers=-1)["workers"]
    except (OSError, TimeoutError) as exc:
        raise ConnectionError(
            f"client: the Dask cluster at {client.scheduler.address} has no worker after "
            f"{WORKER_WAIT_S:g} s or does not answer ({type(exc).__name__}: {exc}); nothing "
            "was designed"
        ) from exc
    return workers


def check_memory(workers: dict, ctx: DesignContext, chunks: list) -> int:
    """Refuse chunks whose estimated memory exceeds the smallest worker memory limit.

    Returns the largest estimate over the chunks [bytes] (:func:`task_memory`). Workers
    without a limit (``memory_limit`` 0 or None) are not checked.

    Raises
    ------
    MemoryError
        Before anything is designed: the estimate, the chunk it is for and the limit.
    """
    need = [task_memory(ctx, len(c), any(item.bound_start for item in c)) for c in chunks]
    worst = int(np.argmax(need))
    limits = [w.get("memory_limit") or 0 for w in workers.values()]
    limits = [m for m in limits if m > 0]
    if limits and need[worst] > min(limits):
        modes = f"{chunks[worst][0].mode}-{chunks[worst][-1].mode}"
        bound = (
            " (a mode tries the margin-constrained bound as its start: bound_start=False "
            "avoids the bound's 0.2 GB)"
            if any(item.bound_start for item in chunks[worst])
            else ""
        )
        raise MemoryError(
            f"the data-driven design needs about {_gb(need[worst])} per Dask worker (modes "
            f"{modes}: {len(chunks[worst])} modes x {ctx.input_freqs.size} frequencies, "
            f"order {max((ctx.free_order, *ctx.auto_orders))}){bound}, more than the "
            f"smallest worker memory limit, {_gb(min(limits))}; nothing was designed: give "
            "the workers more memory (LocalCluster(memory_limit=...), dask worker "
            "--memory-limit) or fewer frequencies"
        )
    return need[worst]


# One chunk at a time per process: the compiled convex problems (``_socp``'s cache, whose
# parameters each solve sets) and the BLAS thread limit of ``_design_chunk`` are per process,
# so two threads of one worker designing at once would share them (measured: Clarabel's
# "Already mutably borrowed" on the second thread).
_PROCESS_LOCK = threading.Lock()


def _chunk_task(design: Callable, ctx: DesignContext, chunk: list) -> list:
    """One task: ``design(ctx, chunk)``, one chunk at a time in a worker process."""
    with _PROCESS_LOCK:
        return design(ctx, chunk)


def _failed(chunk: list, exc: BaseException) -> list:
    """Outcomes of a chunk whose task failed: every mode failed, with the reason."""
    reason = f"its Dask task failed ({type(exc).__name__}: {exc})"
    return [{"mode": item.mode, "error": reason, "bound_error": ""} for item in chunk]


def run_on_client(
    client: Any, design: Callable, ctx: DesignContext, chunks: list, bar: Any
) -> list:
    """``design(ctx, chunk)`` of every chunk as tasks of ``client``; the outcomes of every
    mode, in any order.

    ``design`` is ``_dd_mode._design_chunk`` (passed in: this module is below ``_dd_mode``);
    ``bar`` has ``update(n)`` (a tqdm bar or the no-op ``_dd_mode._Bar``).
    """
    from distributed import as_completed

    token = uuid.uuid4().hex[:12]
    futures = {
        client.submit(
            _chunk_task,
            design,
            ctx,
            chunk,
            key=f"datadriven-chunk-{k}-{token}",
            pure=False,
            retries=TASK_RETRIES,
        ): chunk
        for k, chunk in enumerate(chunks)
    }
    results: list = []
    try:
        for future in as_completed(futures):
            chunk = futures[future]
            if future.status == "finished":
                part = future.result()
            else:
                try:
                    exc = future.exception()
                except Exception as cancelled:  # a cancelled future has no exception to give
                    exc = cancelled
                if is_programming_error(exc):
                    raise exc
                logger.warning(
                    "modes %d-%d: their Dask task failed (%s: %s); the other chunks go on",
                    chunk[0].mode,
                    chunk[-1].mode,
                    type(exc).__name__,
                    exc,
                )
                part = _failed(chunk, exc)
            results.extend(part)
            bar.update(len(part))
    finally:
        client.cancel([f for f in futures if not f.done()])
    return results
