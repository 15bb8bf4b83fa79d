"""The robustness study's bookkeeping (benchmarks/bench_robustness.py, issue 29): the gain
retained, and the analysis's verdict on a run against exact margins and closed-loop poles."""

import importlib.util
import math
import pathlib

import numpy as np
import pytest

from aocontrol import loop_plant
from aocontrol.analysis import closed_loop_poles, margins
from aocontrol.controllers import Integrator

ROOT = pathlib.Path(__file__).resolve().parents[1]
FS = 1000.0


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location(
        "bench_robustness", ROOT / "benchmarks" / "bench_robustness.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _row(error, label, controller, residual, status="ok"):
    return {"case": "c", "error": error, "label": label, "controller": controller,
            "status": status, "residual_nm": residual}  # fmt: skip


def test_retained_is_the_gain_over_the_reference_under_the_error_over_the_nominal_one(bench):
    # Nominal: 1 - (3/4)^2 = 0.4375; under the error: 1 - (4/5)^2 = 0.36: retained 0.8229;
    # loss (4/3)^2. A diverged reference leaves the row without a retained gain.
    rows = [
        _row("nominal", "", "reference", 4.0),
        _row("nominal", "", "dd", 3.0),
        _row("gain", "x2", "reference", 5.0),
        _row("gain", "x2", "dd", 4.0),
        _row("gain", "x3", "reference", math.nan, status="diverged"),
        _row("gain", "x3", "dd", 4.5),
    ]
    bench._retained(rows)
    assert rows[3]["retained"] == pytest.approx(0.36 / 0.4375, rel=1e-12)
    assert rows[3]["loss"] == pytest.approx(16 / 9, rel=1e-12)
    assert math.isnan(rows[5]["retained"]) and rows[5]["loss"] == pytest.approx(2.25)
    # A controller no better than the reference on the nominal instrument retains nothing.
    worse = [_row("nominal", "", "reference", 4.0), _row("nominal", "", "w", 4.2),
             _row("gain", "x2", "reference", 5.0), _row("gain", "x2", "w", 4.0)]  # fmt: skip
    bench._retained(worse)
    assert math.isnan(worse[3]["retained"]) and worse[3]["loss"] == pytest.approx((4 / 4.2) ** 2)


@pytest.mark.parametrize(
    ("error", "magnitude", "overrides"),
    [
        ("latency", 0.3, {}),
        ("latency", 2.5, {}),
        ("loop gain", 1.3, {}),
        ("loop gain", 4.5, {}),
        (
            "gain at +0.3 frame",
            1.3,
            {"stage2.optical_gain_error": 1.3, "stage2.latency_error": 0.3},
        ),
        (
            "gain at +0.3 frame",
            3.0,
            {"stage2.optical_gain_error": 3.0, "stage2.latency_error": 0.3},
        ),
    ],  # fmt: skip
)
def test_the_analysis_verdict_agrees_with_the_poles_of_the_perturbed_loop(
    bench, error, magnitude, overrides
):
    # An integrator of gain 0.5 at latency 0.5 frame: the verdict is "certified" or
    # "stable" exactly when the loop with the error's gain and latency has its closed-loop
    # poles inside the circle (python-control's poles, an independent path).
    plant = loop_plant(FS, 0.5)
    bank = Integrator(0.5, fs=FS, n_modes=2)
    mar = [margins(plant, bank, mode=i) for i in range(2)]
    verdict = bench._predicted(plant, bank, mar, error, magnitude, overrides)
    gain, shift = bench._gain_and_latency(error, magnitude, overrides)
    poles = closed_loop_poles(loop_plant(FS, 0.5 + shift) * gain, bank.transfer_function(0))
    assert (verdict != "unstable") == (np.abs(poles).max() < 1.0)
    assert verdict in ("certified", "stable", "unstable")
    assert bench._predicted(plant, bank, mar, "DM lag", 1.0, {}) == ""
