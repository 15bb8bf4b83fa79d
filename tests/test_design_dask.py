"""The data-driven designs on dask.distributed: the same bank as in one process, failures kept
per mode, a killed worker's modes designed once, clear refusals before anything is designed.

Chunks are shrunk to 2 modes (``_dd_mode._CHUNK``, read in this process where the chunks are
cut) so that a handful of modes makes several tasks.
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import threading

import cloudpickle
import numpy as np
import pytest
from distributed import Client, LocalCluster
from distributed.diagnostics.plugin import WorkerPlugin

from aocontrol import loop_plant
from aocontrol.controllers import Integrator
from aocontrol.study.cli import main
from aocontrol.synthesis import (
    DataDrivenError,
    LoopTelemetry,
    _dd_mode,
    datadriven,
    design_from_telemetry,
)

FS = 1000.0
CHUNK = 2
KW = dict(order=3, noise_psd=1e-4, progress=False)


def _psd(f: np.ndarray, corners=(5.0, 15.0, 40.0, 8.0, 25.0)) -> np.ndarray:
    """Low-pass disturbance PSDs, one row per corner frequency [Hz] (one-sided)."""
    return np.stack([1.0 / (1.0 + (f / fc) ** 2) for fc in corners])


@pytest.fixture
def small_chunks(monkeypatch):
    monkeypatch.setattr(_dd_mode, "_CHUNK", CHUNK)


@pytest.fixture(scope="module")
def threads_client():
    """Two in-process workers: enough for everything but a killed process."""
    with (
        LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=False,
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
            silence_logs=logging.CRITICAL,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def _same_bank(a, b) -> None:
    """Bit for bit: coefficients, figures and each mode's start."""
    np.testing.assert_array_equal(a.controller.b, b.controller.b)
    np.testing.assert_array_equal(a.controller.a, b.controller.a)
    np.testing.assert_array_equal(a.residual_variance, b.residual_variance)
    np.testing.assert_array_equal(a.residual_variance_fine, b.residual_variance_fine)
    assert [r.start for r in a.reports] == [r.start for r in b.reports]


def test_dask_bank_is_the_serial_and_joblib_bank(small_chunks, threads_client):
    # Invariant: the three paths design the same chunks with the same function.
    f = np.linspace(0.0, FS / 2, 151)
    psd = _psd(f)
    plant = loop_plant(FS, 1.0)
    serial = datadriven(plant, f, psd, n_jobs=1, **KW)
    _same_bank(datadriven(plant, f, psd, client=threads_client, **KW), serial)
    _same_bank(datadriven(plant, f, psd, n_jobs=2, **KW), serial)
    # The chunks, not the workers, decide the starts: the first mode of each chunk (0, 2, 4)
    # never starts from the previous mode's design.
    assert all(serial.reports[m].start != "previous mode" for m in range(0, 5, CHUNK))


def test_chunk_boundaries_change_warm_starts(monkeypatch):
    # The twin of the test above: the check can fail. Modes 0-1 and 2-3 designed as two
    # chunks or as one differ where a mode starts from its predecessor across the boundary.
    f = np.linspace(0.0, FS / 2, 151)
    psd = _psd(f, corners=(5.0, 6.0, 7.0, 8.0))
    plant = loop_plant(FS, 1.0)
    one = datadriven(plant, f, psd, n_jobs=1, **KW)
    monkeypatch.setattr(_dd_mode, "_CHUNK", CHUNK)
    two = datadriven(plant, f, psd, n_jobs=1, **KW)
    assert one.reports[2].start == "previous mode" and two.reports[2].start != "previous mode"
    assert not np.array_equal(one.controller.b[2], two.controller.b[2])


