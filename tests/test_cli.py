"""The main job: the demo and the command line."""

import subprocess
import sys

import pytest

from aocontrol.study.cli import main
from aocontrol.study.demo import run_demo


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


def test_cli_demo_prints_margins(tmp_path, capsys):
    assert main(["demo", "--output", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "stable" in out and "rejection.png" in out


def test_cli_bad_input_is_a_clear_error(tmp_path, capsys):
    assert main(["demo", "--output", str(tmp_path), "--fs", "-3"]) == 2
    assert "fs must be a finite number > 0, got -3.0" in capsys.readouterr().err


@pytest.mark.slow
def test_python_dash_m_entry_point(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "aocontrol", "demo", "--output", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "rejection.png").exists()
