"""The command line: every command's help, exit codes, errors without tracebacks, outputs."""

import subprocess
import sys
import time
from unittest import mock

import numpy as np
import pytest

import aocontrol
from aocontrol.controllers import Integrator
from aocontrol.sim import LinearModalSensor, ModalTimeSeries, Stage, run_loop
from aocontrol.study import _cli_design
from aocontrol.study.cli import main, read_telemetry
from aocontrol.study.demo import run_demo
from aocontrol.study.results import save_result
from aocontrol.synthesis import _dd_starts

FS = 1000.0
LATENCY = 0.5
COMMANDS = ("cases", "run", "compare", "design", "sweep", "demo", "adapt")


def test_demo_designs_stable_controllers_and_writes_plot(tmp_path):
    res = run_demo(str(tmp_path), fs=3000.0, latency_frames=0.83)
    assert (tmp_path / "rejection.png").stat().st_size > 10_000
    assert res.margins, "no controller designed"
    for name, m in res.margins.items():
        assert m.stable, name
        assert m.modulus_margin > 0.3, name
    # Ordering required by construction: Wiener bound <= data-driven (it starts from the
    # optimal integrator) <= optimal-gain integrator <= hand-tuned integrator.
    rms = res.residual_rms
    assert res.wiener_rms <= rms["data-driven (order 5)"]
    assert rms["data-driven (order 5)"] <= rms["optimal-gain integrator"]
    assert rms["optimal-gain integrator"] <= rms["integrator g=0.5 (hand-tuned)"] * (1 + 1e-9)


def _table_rows(out, names):
    """Printed table rows of ``names``: the whitespace-separated cells after the name."""
    rows = {}
    for line in out.splitlines():
        for name in names:
            if line.startswith(name):
                rows[name] = line[len(name) :].split()
    return rows


def test_cli_demo_prints_a_row_per_controller_with_its_margins(tmp_path, capsys):
    assert main(["demo", "--output", str(tmp_path), "--no-comparison"]) == 0
    out = capsys.readouterr().out
    names = ["integrator g=0.5 (hand-tuned)", "optimal-gain integrator", "data-driven (order 5)"]
    rows = _table_rows(out, names + ["physical limit (Wiener bound)"])
    # Every controller has its row: stable, a modulus margin above 0.3, no negative phase or
    # latency margin, and a gain that can rise (GM+ > 0 dB) and fall (GM- < 0 dB).
    for name in names:
        stable, gm_down, gm_up, pm, mm, lat_rm, lat_add, resid = rows[name]
        assert stable == "True", name
        assert float(mm) > 0.3, name
        assert float(gm_down) < 0.0 < float(gm_up) and float(pm) > 0.0, name
        assert float(lat_rm) >= 0.0 and float(lat_add) > 0.0, name
    # The Wiener bound row is the smallest residual (the physical limit).
    bound = float(rows["physical limit (Wiener bound)"][0])
    assert all(bound <= float(rows[n][-1]) for n in names)
    assert (tmp_path / "rejection.png").exists()


def test_cli_bad_input_is_a_clear_error(tmp_path, capsys):
    assert main(["demo", "--output", str(tmp_path), "--fs", "-3", "--no-comparison"]) == 2
    assert "fs must be a finite number > 0, got -3.0" in capsys.readouterr().err


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    assert f"aocontrol {command}" in capsys.readouterr().out


def test_run_help_lists_the_registrys_controller_names(capsys):
    # One list of names everywhere (issue 33): run's --help shows every registered name and
    # alias ("reference", which the README uses, included), the same list the sweep checks.
    from aocontrol.study.sweep import default_runner
    from aocontrol.synthesis import controller_names

    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    listed = out.split("--controller {", 1)[1].split("}", 1)[0].split(",")
    assert listed == list(controller_names())
    assert "reference" in listed and "integrator" in listed
    assert tuple(listed) == tuple(default_runner().valid["controllers"])


def test_python_dash_m_entry_point_help():
    proc = subprocess.run(
        [sys.executable, "-m", "aocontrol", "--help"], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    for command in COMMANDS:
        assert command in proc.stdout


def test_unknown_command_fails_with_usage(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["frobnicate"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_cases_lists_every_case(capsys):
    from aocontrol.study.cases import list_cases

    assert main(["cases"]) == 0
    out = capsys.readouterr().out
    names = list_cases()
    assert len(names) >= 6  # the paper's five cases and the vibration case
    lines = out.splitlines()
    for name in names:
        assert any(line.startswith(name + " ") for line in lines), name


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["run", "no-such-case", "--controller", "integrator", "--scheme", "single"], "case"),
        (["run", "bright1-best", "--controller", "pid", "--scheme", "single"], "controller"),
        (["run", "bright1-best", "--controller", "integrator", "--scheme", "triple"], "scheme"),
        (["compare", "no-such-case"], "case"),
    ],
)
def test_unknown_names_list_the_valid_ones(argv, expected, capsys):
    from aocontrol.study import compare
    from aocontrol.study.cases import list_cases

    valid = {
        "case": list_cases(),
        "controller": list(compare.CONTROLLERS),
        "scheme": list(compare.SCHEMES),
    }[expected]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"unknown {expected}" in err and "Traceback" not in err
    assert all(name in err for name in valid), err