def test_failing_mode_is_kept_apart_on_dask(small_chunks, threads_client):
    # As test_datadriven's serial case: mode 1 starts with almost no modulus margin and must
    # reach 0.9 with an integrator structure (infeasible); modes 0 and 2 succeed.
    f = np.linspace(0.0, FS / 2, 101)
    psd = _psd(f, corners=(15.0, 15.0, 15.0))
    kw = dict(
        order=1,
        fixed_denominator=[1, -1],
        modulus_margin=0.9,
        initial=Integrator(np.array([0.05, 0.9, 0.05]), fs=FS),
        progress=False,
    )
    plant = loop_plant(FS, 1.0)
    with pytest.raises(DataDrivenError) as serial:
        datadriven(plant, f, psd, n_jobs=1, **kw)
    with pytest.raises(DataDrivenError, match="mode 1") as dask:
        datadriven(plant, f, psd, client=threads_client, **kw)
    assert list(dask.value.failed) == [1] and "infeasible" in dask.value.failed[1]
    np.testing.assert_array_equal(dask.value.result.ok, [True, False, True])
    _same_bank(dask.value.result, serial.value.result)


class _KillOnce(WorkerPlugin):
    """Kill the worker process running the task ``key_prefix...`` shortly after it starts,
    the first time only (a marker file says it happened), or every time (``marker=None``)."""

    name = "kill-once"

    def __init__(self, key_prefix: str, marker: str | None) -> None:
        self.key_prefix, self.marker = key_prefix, marker

    def transition(self, key, start, finish, **kwargs) -> None:
        name = key if isinstance(key, str) else str(key)
        if finish == "executing" and name.startswith(self.key_prefix):
            if self.marker is None or not os.path.exists(self.marker):
                if self.marker is not None:
                    with open(self.marker, "w") as fh:
                        fh.write(str(os.getpid()))
                threading.Timer(0.05, os._exit, args=(1,)).start()  # mid-design


@pytest.fixture(scope="module")
def process_cluster():
    with LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        silence_logs=logging.CRITICAL,
    ) as cluster:
        yield cluster


def test_killed_worker_modes_designed_once(small_chunks, process_cluster, tmp_path):
    # The plugin's class travels by value: the workers cannot import this test module.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    f = np.linspace(0.0, FS / 2, 151)
    psd = _psd(f)
    plant = loop_plant(FS, 1.0)
    serial = datadriven(plant, f, psd, n_jobs=1, **KW)
    marker = tmp_path / "killed"
    with Client(process_cluster) as client:
        pids = set(client.run(os.getpid).values())
        client.register_plugin(_KillOnce("datadriven-chunk-1-", str(marker)))
        try:
            res = datadriven(plant, f, psd, client=client, **KW)
        finally:
            client.unregister_worker_plugin(_KillOnce.name)
    assert marker.exists() and int(marker.read_text()) in pids  # a worker died mid-chunk
    # Every mode once, in order, and the serial bank bit for bit.
    assert [r.mode for r in res.reports] == list(range(psd.shape[0]))
    assert all(r.ok for r in res.reports)
    _same_bank(res, serial)


def test_a_chunk_that_kills_every_worker_fails_alone(small_chunks, process_cluster):
    # The scheduler gives up on a task whose worker died more than allowed_failures times
    # (Dask's default 3; 0 here to keep the test short): its modes fail with the reason, the
    # other chunks' modes are designed as in one process.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    f = np.linspace(0.0, FS / 2, 151)
    psd = _psd(f)
    plant = loop_plant(FS, 1.0)
    serial = datadriven(plant, f, psd, n_jobs=1, **KW)
    scheduler = process_cluster.scheduler
    allowed, scheduler.allowed_failures = scheduler.allowed_failures, 0
    try:
        with Client(process_cluster) as client:
            client.register_plugin(_KillOnce("datadriven-chunk-1-", None))
            try:
                with pytest.raises(DataDrivenError) as info:
                    datadriven(plant, f, psd, client=client, **KW)
            finally:
                client.unregister_worker_plugin(_KillOnce.name)
    finally:
        scheduler.allowed_failures = allowed
    failed = info.value.failed
    assert sorted(failed) == [2, 3] and all("KilledWorker" in failed[m] for m in failed)
    kept = [0, 1, 4]
    np.testing.assert_array_equal(info.value.result.controller.b[kept], serial.controller.b[kept])
    np.testing.assert_array_equal(info.value.result.controller.a[kept], serial.controller.a[kept])


