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

Layout: this module loads the spec and runs the sweep; the spec's validation and run hashes are
in ``_sweep_spec``, the runner contract and the table in ``_sweep_runs``, the placement of runs
on workers in ``_sweep_place`` and the Dask cluster in ``_sweep_cluster``.
"""

from __future__ import annotations

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
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from aocontrol._atomic import atomic_path
from aocontrol.study._cache import process_usage
from aocontrol.study._sweep_cluster import _connect, blas_threads_per_worker, local_cluster
from aocontrol.study._sweep_place import _after_builds, _run_placement
from aocontrol.study._sweep_runs import SweepRunner, default_runner, summary_table, sweep_table
from aocontrol.study._sweep_spec import (
    _NAME_KEYS,
    SPEC_KEYS,  # noqa: F401  (re-exported: the keys of a spec file)
    SweepRun,
    SweepSpec,
    SweepSpecError,
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