# ------------------------------------------------------------------------------- design
def _telemetry(n_frames=4096, n_modes=3, seed=0):
    """Closed-loop telemetry of a noisy integrator loop on low-pass disturbances [nm]."""
    rng = np.random.default_rng(seed)
    white = rng.standard_normal((n_frames, n_modes)) * np.array([20.0, 10.0, 5.0])[:n_modes]
    d = np.empty_like(white)
    acc = np.zeros(n_modes)
    for k in range(n_frames):  # AR(1) disturbance, pole 0.99: a ~1.6 Hz corner at 1 kHz
        acc = 0.99 * acc + white[k]
        d[k] = acc
    stage = Stage(
        Integrator(0.3, fs=FS, n_modes=n_modes),
        sensor=LinearModalSensor(noise_std=2.0),
        latency_frames=LATENCY,
    )
    return run_loop(stage, ModalTimeSeries(d), n_frames, rng=seed + 1, settle_frames=0)


@pytest.mark.slow
def test_design_from_npz_writes_a_reloadable_controller(tmp_path, capsys):
    res = _telemetry(n_frames=2048, n_modes=2)
    tel = tmp_path / "tel.npz"
    np.savez(tel, measurements=res.telemetry["measurements"], commands=res.telemetry["commands"])
    out = tmp_path / "ctrl" / "dd.h5"
    argv = [
        "design",
        str(tel),
        "--fs",
        str(FS),
        "--latency",
        str(LATENCY),
        "--order",
        "3",
        "--jobs",
        "1",
        "--no-progress",
        "--out",
        str(out),
    ]
    # The estimated PSD of a mode has a peak that turns on the reduced-bound start: from a
    # 64-tap bound here (the same path; the library's 256 taps made this test 2.5x slower:
    # 356 vs 144 s for the command at load 17).
    with mock.patch.object(_dd_starts, "BOUND_TAPS", 64):
        t0 = time.perf_counter()
        assert main(argv) == 0
        elapsed = time.perf_counter() - t0
    text = capsys.readouterr().out
    bank = aocontrol.load_controller(out)
    assert bank.n_modes == 2 and bank.fs == FS
    # The last line splits the command's wall time by step: the steps add up to the total
    # (to the printed 0.1 s), which the clock around the call bounds.
    last = text.splitlines()[-1]
    assert last.startswith("wall time: reading ")
    steps = {
        part.rsplit(" ", 2)[0]: float(part.rsplit(" ", 2)[1])
        for part in last.removeprefix("wall time: ").split("; ")[0].split(", ")
    }
    assert list(steps) == [
        "reading",
        "check and estimate",
        "design",
        "certificates and bounds",
        "files and report",
    ]
    total = float(last.split("; ")[1].split(" s")[0])
    assert abs(sum(steps.values()) - total) <= 0.05 * len(steps) + 0.05
    assert 0 < steps["design"] and total <= elapsed + 0.05
    # Every mode's row says stable with a modulus margin >= the required 0.5 (to the
    # design's verification tolerance of 1 %).
    rows = [line.split() for line in text.splitlines() if line[:1].isdigit()]
    assert [int(r[0]) for r in rows] == [0, 1]
    for r in rows:
        assert r[1] == "yes" and float(r[4]) >= 0.5 * 0.99
    # Oracle by construction: the data-driven design starts from the optimal-gain
    # integrator, so its predicted residual is not larger (ratio <= 1 to rounding).
    ratio = float(text.split("(ratio ")[1].split(")")[0])
    assert ratio <= 1.0 + 1e-6
    assert (tmp_path / "ctrl" / "dd_sensitivity.png").stat().st_size > 10_000
    assert (tmp_path / "ctrl" / "dd_margins.png").stat().st_size > 10_000
    assert f"report: {tmp_path / 'ctrl' / 'dd_report.html'}" in text  # content: test_report.py


