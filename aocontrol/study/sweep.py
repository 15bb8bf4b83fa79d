"""Parameter sweeps on ``dask.distributed``: many runs, one self-describing file each, resumable.

A sweep spec (TOML) lists cases x controllers x schemes x seeds, optional overrides (each key a
list of values; the sweep takes every combination), the simulated ``seconds`` per run and
``quick``::

    cases = ["bright1-best", "red5-best"]
    controllers = ["integrator", "datadriven"]
    schemes = ["standalone", "dcao"]
    seeds = [0, 1]
    seconds = 1.0
    quick = false

    [overrides]
    seeing = [0.6, 0.8]
    "stage2.fs" = [1250, 3000]

The spec is validated completely before any run starts: an unknown key, a wrong type, an unknown
case, controller or scheme, or an override the case does not have fails with a
:class:`SweepSpecError` that names the file, the key and the valid values.

Each run is described by a settings dict ``{case, controller, scheme, seed, seconds, quick,
overrides}``; its file is ``<hash>.h5`` with ``hash`` = the first 16 hex digits of the SHA-256
of the settings as sorted, compact JSON (floats with an integral value hashed as integers, so
``1250`` and ``1250.0`` name the same run). The hash identifies the *request*: a changed case
file or a new software version does not rename its runs; sweep into a new folder then.

Execution: every run whose file is missing is submitted to a Dask cluster (a ``LocalCluster``
of 2 processes with 1 thread each by default, each with its share of the cores as BLAS threads,
or the scheduler at ``scheduler=``; a remote cluster's workers must see ``out`` on a shared file
system). The *worker* writes the result in
``out/.partial/`` and renames it to ``out/<hash>.h5`` when complete, so a file with a final name
is always complete and a killed sweep loses at most the runs in flight; run it again and it
skips what exists. A run that raises leaves ``out/<hash>.error.json`` (settings, error,
traceback) instead of a result, and the other runs go on. The first run of a case whose
calibrations are not yet on disk builds them on a worker of its own where possible (each worker
process caches the scenes it builds in memory; their calibrations are also cached on disk,
:mod:`aocontrol.study._cache`, so that a scene built by one worker or an earlier sweep is read,
not built again); the case's other runs are submitted once that run is done, to any worker
(never one that would wait for the build); the runs of cases on disk are balanced over the
workers by their expected work (fast frames of the run, a scene loaded from disk;
:mod:`aocontrol.study._sweep_place`), each preferably on a worker that holds its scene in
memory. :attr:`SweepReport.timings` gives
each run's worker, wall and CPU time. Start one sweep per folder at a time:
a sweep clears ``out/.partial/`` (files of interrupted sweeps) first.

The sweep's table (:func:`sweep_table`, one row per file, also written to
``out/summary.csv``) is rebuilt from the files alone. (It was ``summary_table``, a name it
shared with :func:`aocontrol.study.results.summary_table`, which takes a list of files: that
name here is deprecated.)
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import os
import pathlib
import shutil
import socket
import sys
import time
import traceback
import uuid
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from aocontrol._atomic import atomic_path
from aocontrol._deprecation import deprecated_function
from aocontrol.study._cache import process_usage
from aocontrol.study._sweep_place import _after_builds, _run_placement
from aocontrol.study._sweep_spec import (
    _HASH_LEN,
    _NAME_KEYS,
    SPEC_KEYS,  # noqa: F401  (re-exported: the keys of a spec file)
    SweepRun,
    SweepSpec,
    SweepSpecError,
    _canonical,
    _fail,
    _names,
    run_hash,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = [
    "SweepSpec",
    "SweepSpecError",
    "SweepRun",
    "SweepRunner",
    "SweepReport",
    "load_sweep_spec",
    "run_hash",
    "run_sweep",
    "sweep_table",
    "summary_table",
    "default_runner",
    "blas_threads_per_worker",
    "local_cluster",
]

logger = logging.getLogger(__name__)

#: Sub-folder of ``out`` holding the files of runs in flight.
PARTIAL_DIR = ".partial"
#: Seconds to wait for a scheduler at ``scheduler=`` before failing.
CONNECT_TIMEOUT_S = 5.0
# Thread-count variables of the BLAS and OpenMP libraries numpy and scipy may use.
_BLAS_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# ... and the cores joblib may use in a worker (``joblib.cpu_count`` reads it): the process
# pools of the syntheses and fits inside a run take the worker's share, not every core.
_WORKER_VARS = (*_BLAS_VARS, "LOKY_MAX_CPU_COUNT")


# ------------------------------------------------------------------------------------ runners
@dataclass(frozen=True)
class SweepRunner:
    """What a sweep calls: the run itself, the reader of its file and the valid names.

    Parameters
    ----------
    run : callable ``(settings: dict, path: pathlib.Path) -> None``
        Runs one configuration and writes its result file at ``path`` (any format the
        ``read`` callable understands). Must be importable by the workers (a module-level
        function or an instance of a module-level class).
    read : callable ``(path: pathlib.Path) -> dict``
        One summary row from a result file: ``{"settings": <the run's settings dict>, ...
        figures of merit}``.
    valid : mapping, optional
        Valid names per spec key (``"cases"``, ``"controllers"``, ``"schemes"``); a key that is
        absent is not checked.
    check : callable ``(settings: dict) -> None``, optional
        Raises ``ValueError`` for a run that cannot work (e.g. an override the case lacks);
        called on every run before any starts.
    """

    run: Callable[[dict, pathlib.Path], None]
    read: Callable[[pathlib.Path], dict]
    valid: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    check: Callable[[dict], None] | None = None

    def __post_init__(self) -> None:
        for name in ("run", "read"):
            if not callable(getattr(self, name)):
                raise TypeError(f"{name} must be callable, got {getattr(self, name)!r}")
        if self.check is not None and not callable(self.check):
            raise TypeError(f"check must be callable or None, got {self.check!r}")
        bad = set(self.valid) - set(_NAME_KEYS)
        if bad:
            raise ValueError(f"valid keys must be among {sorted(_NAME_KEYS)}, got {sorted(bad)}")


def _run_configuration_and_save(settings: dict, path: pathlib.Path) -> None:
    """Default run: :func:`aocontrol.study.compare.run_configuration` + ``save_result``."""
    from aocontrol.study.compare import run_configuration
    from aocontrol.study.results import save_result

    outcome = run_configuration(
        settings["case"],
        controller=settings["controller"],
        scheme=settings["scheme"],
        seconds=settings["seconds"],
        seed=settings["seed"],
        overrides=dict(settings["overrides"]) or None,
        quick=settings["quick"],
        progress=False,
    )
    full = dict(outcome.settings)
    full["sweep"] = {"hash": run_hash(settings), "request": settings}
    save_result(outcome.result, path, settings=full)


#: Columns of a results file's summary row kept in the sweep's table (E1's results module).
_RESULT_FIGURES = ("strehl", "mean_contrast_4_6", "residual_rms_nm", "fs", "n_frames")


def _read_result_row(path: pathlib.Path) -> dict:
    """Default read: the run's request (stored by the sweep) and its figures of merit."""
    from aocontrol.study.results import read_settings
    from aocontrol.study.results import summary_table as file_rows

    settings = read_settings(path)
    request = settings.get("sweep", {}).get("request")
    if request is None:  # a results file written outside a sweep
        request = {
            k: settings[k] for k in ("case", "controller", "scheme", "seed") if k in settings
        }
    row = file_rows([path])[0]
    return {"settings": request, **{k: row[k] for k in _RESULT_FIGURES if k in row}}


