"""A tiny sweep runner for tests/test_sweep.py, importable by Dask workers (module level).

Each call leaves a marker file ``<hash>.<uuid>`` in ``marker_dir`` when it starts (so a test
counts the runs executed), sleeps, then writes a small HDF5 result (its settings as a JSON root
attribute and one figure ``value = 10 * seed + len(case)``). A run of case ``fail_case`` raises.
"""

from __future__ import annotations

import json
import pathlib
import sys
import time
import uuid
from dataclasses import dataclass

import h5py

from aocontrol.study.sweep import SweepRunner, run_hash, run_sweep

VALID = {
    "cases": ("alpha", "beta", "gamma"),
    "controllers": ("integrator", "datadriven"),
    "schemes": ("single", "dcao"),
}


def expected_value(settings: dict) -> float:
    """The figure the runner writes for ``settings`` (the oracle of the summary table)."""
    return 10.0 * settings["seed"] + len(settings["case"])


@dataclass(frozen=True)
class MarkerRunner:
    """Callable run: marker, sleep, HDF5 result (or an error for ``fail_case``)."""

    marker_dir: str
    sleep_s: float = 0.3
    fail_case: str | None = None

    def __call__(self, settings: dict, path: pathlib.Path) -> None:
        marker = pathlib.Path(self.marker_dir) / f"{run_hash(settings)}.{uuid.uuid4().hex}"
        marker.touch()
        time.sleep(self.sleep_s)
        if settings["case"] == self.fail_case:
            raise RuntimeError(f"case {self.fail_case!r} is set to fail")
        with h5py.File(path, "w") as f:
            f.attrs["settings"] = json.dumps(settings)
            f.attrs["value"] = expected_value(settings)


def read_row(path: pathlib.Path) -> dict:
    """Summary row of a MarkerRunner result."""
    with h5py.File(path, "r") as f:
        return {"settings": json.loads(f.attrs["settings"]), "value": float(f.attrs["value"])}


def check(settings: dict) -> None:
    """Reject overrides other than ``seeing`` (as a real case would reject unknown keys)."""
    for key in settings["overrides"]:
        if key != "seeing":
            raise ValueError(f"case {settings['case']!r} has no value {key!r}; known: seeing")


def make_runner(marker_dir: str, sleep_s: float = 0.3, fail_case: str | None = None):
    """A SweepRunner around MarkerRunner with the fake registries of VALID."""
    return SweepRunner(
        run=MarkerRunner(str(marker_dir), sleep_s, fail_case),
        read=read_row,
        valid=VALID,
        check=check,
    )


@dataclass(frozen=True)
class SharedCalibrationRunner:
    """Runs that need one calibration (one disk-cache key) built in ``build_s`` seconds.

    The run of case ``first`` asks the cache at once; the others wait until its build has
    started (a marker file), so that they ask while it holds the entry's lock.
    """

    cache: str
    first: str
    build_s: float = 0.6

    def __call__(self, settings: dict, path: pathlib.Path) -> None:
        import os

        saved = os.environ.get("AOCONTROL_CACHE")
        os.environ["AOCONTROL_CACHE"] = self.cache  # this test's cache folder, for this run
        try:
            self._run(settings, path)
        finally:
            if saved is None:
                os.environ.pop("AOCONTROL_CACHE")
            else:
                os.environ["AOCONTROL_CACHE"] = saved

    def _run(self, settings: dict, path: pathlib.Path) -> None:
        from aocontrol.study._cache import cached

        started = pathlib.Path(self.cache) / "build-started"
        if settings["case"] != self.first:
            deadline = time.monotonic() + 60.0
            while not started.exists() and time.monotonic() < deadline:
                time.sleep(0.01)

        def build() -> list:
            started.touch()
            time.sleep(self.build_s)
            return list(range(10))

        value = cached("shared calibration", build)
        with h5py.File(path, "w") as f:
            f.attrs["settings"] = json.dumps(settings)
            f.attrs["value"] = float(sum(value))


@dataclass(frozen=True)
class IntervalRunner:
    """Writes ``<case>.<seed>.json`` in ``record_dir``: the run's start and end time and its
    process; sleeps ``sleep_s`` (``first_s`` for seed 0) in between; then a small result."""

    record_dir: str
    sleep_s: float = 0.1
    first_s: float = 0.6

    def __call__(self, settings: dict, path: pathlib.Path) -> None:
        import os

        start = time.time()
        time.sleep(self.first_s if settings["seed"] == 0 else self.sleep_s)
        record = {"start": start, "end": time.time(), "pid": os.getpid()}
        name = f"{settings['case']}.{settings['seed']}.json"
        (pathlib.Path(self.record_dir) / name).write_text(json.dumps(record))
        with h5py.File(path, "w") as f:
            f.attrs["settings"] = json.dumps(settings)
            f.attrs["value"] = expected_value(settings)


BLAS_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def environment_run(settings: dict, path: pathlib.Path) -> None:
    """A run that records the worker's BLAS thread variables, the cores joblib gives its
    process pools, glibc's trim threshold, whether Dask profiles the task (and its process
    id)."""
    import os

    import dask
    import joblib

    env = {k: os.environ.get(k) for k in (*BLAS_VARS, "MALLOC_TRIM_THRESHOLD_")}
    env["joblib.cpu_count"] = joblib.cpu_count()
    env["profile"] = bool(dask.config.get("distributed.worker.profile.enabled", True))
    with h5py.File(path, "w") as f:
        f.attrs["settings"] = json.dumps(settings)
        f.attrs["env"] = json.dumps(env)
        f.attrs["pid"] = os.getpid()


def environment_row(path: pathlib.Path) -> dict:
    """Summary row of an environment_run result."""
    with h5py.File(path, "r") as f:
        return {
            "settings": json.loads(f.attrs["settings"]),
            "env": json.loads(f.attrs["env"]),
            "pid": int(f.attrs["pid"]),
        }


def main(spec: str, out: str, marker_dir: str, sleep_s: str) -> None:
    """Entry point of the subprocess that the kill test kills mid-way."""
    run_sweep(spec, out=out, runner=make_runner(marker_dir, float(sleep_s)))


if __name__ == "__main__":
    main(*sys.argv[1:])