def test_design_time_line_counts_every_certificate_step():
    # reference, margins, the robust margins and the bounds are the certificates' share.
    timings = {"estimate": 1.0, "design": 10.0, "reference": 0.25, "margins": 2.0}
    timings |= {"robust": 0.5, "bounds": 0.25}
    line = _cli_design._time_line(timings, 0.5, 3.0)
    assert "reading 0.5 s, check and estimate 1.0 s, design 10.0 s" in line
    assert "certificates and bounds 3.0 s, files and report 3.0 s" in line
    assert "; 17.5 s in all" in line
    assert timings["robust"] == 0.5  # not consumed


def test_design_reads_a_results_file_with_telemetry(tmp_path, capsys):
    res = _telemetry(n_frames=2048, n_modes=2)
    path = save_result(res, tmp_path / "run.h5", telemetry=True)
    out = tmp_path / "omgi.h5"
    # fs and the latency come from the results file.
    assert main(["design", str(path), "--controller", "omgi", "--out", str(out)]) == 0
    assert "fs = 1000 Hz, latency = 0.5 frame" in capsys.readouterr().out
    bank = aocontrol.load_controller(out)
    assert type(bank) is Integrator and bank.n_modes == 2


def test_design_reports_the_margin_over_an_uncertainty_set(tmp_path, capsys):
    # --robust-gain / --robust-latency: a column per mode and one line saying what the
    # margins cover, for any controller; a reversed interval is refused by name.
    res = _telemetry(n_frames=2048, n_modes=2)
    path = save_result(res, tmp_path / "run.h5", telemetry=True)
    argv = ["design", str(path), "--controller", "omgi", "--out", str(tmp_path / "o.h5"),
            "--bounds", "none", "--robust-gain", "0.7,1.3",
            "--robust-latency=-0.3,0.3"]  # fmt: skip
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "MMset[1]" in text
    assert "certified over loop gain [0.7, 1.3] x latency change [-0.3, +0.3] frames" in text
    rows = [line.split() for line in text.splitlines() if line[:1].isdigit()]
    header = next(line.split() for line in text.splitlines() if "MMset[1]" in line)
    col = header.index("MMset[1]")
    for r in rows:  # the set's margin cannot exceed the nominal one
        assert float(r[col]) <= float(r[header.index("MM[1]")]) + 1e-3
    argv[-2] = "1.3,0.7"  # the gain interval, reversed
    assert main(argv) == 2
    assert "--robust-gain / --robust-latency: gain interval reversed" in capsys.readouterr().err


def test_read_telemetry_agrees_for_npz_and_results_file(tmp_path):
    res = _telemetry(n_frames=256, n_modes=2)
    np.savez(
        tmp_path / "t.npz",
        measurements=res.telemetry["measurements"],
        commands=res.telemetry["commands"],
    )
    save_result(res, tmp_path / "t.h5", telemetry=True)
    m1, u1, _ = read_telemetry(str(tmp_path / "t.npz"))
    m2, u2, info = read_telemetry(str(tmp_path / "t.h5"))
    np.testing.assert_array_equal(m1, m2)
    np.testing.assert_array_equal(u1, u2)
    assert info == {"fs": FS, "latency_frames": LATENCY}