def _check_run(settings: dict) -> None:
    """Default check: the case loads and takes the overrides (before any run starts)."""
    from aocontrol.study.cases import apply_overrides, load_case

    apply_overrides(load_case(settings["case"]), dict(settings["overrides"]) or None)


def default_runner() -> SweepRunner:
    """The real runner: ``run_configuration`` of the case comparison, HDF5 results files.

    Returns
    -------
    SweepRunner
        Valid names from :func:`aocontrol.study.cases.list_cases`, the controller registry and
        the schemes of :mod:`aocontrol.study.compare`; every run's overrides are checked with
        :func:`aocontrol.study.cases.apply_overrides` before any run starts.
    """
    from aocontrol.study import compare
    from aocontrol.study.cases import list_cases

    valid = {
        "cases": tuple(list_cases()),
        "controllers": compare.controller_names(),
        "schemes": tuple(compare.SCHEMES),
    }
    return SweepRunner(
        run=_run_configuration_and_save, read=_read_result_row, valid=valid, check=_check_run
    )


def load_sweep_spec(
    path: str | os.PathLike, *, runner: SweepRunner | None = None
) -> tuple[SweepSpec, tuple[SweepRun, ...]]:
    """Read and validate a sweep spec file completely (before any run starts).

    Parameters
    ----------
    path : str or path-like
        TOML file (module docstring).
    runner : SweepRunner, optional
        Supplies the valid names and the per-run check; default :func:`default_runner`.

    Returns
    -------
    spec : SweepSpec
    runs : tuple of SweepRun
        Every run of the spec.

    Raises
    ------
    SweepSpecError
        Unreadable file, TOML syntax error, unknown key, wrong type, unknown name, or a run
        that the runner's check rejects; the message names the file and the key.
    """
    path = pathlib.Path(path)
    source = str(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise SweepSpecError(f"{source}: cannot read the sweep spec: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise SweepSpecError(f"{source}: not valid TOML: {exc}") from exc
    spec = SweepSpec.from_dict(data, source=source)
    return spec, _validated_runs(spec, runner or default_runner())


def _validated_runs(spec: SweepSpec, runner: SweepRunner) -> tuple[SweepRun, ...]:
    for key in _NAME_KEYS:
        if key in runner.valid:
            _names(spec.source, key, getattr(spec, key), runner.valid[key])
    runs = spec.runs()
    if runner.check is not None:
        for run in runs:
            try:
                runner.check(dict(run.settings))
            except (ValueError, TypeError, KeyError) as exc:
                s = run.settings
                raise _fail(
                    spec.source,
                    "overrides" if s["overrides"] else "cases",
                    f"run case={s['case']!r} controller={s['controller']!r} "
                    f"scheme={s['scheme']!r} overrides={s['overrides']} is invalid: {exc}",
                ) from exc
    return runs


# ------------------------------------------------------------------------------------ execution
def _write_json_atomic(path: pathlib.Path, data: dict) -> None:
    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        json.dump(data, fh, indent=1, sort_keys=True, default=str)


def _error_record(settings: Mapping, hash_: str, exc: BaseException, where: str) -> dict:
    return {
        "hash": hash_,
        "settings": dict(settings),
        "error_type": type(exc).__name__,
        "error": str(exc),
        "traceback": "".join(traceback.format_exception(exc)),
        "where": where,
    }


def _execute(
    run: Callable[[dict, pathlib.Path], None], settings: dict, hash_: str, out: str
) -> dict:
    """Worker side of one run: write to ``.partial/``, rename when complete, or record the error."""
    out_dir = pathlib.Path(out)
    final = out_dir / f"{hash_}.h5"
    if final.exists():
        return {"hash": hash_, "status": "skipped", "seconds": 0.0}
    partial = out_dir / PARTIAL_DIR
    partial.mkdir(parents=True, exist_ok=True)
    tmp = partial / f"{hash_}.{uuid.uuid4().hex}.h5"
    error_file = out_dir / f"{hash_}.error.json"
    t0, c0, u0 = time.perf_counter(), time.process_time(), process_usage()
    th0 = time.thread_time()
    try:
        run(dict(settings), tmp)
        if not tmp.is_file():
            raise RuntimeError(f"the runner returned without writing its result file {tmp}")
        os.replace(tmp, final)
    except Exception as exc:  # one failing run never stops the others
        tmp.unlink(missing_ok=True)
        _write_json_atomic(error_file, _error_record(settings, hash_, exc, "worker"))
        return {"hash": hash_, "status": "failed", "error": f"{type(exc).__name__}: {exc}"}
    error_file.unlink(missing_ok=True)
    return {
        "hash": hash_,
        "status": "done",
        "seconds": time.perf_counter() - t0,
        # CPU of the worker process over the run (its every thread), and which process ran it
        "cpu_s": time.process_time() - c0,
        "worker": f"{socket.gethostname()}:{os.getpid()}",
        # the run's own thread (the rest of cpu_s: BLAS threads, Dask's event loop)
        "thread_cpu_s": time.thread_time() - th0,
        "parts": {k: v - u0[k] for k, v in process_usage().items()},
    }


@dataclass(frozen=True)
class SweepReport:
    """What a sweep did.

    Parameters
    ----------
    out : pathlib.Path
        Results folder.
    ran, skipped : tuple of str
        Hashes of the runs executed now / found complete.
    failed : tuple of (str, str)
        ``(hash, error)`` of the runs that raised (``<hash>.error.json`` has the details).
    table : tuple of dict
        :func:`sweep_table` of the folder after the sweep.
    wall_s : float
        Wall-clock time of the sweep [s], cluster start-up included.
    timings : tuple of dict
        Per run executed now, in completion order: ``hash``, ``worker`` (``host:pid`` of the
        process that ran it), ``seconds`` (wall) and ``cpu_s`` (that process's CPU over the
        run, every thread) [s]: the load balance of the sweep (``bench_sweep`` prints it);
        ``thread_cpu_s`` (the CPU of the thread that ran it, a part of ``cpu_s``); ``parts``:
        what the run spent in the calibration cache and the kernel's counts
        (``aocontrol.study._cache.process_usage``, differences over the run).
    """

    out: pathlib.Path
    ran: tuple[str, ...]
    skipped: tuple[str, ...]
    failed: tuple[tuple[str, str], ...]
    table: tuple[dict, ...]
    wall_s: float
    timings: tuple[dict, ...] = ()


#: What :attr:`SweepReport.timings` keeps of a worker's status of a completed run.
_TIMING_KEYS = ("hash", "worker", "seconds", "cpu_s", "thread_cpu_s", "parts")

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


def _clear_partial(out: pathlib.Path) -> None:
    partial = out / PARTIAL_DIR
    if partial.is_dir():
        stale = list(partial.iterdir())
        if stale:
            logger.info("removing %d temporary file(s) of an interrupted sweep", len(stale))
        shutil.rmtree(partial)


def run_sweep(
    spec: str | os.PathLike | SweepSpec,
    *,
    out: str | os.PathLike,
    scheduler: Any = None,
    runner: SweepRunner | None = None,
    n_workers: int = 2,
    progress: bool = False,
    timeout: float = CONNECT_TIMEOUT_S,
) -> SweepReport:
    """Run every missing run of a sweep on Dask and rebuild the summary table.

    Parameters
    ----------
    spec : path or SweepSpec
        Sweep spec file (validated completely first) or a spec object.
    out : path
        Results folder (created): ``<hash>.h5`` per run, ``<hash>.error.json`` per failure,
        ``summary.csv``. With a remote scheduler the workers must see it.
    scheduler : str or distributed.Client, optional
        Address of a running scheduler (``"tcp://host:8786"``) or a client; default a
        ``LocalCluster`` of ``n_workers`` processes with one thread each.
    runner : SweepRunner, optional
        Default :func:`default_runner` (the case comparison's ``run_configuration``).
    n_workers : int, default 2
        Processes of the local cluster (ignored with ``scheduler``).
    progress : bool, default False
        Show a tqdm progress bar over the runs (completion order).
    timeout : float, default 5.0
        Seconds to wait for the scheduler at ``scheduler``.

    Returns
    -------
    SweepReport

    Raises
    ------
    SweepSpecError
        Invalid spec (before anything runs).
    ConnectionError
        No scheduler at ``scheduler`` within ``timeout`` seconds.
    """
    t0 = time.perf_counter()
    runner = runner or default_runner()
    if isinstance(spec, SweepSpec):
        runs = _validated_runs(spec, runner)
    else:
        spec, runs = load_sweep_spec(spec, runner=runner)
    if isinstance(n_workers, bool) or not isinstance(n_workers, int) or n_workers < 1:
        raise ValueError(f"n_workers must be an integer >= 1, got {n_workers!r}")
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    _clear_partial(out)
    todo = [r for r in runs if not (out / f"{r.hash}.h5").exists()]
    skipped = [r.hash for r in runs if (out / f"{r.hash}.h5").exists()]
    logger.info(
        "sweep %s: %d runs, %d present, %d to run", spec.source, len(runs), len(skipped), len(todo)
    )
    ran: list[str] = []
    failed: list[tuple[str, str]] = []
    timings: list[dict] = []
    if todo:
        from contextlib import ExitStack

        from distributed import as_completed

        with ExitStack() as stack:
            client = _connect(scheduler, n_workers, timeout, stack)
            token = uuid.uuid4().hex[:8]
            placement = _run_placement(client, todo)
            later = _after_builds(todo)
            held = {r.hash for runs in later.values() for r in runs}

            def submit(r: SweepRun, where: str | None) -> Any:
                return client.submit(
                    _execute,
                    runner.run,
                    dict(r.settings),
                    r.hash,
                    str(out.resolve()),
                    key=f"aocontrol-run-{r.hash}-{token}",
                    pure=False,
                    retries=0,
                    # (a restriction only with affinity: Dask refuses allow_other_workers alone)
                    **({"workers": [where], "allow_other_workers": True} if where else {}),
                )

            futures = {submit(r, placement.get(r.hash)): r for r in todo if r.hash not in held}
            bar = None
            if progress:
                from tqdm.auto import tqdm

                bar = stack.enter_context(tqdm(total=len(todo), desc="sweep", unit="run"))
            done = as_completed(futures)
            for fut in done:
                r = futures[fut]
                # the case's calibrations are built (or its build failed): its other runs
                # go to any worker
                for other in later.pop(r.hash, ()):
                    new = submit(other, None)
                    futures[new] = other
                    done.add(new)
                try:
                    status = fut.result()
                except Exception as exc:  # the worker died (killed, out of memory)
                    record = _error_record(r.settings, r.hash, exc, "scheduler")
                    _write_json_atomic(out / f"{r.hash}.error.json", record)
                    status = {"hash": r.hash, "status": "failed", "error": record["error"]}
                if status["status"] == "failed":
                    failed.append((r.hash, status["error"]))
                    logger.warning("run %s failed: %s", r.hash, status["error"])
                elif status["status"] == "skipped":
                    skipped.append(r.hash)
                else:
                    ran.append(r.hash)
                    timings.append({k: status.get(k) for k in _TIMING_KEYS})
                    logger.info("run %s done in %.1f s", r.hash, status["seconds"])
                if bar is not None:
                    bar.update(1)
    partial = out / PARTIAL_DIR
    if partial.is_dir() and not any(partial.iterdir()):
        partial.rmdir()
    table = sweep_table(out, runner=runner)
    return SweepReport(
        out=out,
        ran=tuple(ran),
        skipped=tuple(skipped),
        failed=tuple(failed),
        table=tuple(table),
        wall_s=time.perf_counter() - t0,
        timings=tuple(timings),
    )


# ------------------------------------------------------------------------------------ summary
def _flat_item(prefix: str, key: str, value: Any, row: dict) -> None:
    name = f"{prefix}{key}"
    if isinstance(value, Mapping):
        for k, v in value.items():
            _flat_item(f"{name}.", k, v, row)
    elif isinstance(value, list | tuple):
        row[name] = json.dumps(_canonical(value))
    else:
        row[name] = value


_FIRST = ("hash", "status", "case", "controller", "scheme", "seed", "seconds", "quick")


@deprecated_function(
    "aocontrol.study.sweep.summary_table",
    "sweep_table(out) of aocontrol.study.sweep (the name summary_table belongs to "
    "aocontrol.study.results.summary_table(paths))",
)
def summary_table(
    out: str | os.PathLike,
    *,
    runner: SweepRunner | None = None,
    csv_path: str | os.PathLike | None = "summary.csv",
) -> list[dict]:
    """Deprecated name of :func:`sweep_table` (same arguments, same rows).

    :func:`aocontrol.study.results.summary_table` (a list of files) keeps the name.

    Parameters
    ----------
    out : path
        Results folder of a sweep.
    runner : SweepRunner, optional
        As in :func:`sweep_table`.
    csv_path : path or None, default "summary.csv"
        As in :func:`sweep_table`.

    Returns
    -------
    list of dict

    Warns
    -----
    DeprecationWarning
        Always, pointing to :func:`sweep_table`.
    """
    return sweep_table(out, runner=runner, csv_path=csv_path)


def sweep_table(
    out: str | os.PathLike,
    *,
    runner: SweepRunner | None = None,
    csv_path: str | os.PathLike | None = "summary.csv",
) -> list[dict]:
    """One row per run file in ``out``, rebuilt from the files alone (and written as CSV).

    Parameters
    ----------
    out : path
        Results folder of a sweep.
    runner : SweepRunner, optional
        Its ``read`` turns a result file into a row; default :func:`default_runner`'s.
    csv_path : path or None, default "summary.csv"
        CSV file written (atomically); relative paths are inside ``out``; None writes nothing.

    Returns
    -------
    list of dict
        Sorted by hash. Keys: ``hash``, ``status`` (``"done"`` or ``"failed"``), the request
        (``case``, ``controller``, ``scheme``, ``seed``, ``seconds``, ``quick``,
        ``overrides.<key>``), then the reader's figures (nested keys joined by dots); failed
        runs have ``error``.
    """
    out = pathlib.Path(out)
    read = (runner or default_runner()).read
    rows = []
    for path in sorted(out.glob("*.h5")):
        if len(path.stem) != _HASH_LEN:
            continue
        data = dict(read(path))
        settings = data.pop("settings", {})
        row = {"hash": path.stem, "status": "done"}
        for k, v in settings.items():
            _flat_item("", k, v, row)
        for k, v in data.items():
            _flat_item("", k, v, row)
        rows.append(row)
    for path in sorted(out.glob("*.error.json")):
        hash_ = path.name.split(".")[0]
        if (out / f"{hash_}.h5").exists():
            continue  # a later attempt succeeded
        record = json.loads(path.read_text())
        row = {"hash": hash_, "status": "failed"}
        for k, v in record.get("settings", {}).items():
            _flat_item("", k, v, row)
        row["error"] = f"{record.get('error_type')}: {record.get('error')}"
        rows.append(row)
    rows.sort(key=lambda r: r["hash"])
    if csv_path is not None:
        target = pathlib.Path(csv_path)
        target = target if target.is_absolute() else out / target
        keys = [k for k in _FIRST if any(k in r for r in rows)]
        keys += sorted({k for r in rows for k in r} - set(keys))
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        with atomic_path(target) as tmp:
            pathlib.Path(tmp).write_text(buf.getvalue())
    return rows