def test_memory_refused_before_anything_is_designed():
    f = np.linspace(0.0, FS / 2, 151)
    with (
        LocalCluster(
            n_workers=1,
            threads_per_worker=1,
            processes=False,
            memory_limit="200 MB",
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
            silence_logs=logging.CRITICAL,
        ) as cluster,
        Client(cluster) as client,
    ):
        with pytest.raises(MemoryError, match=r"needs about 0\.4\d GB per Dask worker.*0\.20 GB"):
            datadriven(loop_plant(FS, 1.0), f, _psd(f), client=client, **KW)
        # Nothing reached the scheduler.
        assert client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)) == 0


def test_closed_client_and_non_dask_design_are_refused(threads_client):
    f = np.linspace(0.0, FS / 2, 151)
    plant = loop_plant(FS, 1.0)
    closed = Client(threads_client.cluster)
    closed.close()
    with pytest.raises(ConnectionError, match="not connected"):
        datadriven(plant, f, _psd(f), client=closed, **KW)
    with pytest.raises(TypeError, match="distributed.Client"):
        datadriven(plant, f, _psd(f), client="tcp://127.0.0.1:8786", **KW)
    tel = LoopTelemetry(np.zeros((512, 2)), np.zeros((512, 2)), fs=FS, latency_frames=1.0)
    with pytest.raises(ValueError, match="'lqg' does not run on a Dask client"):
        design_from_telemetry(tel, "lqg", client=threads_client)


def test_design_from_telemetry_on_dask_is_the_serial_design(threads_client):
    rng = np.random.default_rng(0)
    m = np.cumsum(rng.standard_normal((2048, 2)), axis=0) * 0.05 + rng.standard_normal((2048, 2))
    tel = LoopTelemetry(m, np.zeros_like(m), fs=FS, latency_frames=1.0)
    kw = dict(bounds=(), options={"order": 3, "n_jobs": 1})
    serial = design_from_telemetry(tel, **kw)
    dask = design_from_telemetry(tel, client=threads_client, **kw)
    np.testing.assert_array_equal(dask.controller.b, serial.controller.b)
    np.testing.assert_array_equal(dask.controller.a, serial.controller.a)


def test_cli_unreachable_scheduler_designs_nothing(tmp_path, capsys, monkeypatch):
    from aocontrol.study import sweep

    monkeypatch.setattr(sweep, "CONNECT_TIMEOUT_S", 0.5)  # the CLI reads it at each call
    with socket.socket() as s:  # a free local port: nothing listens there once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    tel = tmp_path / "tel.npz"
    np.savez(tel, measurements=np.zeros((1024, 2)), commands=np.zeros((1024, 2)))
    out = tmp_path / "dd.h5"
    argv = ["design", str(tel), "--fs", "1000", "--latency", "1", "--out", str(out)]
    assert main([*argv, "--scheduler", f"tcp://127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err
    assert "no Dask scheduler answered within 0.5 s" in err and "Traceback" not in err
    assert not out.exists()
    assert main([*argv, "--controller", "lqg", "--workers", "2"]) == 2
    assert "'lqg' does not run on a Dask cluster" in capsys.readouterr().err


def test_cli_design_on_a_scheduler_writes_the_serial_bank(tmp_path, capsys, threads_client):
    import aocontrol

    rng = np.random.default_rng(1)
    m = np.cumsum(rng.standard_normal((2048, 2)), axis=0) * 0.05 + rng.standard_normal((2048, 2))
    tel = tmp_path / "tel.npz"
    np.savez(tel, measurements=m, commands=np.zeros_like(m))
    argv = ["design", str(tel), "--fs", "1000", "--latency", "1", "--order", "3"]
    argv += ["--bounds", "none", "--no-progress"]
    assert main([*argv, "--jobs", "1", "--out", str(tmp_path / "serial.h5")]) == 0
    address = threads_client.scheduler.address
    assert main([*argv, "--scheduler", address, "--out", str(tmp_path / "dask.h5")]) == 0
    serial, dask = (aocontrol.load_controller(tmp_path / n) for n in ("serial.h5", "dask.h5"))
    np.testing.assert_array_equal(dask.b, serial.b)
    np.testing.assert_array_equal(dask.a, serial.a)
