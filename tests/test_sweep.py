"""Sweeps on dask.distributed: validation before any run, hashing, kill and resume, failures."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pathlib
import signal
import socket
import subprocess
import sys
import time

import pytest
from _sweep_runner import (
    BLAS_VARS,
    VALID,
    IntervalRunner,
    SharedCalibrationRunner,
    environment_row,
    environment_run,
    expected_value,
    make_runner,
    read_row,
)

from aocontrol.study.sweep import (
    PARTIAL_DIR,
    SweepRunner,
    SweepSpec,
    SweepSpecError,
    blas_threads_per_worker,
    load_sweep_spec,
    run_hash,
    run_sweep,
    summary_table,
    sweep_table,
)

HERE = pathlib.Path(__file__).resolve().parent

SPEC = """\
cases = ["alpha", "beta"]
controllers = ["integrator", "datadriven"]
schemes = ["single"]
seeds = [0, 1, 2]
seconds = 0.1
quick = true
"""


@pytest.fixture(scope="module")
def scheduler_address():
    """One local cluster for the module's in-process sweeps, reached by its address (the
    ``scheduler=`` path); the killed sweep starts its own default cluster in a subprocess."""
    from distributed import LocalCluster

    with LocalCluster(
        n_workers=2, threads_per_worker=1, dashboard_address=None, silence_logs=50
    ) as cluster:
        yield cluster.scheduler_address


def _write(tmp_path: pathlib.Path, text: str, name: str = "sweep.toml") -> pathlib.Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _hashes(out: pathlib.Path) -> list[str]:
    return sorted(p.stem for p in out.glob("*.h5"))


def _markers(marker_dir: pathlib.Path) -> list[str]:
    return sorted(p.name for p in marker_dir.iterdir())


def test_run_hash_is_sha256_of_sorted_compact_json():
    # Oracle: the documented recipe written out by hand.
    settings = {"seed": 3, "case": "alpha", "overrides": {"seeing": 0.6}, "seconds": 0.5}
    text = '{"case":"alpha","overrides":{"seeing":0.6},"seconds":0.5,"seed":3}'
    assert run_hash(settings) == hashlib.sha256(text.encode()).hexdigest()[:16]
    # key order and an integral float written as 1250.0 do not change the name ...
    assert run_hash({"fs": 1250.0, "a": 1}) == run_hash({"a": 1, "fs": 1250})
    # ... any value does
    assert run_hash({**settings, "seed": 4}) != run_hash(settings)


def test_spec_expands_every_combination(tmp_path):
    text = SPEC + "\n[overrides]\nseeing = [0.6, 0.8]\n"
    spec, runs = load_sweep_spec(_write(tmp_path, text), runner=make_runner(tmp_path))
    # 2 cases x 2 controllers x 1 scheme x 2 seeings x 3 seeds
    assert len(runs) == 24
    assert len({r.hash for r in runs}) == 24
    seen = {
        (r.settings["case"], r.settings["overrides"]["seeing"], r.settings["seed"]) for r in runs
    }
    assert len(seen) == 12
    assert spec.seconds == 0.1 and spec.quick is True


@pytest.mark.parametrize(
    ("text", "key", "needle"),
    [
        (SPEC.replace("controllers", "controlers"), "controlers", "did you mean 'controllers'"),
        (SPEC.replace('"beta"', '"betta"'), "cases", "valid: alpha, beta, gamma"),
        (SPEC.replace('"single"', '"dCAO"'), "schemes", "valid: dcao, single"),
        (SPEC.replace('"integrator"', '"lqq"'), "controllers", "valid: datadriven, integrator"),
        (SPEC.replace("seconds = 0.1", 'seconds = "fast"'), "seconds", "finite number > 0"),
        (SPEC.replace("seeds = [0, 1, 2]", "seeds = [0, 0]"), "seeds", "more than once"),
        (SPEC.replace("seeds = [0, 1, 2]", "seeds = [-1]"), "seeds", "integers >= 0"),
        (SPEC.replace("quick = true", "quick = 1"), "quick", "true or false"),
        (SPEC.replace('schemes = ["single"]\n', ""), "schemes", "missing"),
        (SPEC + "\n[overrides]\nseeing = []\n", "overrides.seeing", "at least one value"),
        (SPEC + "\n[overrides]\nseing = [0.6]\n", "overrides", "has no value 'seing'"),
        (SPEC + "cases = 3\n", "", "not valid TOML"),
    ],
)
def test_spec_typo_fails_before_any_run(tmp_path, text, key, needle):
    spec = _write(tmp_path, text)
    markers = tmp_path / "markers"
    markers.mkdir()
    out = tmp_path / "out"
    t0 = time.perf_counter()
    with pytest.raises(SweepSpecError) as info:
        run_sweep(spec, out=out, runner=make_runner(markers))
    message = str(info.value)
    assert str(spec) in message  # the file ...
    assert f": {key}:" in message or not key  # ... the key ...
    assert needle in message  # ... and what is valid
    assert _markers(markers) == []  # no run started
    assert not out.exists()  # nothing written
    assert time.perf_counter() - t0 < 2.0  # no cluster was started


def test_spec_object_validates_its_fields():
    with pytest.raises(SweepSpecError, match="seconds: must be a finite number > 0"):
        SweepSpec(cases=("a",), controllers=("b",), schemes=("c",), seconds=-1.0)
    spec = SweepSpec(cases="a", controllers=["b"], schemes=("c",), overrides={"x": 1})
    assert spec.cases == ("a",) and spec.overrides == (("x", (1,)),)


def test_unreachable_scheduler_fails_fast(tmp_path):
    with socket.socket() as s:  # a free local port: nothing listens there once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    markers = tmp_path / "markers"
    markers.mkdir()
    t0 = time.perf_counter()
    with pytest.raises(ConnectionError, match=f"scheduler='{address}'.*within 1 s"):
        run_sweep(
            _write(tmp_path, SPEC),
            out=tmp_path / "out",
            scheduler=address,
            runner=make_runner(markers),
            timeout=1.0,
        )
    # the connection timeout plus the client's shutdown; far below a hang
    assert time.perf_counter() - t0 < 10.0
    assert _markers(markers) == []


@pytest.mark.slow
def test_killed_sweep_resumes_without_losing_or_duplicating(tmp_path, scheduler_address):
    spec_path = _write(tmp_path, SPEC)
    out, markers = tmp_path / "out", tmp_path / "markers"
    markers.mkdir()
    _, runs = load_sweep_spec(spec_path, runner=make_runner(markers))
    expected = sorted(r.hash for r in runs)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(HERE), *sys.path]))
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    code = "import _sweep_runner, sys; _sweep_runner.main(*sys.argv[1:])"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(spec_path), str(out), str(markers), "0.4"],
        env=env,
        start_new_session=True,  # its own process group: the cluster's workers die with it
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        # generous: a loaded 2-core machine takes over a minute to start the cluster
        deadline = time.monotonic() + 150.0
        while time.monotonic() < deadline and len(_hashes(out) if out.exists() else []) < 3:
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            time.sleep(0.05)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
    time.sleep(0.5)  # let the killed workers' last writes (if any) land
    done_before = set(_hashes(out))
    markers_before = set(_markers(markers))
    assert 3 <= len(done_before) < len(expected), "the kill must land mid-way"
    assert done_before <= set(expected)
    assert {m.split(".")[0] for m in markers_before} >= done_before  # each file had its run

    report = run_sweep(
        spec_path, out=out, runner=make_runner(markers, sleep_s=0.05), scheduler=scheduler_address
    )

    # every expected result present exactly once (one file per hash, nothing else)
    assert _hashes(out) == expected
    assert sorted(report.skipped) == sorted(done_before)
    assert sorted(report.ran) == sorted(set(expected) - done_before)
    assert report.failed == ()
    # each run executed now has its timing: the process that ran it, its wall and CPU time
    assert sorted(t["hash"] for t in report.timings) == sorted(report.ran)
    for t in report.timings:
        assert t["seconds"] >= 0.05 and t["cpu_s"] >= 0.0 and ":" in t["worker"], t
    # the resumed sweep ran only the missing ones, each once
    new = sorted(m.split(".")[0] for m in set(_markers(markers)) - markers_before)
    assert new == sorted(set(expected) - done_before)
    # no temporary file remains, and no file other than results and the summary
    assert not (out / PARTIAL_DIR).exists()
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{h}.h5" for h in expected] + ["summary.csv"]
    )
    # the summary table is rebuilt from the files: one row per run with its figure
    rows = sweep_table(out, runner=make_runner(markers), csv_path=None)
    assert [r["hash"] for r in rows] == expected
    by_hash = {r.hash: r.settings for r in runs}
    for row in rows:
        assert row["value"] == expected_value(by_hash[row["hash"]])
        assert row["case"] == by_hash[row["hash"]]["case"]
    assert (out / "summary.csv").read_text().count("\n") == len(expected) + 1
    # The old name stays, deprecated (it clashed with results.summary_table(paths)).
    with pytest.warns(DeprecationWarning, match="use sweep_table"):
        assert summary_table(out, runner=make_runner(markers), csv_path=None) == rows


@pytest.mark.slow
def test_failing_run_is_recorded_and_the_others_complete(tmp_path, scheduler_address):
    text = SPEC.replace('"beta"', '"gamma"').replace("seeds = [0, 1, 2]", "seeds = [0]")
    markers = tmp_path / "markers"
    markers.mkdir()
    out = tmp_path / "out"
    runner = make_runner(markers, sleep_s=0.0, fail_case="gamma")
    report = run_sweep(_write(tmp_path, text), out=out, runner=runner, scheduler=scheduler_address)
    _, runs = load_sweep_spec(_write(tmp_path, text), runner=runner)
    good = sorted(r.hash for r in runs if r.settings["case"] == "alpha")
    bad = sorted(r.hash for r in runs if r.settings["case"] == "gamma")
    assert sorted(report.ran) == good and _hashes(out) == good
    assert sorted(h for h, _ in report.failed) == bad
    for h in bad:  # an error record, never a file that looks like a result
        record = json.loads((out / f"{h}.error.json").read_text())
        assert record["error_type"] == "RuntimeError" and "set to fail" in record["error"]
        assert record["settings"]["case"] == "gamma"
        assert not (out / f"{h}.h5").exists()
    rows = {r["hash"]: r for r in report.table}
    assert {h: rows[h]["status"] for h in good + bad} == {
        **{h: "done" for h in good},
        **{h: "failed" for h in bad},
    }
    assert not (out / PARTIAL_DIR).exists()
    assert set(VALID["cases"]) >= {r["case"] for r in report.table}


@pytest.mark.slow
def test_real_runs_write_results_files_that_the_summary_reads(tmp_path, scheduler_address):
    pytest.importorskip("aocontrol.study.compare", reason="the case comparison (task C)")
    from aocontrol.study.results import load_result, read_settings

    # The cheapest real run: quick scene, stage 2 alone, 0.05 s of exposure.
    text = (
        'cases = ["bright1-best"]\ncontrollers = ["integrator"]\nschemes = ["single"]\n'
        "seeds = [0]\nseconds = 0.05\nquick = true\n\n[overrides]\nseeing = [0.6]\n"
    )
    spec = _write(tmp_path, text)
    out = tmp_path / "out"
    report = run_sweep(spec, out=out, scheduler=scheduler_address)
    assert report.failed == ()
    (hash_,) = report.ran
    path = out / f"{hash_}.h5"
    # the file is a results file of the results module, with the sweep's request inside
    stored = read_settings(path)
    assert stored["sweep"]["hash"] == hash_
    assert run_hash(stored["sweep"]["request"]) == hash_
    assert stored["case"] == "bright1-best" and stored["overrides"] == {"seeing": 0.6}
    # two paths to the same figure: the summary row and the reloaded result
    (row,) = report.table
    strehl = load_result(path).science.strehl
    assert row["strehl"] == pytest.approx(strehl, rel=1e-12)  # same stored number
    assert 0.0 < row["strehl"] <= 1.0
    assert row["case"] == "bright1-best" and row["overrides.seeing"] == 0.6
    # run again: everything is present, nothing runs (and no cluster is needed)
    again = run_sweep(spec, out=out, scheduler="tcp://127.0.0.1:9")
    assert again.ran == () and again.skipped == (hash_,)
    # two paths: the same run in this process gives the same figures as the cluster's worker
    # (same settings, same seed, the calibrations from the shared disk cache). To rounding:
    # the worker's BLAS has one thread and this process's every core, which splits the
    # reductions of a matrix product differently (measured: the last bit of the RMS).
    from aocontrol.study.sweep import default_runner

    runner = default_runner()
    (settings,) = [r.settings for r in load_sweep_spec(spec)[1]]
    local = tmp_path / "local"
    local.mkdir()
    runner.run(dict(settings), local / f"{hash_}.h5")
    (local_row,) = sweep_table(local, csv_path=None)
    for key in ("strehl", "mean_contrast_4_6", "residual_rms_nm"):
        assert local_row[key] == pytest.approx(row[key], rel=1e-12, abs=0), key


def test_real_spec_typos_name_the_valid_cases_and_keys(tmp_path):
    pytest.importorskip("aocontrol.study.compare", reason="the case comparison (task C)")
    from aocontrol.study.cases import list_cases

    text = 'cases = ["bright-best"]\ncontrollers = ["integrator"]\nschemes = ["single"]\n'
    with pytest.raises(SweepSpecError, match="did you mean 'bright1-best'") as info:
        load_sweep_spec(_write(tmp_path, text))
    assert all(name in str(info.value) for name in list_cases())
    text = text.replace("bright-best", "bright1-best") + "\n[overrides]\nseeinng = [0.6]\n"
    with pytest.raises(SweepSpecError, match="overrides.*seeinng"):
        load_sweep_spec(_write(tmp_path, text, "typo.toml"))


@pytest.mark.parametrize("n_workers", [1, 2])
def test_local_cluster_shares_the_cores_as_blas_threads_and_stays_quiet(
    n_workers, tmp_path, caplog, capfd, monkeypatch
):
    # run_sweep's own local cluster: each worker has cores // workers BLAS threads, set before
    # the worker starts (one worker: every core, where Dask's default would give it one; as
    # many workers as cores: one each); Dask's INFO messages are not shown when aocontrol is
    # not verbose, and the shutdown leaves no traceback.
    text = 'cases = ["alpha"]\ncontrollers = ["c"]\nschemes = ["s"]\nseeds = [0, 1, 2, 3]\n'
    runner = SweepRunner(run=environment_run, read=environment_row)
    for var in (*BLAS_VARS, "LOKY_MAX_CPU_COUNT", "MALLOC_TRIM_THRESHOLD_"):  # the user's wins
        monkeypatch.delenv(var, raising=False)
    with caplog.at_level(logging.WARNING, logger="aocontrol"):
        report = run_sweep(
            _write(tmp_path, text), out=tmp_path / "out", runner=runner, n_workers=n_workers
        )
    assert report.failed == () and len(report.ran) == 4
    want = str(max(1, (os.cpu_count() or 1) // n_workers))
    for row in report.table:
        assert {k: row[f"env.{k}"] for k in BLAS_VARS} == dict.fromkeys(BLAS_VARS, want)
        # the syntheses' process pools inside a run take the worker's cores, not every core
        assert row["env.joblib.cpu_count"] == int(want)
        # glibc keeps its adaptive mmap threshold (Dask's default trim threshold turns it off:
        # page faults on every large array) and no profiler samples the running task
        assert row["env.MALLOC_TRIM_THRESHOLD_"] is None
        assert row["env.profile"] is False
    assert blas_threads_per_worker(os.cpu_count() or 1) == 1
    # this process's environment left as it was
    assert not {*BLAS_VARS, "LOKY_MAX_CPU_COUNT"} & set(os.environ)
    assert blas_threads_per_worker(1) == (os.cpu_count() or 1)
    noisy = [r for r in caplog.records if r.name.startswith("distributed") and r.levelno < 30]
    assert noisy == []
    assert not any(r.exc_info for r in caplog.records)
    err = capfd.readouterr().err  # the worker processes' stderr too
    assert "Traceback" not in err and "CommClosedError" not in err, err[-2000:]


@pytest.mark.slow
def test_successful_cli_sweep_prints_no_traceback_and_no_dask_info(tmp_path):
    # `aocontrol sweep` end to end in a fresh process (the cheapest real run): exit 0, the
    # summary on stdout, and on stderr neither a traceback nor Dask's INFO lines.
    text = (
        'cases = ["bright1-best"]\ncontrollers = ["integrator"]\nschemes = ["single"]\n'
        "seeds = [0]\nseconds = 0.05\nquick = true\n\n[overrides]\nseeing = [0.6]\n"
    )
    spec = _write(tmp_path, text)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(HERE.parent), *sys.path]))
    proc = subprocess.run(
        [sys.executable, "-m", "aocontrol", "sweep", str(spec), "--out", str(tmp_path / "out")],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "1 run, 0 already present, 0 failed" in proc.stdout
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert "CommClosedError" not in proc.stderr
    assert "Warning" not in proc.stderr, proc.stderr[-3000:]  # e.g. a busy dashboard port
    assert not [line for line in proc.stderr.splitlines() if line.startswith("INFO")]


def test_timings_give_each_runs_cache_parts_and_cpu(tmp_path, scheduler_address):
    # Two cases needing one calibration, on two workers at once: the first builds it, the
    # other waits on the entry's lock and reads it; each run's timing says so (its parts).
    cache = tmp_path / "cache"
    cache.mkdir()
    text = SPEC.replace('["integrator", "datadriven"]', '["integrator"]').replace(
        "[0, 1, 2]", "[0]"
    )
    runner = SweepRunner(
        run=SharedCalibrationRunner(str(cache), first="alpha"), read=read_row, valid=VALID
    )
    report = run_sweep(
        _write(tmp_path, text), out=tmp_path / "out", runner=runner, scheduler=scheduler_address
    )
    assert report.failed == () and len(report.timings) == 2
    parts = {}
    for t in report.timings:
        (row,) = [r for r in report.table if r["hash"] == t["hash"]]
        parts[row["case"]] = t["parts"]
        # the process's CPU is its user + system time; the run's thread is a part of it
        assert t["parts"]["user_s"] + t["parts"]["sys_s"] == pytest.approx(t["cpu_s"], abs=0.02)
        assert 0.0 <= t["thread_cpu_s"] <= t["cpu_s"] + 1e-3, t
    assert len({t["worker"] for t in report.timings}) == 2  # ran at the same time
    alpha, beta = parts["alpha"], parts["beta"]
    assert (alpha["build_n"], alpha["write_n"], beta["build_n"], beta["write_n"]) == (1, 1, 0, 0)
    assert alpha["build_s"] >= 0.6 and alpha["lock_wait_s"] < 0.3
    # beta asked once the build had started: it waited for it (the lock), then loaded the entry
    assert 0.2 <= beta["lock_wait_s"] <= alpha["build_s"] + alpha["write_s"] + 0.5
    assert beta["load_n"] == 1 and alpha["load_n"] == 1  # alpha's one look found nothing
    assert {r["value"] for r in report.table} == {45.0}


def test_other_runs_of_a_case_to_build_wait_for_its_first_then_go_anywhere(
    tmp_path, scheduler_address
):
    # A case not calibrated (every case of a runner that is not the package's): its first run
    # builds on a worker of its own; the others start only once it is done (none waits on the
    # build's lock), then on any worker.
    records = tmp_path / "records"
    records.mkdir()
    text = SPEC.replace('["integrator", "datadriven"]', '["integrator"]').replace(
        "[0, 1, 2]", "[0, 1, 2, 3]"
    )
    runner = SweepRunner(run=IntervalRunner(str(records)), read=read_row, valid=VALID)
    report = run_sweep(
        _write(tmp_path, text), out=tmp_path / "out", runner=runner, scheduler=scheduler_address
    )
    assert report.failed == () and len(report.ran) == 8
    rec = {p.stem: json.loads(p.read_text()) for p in records.glob("*.json")}
    assert len(rec) == 8
    for case in ("alpha", "beta"):
        first = rec[f"{case}.0"]
        for seed in (1, 2, 3):
            assert rec[f"{case}.{seed}"]["start"] >= first["end"], (case, seed, rec)
    # the two first runs ran at the same time, on the two workers
    assert rec["alpha.0"]["pid"] != rec["beta.0"]["pid"]
    assert {row["value"] for row in report.table} == {
        expected_value({"seed": s, "case": c}) for c in ("alpha", "beta") for s in range(4)
    }