@pytest.mark.parametrize(
    ("arrays", "expected"),
    [
        ({"meas": np.zeros((100, 2)), "commands": np.zeros((100, 2))}, "missing ['measurements']"),
        ({"measurements": np.zeros((100, 2)), "commands": np.zeros((100, 3))}, "same shape"),
        ({"measurements": np.zeros((2, 500)), "commands": np.zeros((2, 500))}, "transposed"),
        ({"measurements": np.full((100, 2), np.nan), "commands": np.zeros((100, 2))}, "NaN"),
    ],
)
def test_design_bad_telemetry_says_what_was_expected(tmp_path, capsys, arrays, expected):
    np.savez(tmp_path / "bad.npz", **arrays)
    argv = [
        "design",
        str(tmp_path / "bad.npz"),
        "--fs",
        "1000",
        "--latency",
        "0.5",
        "--out",
        str(tmp_path / "c.h5"),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert expected in err and "Traceback" not in err
    assert not (tmp_path / "c.h5").exists()


def test_design_unreadable_file(tmp_path, capsys):
    (tmp_path / "junk.h5").write_text("not a telemetry file")
    assert main(["design", str(tmp_path / "junk.h5"), "--fs", "1000", "--latency", "0.5"]) == 2
    err = capsys.readouterr().err
    assert "neither .npz nor HDF5" in err and "'measurements' and 'commands'" in err
    assert main(["design", str(tmp_path / "nope.npz"), "--fs", "1", "--latency", "0"]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_sweep_with_a_typo_fails_before_any_run(tmp_path, capsys):
    spec = tmp_path / "spec.toml"
    spec.write_text('cases = ["bright1-best"]\ncontrolers = ["integrator"]\n')
    assert main(["sweep", str(spec), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "controlers" in err and "Traceback" not in err
    assert not list((tmp_path / "out").glob("*.h5"))
    assert main(["sweep", str(tmp_path / "missing.toml")]) == 2
    assert "does not exist" in capsys.readouterr().err


# ------------------------------------------------------------------------------- run
@pytest.mark.slow
@pytest.mark.parametrize("scheme", ["single", "dcao"])
def test_run_writes_a_results_file_and_prints_its_summary(tmp_path, capsys, scheme):
    argv = [
        "run",
        "bright1-best",
        "--controller",
        "integrator",
        "--scheme",
        scheme,
        "--quick",
        "--seconds",
        "0.05",
        "--no-progress",
        "--out",
        str(tmp_path),
    ]
    assert main(argv) == 0
    out = capsys.readouterr().out
    path = tmp_path / f"bright1-best-integrator-{scheme}-seed0.h5"
    res = aocontrol.load_result(path)
    assert hasattr(res, "stages") == (scheme != "single")
    # The printed one-line summary is the file's content (3 decimals of the Strehl).
    strehl = float(out.split("Strehl ")[1].split(",")[0])
    assert strehl == pytest.approx(res.science.strehl, abs=5e-4)
    assert 0.0 < strehl <= 1.0
    assert (tmp_path / f"bright1-best-integrator-{scheme}-seed0_contrast.png").exists()


# ------------------------------------------------------------------------------- compare
def test_write_comparison_saves_table_csv_and_plots(tmp_path):
    # A comparison assembled from two real (short) loop runs with their results files: the
    # writer must save the table, a CSV row per cell with its figures, and the plots.
    import csv
    import dataclasses

    from aocontrol.sim import ScienceResult
    from aocontrol.study.cli import write_comparison
    from aocontrol.study.compare import CaseComparison, Cell

    radii = np.arange(1, 30) * 0.5
    cells = []
    for i, name in enumerate(("reference", "datadriven")):
        sci = ScienceResult(
            0.8 + 0.05 * i, 1e-4 / (i + 1), radii, 1e-3 * np.exp(-radii / (i + 1)), n_frames=10
        )
        res = dataclasses.replace(_telemetry(n_frames=512, n_modes=2, seed=i), science=sci)
        path = save_result(res, tmp_path / f"{name}.h5", settings={"case": "x"})
        cells.append(
            Cell(
                name,
                "standalone",
                sci.strehl,
                sci.mean_contrast_4_6,
                res.residual_rms,
                float("nan"),
                radii,
                sci.contrast_profile,
                {},
                path,
            )
        )
    # The vibration report as compare_case gives it for a case with a vibration.
    f = np.linspace(0.0, 500.0, 257)
    vibration = {
        "mode": 0,
        "scheme": "standalone",
        "psd": {c.controller: (f, 1.0 / (1.0 + f)) for c in cells},
        "freqs": f,
        "sensitivity2": {c.controller: np.full(f.shape, 0.5) for c in cells},
        "disturbance_psd": 1.0 / (1.0 + f**2),
    }
    comparison = CaseComparison(
        "bright1-best", tuple(cells), {"standalone": 0.4}, {}, vibration=vibration
    )
    lines = write_comparison(comparison, str(tmp_path))
    assert lines[0] == comparison.table()
    with open(tmp_path / "bright1-best_table.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["controller"] for r in rows] == ["reference", "datadriven"]
    assert [float(r["strehl"]) for r in rows] == pytest.approx([0.8, 0.85], rel=1e-12)
    pngs = (
        "bright1-best_contrast.png",
        "bright1-best_standalone_residual_psd.png",
        "bright1-best_tilt_psd.png",
        "bright1-best_sensitivity.png",
    )
    for png in pngs:
        assert (tmp_path / png).stat().st_size > 10_000, png
        assert f"plot: {tmp_path / png}" in lines
    # and the HTML report (its content: tests/test_report.py)
    report = tmp_path / "bright1-best_report.html"
    assert f"report: {report}" in lines
    assert "data:image/png;base64," in report.read_text()


def test_sweep_unreachable_scheduler_is_a_clear_error(tmp_path, capsys):
    import socket

    with socket.socket() as s:  # a free local port: nothing listens there once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    spec = tmp_path / "spec.toml"
    spec.write_text(
        'cases = ["bright1-best"]\ncontrollers = ["integrator"]\nschemes = ["single"]\n'
        "seeds = [0]\nseconds = 0.05\nquick = true\n"
    )
    argv = [
        "sweep",
        str(spec),
        "--scheduler",
        f"tcp://127.0.0.1:{port}",
        "--out",
        str(tmp_path / "out"),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "no Dask scheduler answered" in err and "Traceback" not in err
    assert not list((tmp_path / "out").glob("*.h5"))
