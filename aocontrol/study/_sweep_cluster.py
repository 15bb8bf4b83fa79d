"""The Dask side of a sweep (private to :mod:`aocontrol.study.sweep`): the local cluster, its
workers' BLAS threads and environment, the connection to a scheduler, Dask's logging kept quiet.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator, Mapping
from typing import Any

# Thread-count variables of the BLAS and OpenMP libraries numpy and scipy may use.
_BLAS_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# ... and the cores joblib may use in a worker (``joblib.cpu_count`` reads it): the process
# pools of the syntheses and fits inside a run take the worker's share, not every core.
_WORKER_VARS = (*_BLAS_VARS, "LOKY_MAX_CPU_COUNT")


#: Loggers of the Dask machinery kept quiet around a sweep's own local cluster.
_DASK_LOGGERS = ("distributed", "tornado", "asyncio")


def _set_levels(levels: Mapping[str, int]) -> dict[str, int]:
    """Set logger levels; return the previous ones."""
    old = {}
    for name, level in levels.items():
        log = logging.getLogger(name)
        old[name] = log.level
        log.setLevel(level)
    return old


def blas_threads_per_worker(n_workers: int) -> int:
    """BLAS/OpenMP threads of each local worker process: the cores shared among the workers.

    One thread per worker when the cluster has as many workers as cores (or more): two
    processes each running a multi-threaded BLAS on two cores slow each other down.

    Parameters
    ----------
    n_workers : int
        Worker processes of the local cluster.
    """
    return max(1, (os.cpu_count() or 1) // n_workers)


def _verbose() -> bool:
    """aocontrol logs at INFO (``aocontrol -v``): Dask's messages are shown too."""
    return logging.getLogger("aocontrol").isEnabledFor(logging.INFO)


@contextlib.contextmanager
def local_cluster(n_workers: int = 2) -> Iterator[Any]:
    """The local Dask cluster of :func:`run_sweep` (also for running several sweeps on one).

    ``n_workers`` processes of one thread, without work stealing (runs stay on the worker
    holding their case's scene), each with :func:`blas_threads_per_worker` BLAS threads (set
    in its environment before it starts, so that numpy's BLAS reads it; ``OMP_NUM_THREADS``,
    ``OPENBLAS_NUM_THREADS`` or ``MKL_NUM_THREADS`` set in this process's environment take
    precedence). ``LOKY_MAX_CPU_COUNT`` is set to the same share, so that a data-driven
    synthesis or a disturbance fit inside a run (``n_jobs=None``: ``joblib.cpu_count()``
    processes) uses the worker's cores instead of starting one process per core in every
    worker. Dask's default ``MALLOC_TRIM_THRESHOLD_`` is not set (it makes every large array
    a fresh ``mmap``: page faults) and the workers' statistical profiler is off. Unless
    aocontrol logs at INFO (``aocontrol -v``), Dask's own INFO messages (scheduler, nannies,
    connections) are not shown and the shutdown, after every result is in, is silent (a
    worker slow to exit is killed by its nanny: harmless then).

    Parameters
    ----------
    n_workers : int, default 2
        Worker processes.

    Yields
    ------
    distributed.LocalCluster
    """
    import dask
    from distributed import LocalCluster

    verbose = _verbose()
    threads = str(blas_threads_per_worker(n_workers))
    config = {
        # The whole pre-spawn environment, replacing Dask's default, whose
        # MALLOC_TRIM_THRESHOLD_ turns off glibc's adaptive mmap threshold: every array above
        # 128 KiB is then a fresh mmap, page-faulted in and unmapped again (measured: twice the
        # CPU of a quick run in a worker, a third of it system time).
        "distributed.nanny.pre-spawn-environ": dict.fromkeys(_WORKER_VARS, threads),
        "distributed.scheduler.work-stealing": False,
        # the statistical profiler samples the running task's stack every 10 ms (unused here)
        "distributed.worker.profile.enabled": False,
    }
    old = None if verbose else _set_levels(dict.fromkeys(_DASK_LOGGERS, logging.WARNING))
    # Dask's nannies copy these variables into this process's environment before spawning;
    # restored once the workers run, so that this process's environment stays the user's
    # (and a variable the user set explicitly keeps precedence, as Dask documents).
    saved_env = {v: os.environ.get(v) for v in _WORKER_VARS}
    try:
        with (
            dask.config.set(config),
            LocalCluster(
                n_workers=n_workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                # no dashboard; the scheduler's HTTP endpoints on a free local port (the
                # default 8787 may be taken: Dask then warns on stderr)
                scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                silence_logs=logging.WARNING if verbose else logging.CRITICAL,
            ) as cluster,
        ):
            _restore_env(saved_env)
            try:
                yield cluster
            finally:
                if not verbose:
                    _set_levels(dict.fromkeys(_DASK_LOGGERS, logging.CRITICAL + 1))
    finally:
        _restore_env(saved_env)
        if old is not None:
            _set_levels(old)


def _restore_env(saved: Mapping[str, str | None]) -> None:
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


def _connect(scheduler: Any, n_workers: int, timeout: float, stack: Any) -> Any:
    """A client of the scheduler at ``scheduler`` or of a new :func:`local_cluster`.

    Closed in order: the client, then the cluster (the shutdown silent, see local_cluster).
    """
    from distributed import Client

    if scheduler is None:
        cluster = stack.enter_context(local_cluster(n_workers))
        client = stack.enter_context(Client(cluster))
        if not _verbose():  # runs first on exit: the client's closing is silent too
            stack.callback(_set_levels, dict.fromkeys(_DASK_LOGGERS, logging.CRITICAL + 1))
        return client
    if isinstance(scheduler, Client):
        return scheduler
    if not isinstance(scheduler, str) or not scheduler:
        raise TypeError(
            f"scheduler must be None, an address string or a distributed.Client, got {scheduler!r}"
        )
    try:
        client = Client(scheduler, timeout=timeout)
    except (OSError, TimeoutError) as exc:
        raise ConnectionError(
            f"scheduler={scheduler!r}: no Dask scheduler answered within {timeout:g} s "
            f"({type(exc).__name__}: {exc}); start one with `dask scheduler` or leave scheduler "
            "unset for a local cluster"
        ) from exc
    return stack.enter_context(client)
