"""design_from_telemetry: telemetry in, certified controller out (and the one registry)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import signal

from aocontrol.analysis import margins, residual_variance
from aocontrol.plant import loop_plant
from aocontrol.study import compare
from aocontrol.synthesis import (
    CONTROLLERS,
    ControllerSpec,
    DesignInputs,
    LoopTelemetry,
    TelemetryDesign,
    design_from_telemetry,
    disturbance_from_telemetry,
    optimal_modal_gain,
    register_controller,
)

FS = 1000.0
LATENCY = 0.3
N_MODES = 3


@pytest.fixture(scope="module")
def telemetry():
    """Open-loop-like telemetry (u = 0): AR(2) disturbances of three widths plus white noise."""
    rng = np.random.default_rng(16)
    n = 8192
    poles = np.array([0.995, 0.98, 0.9])
    d = np.column_stack(
        [
            signal.lfilter([1.0], np.convolve([1, -p], [1, -p]), rng.normal(size=n)) * 0.05
            for p in poles
        ]
    )
    m = d + 0.5 * rng.normal(size=(n, N_MODES))
    return LoopTelemetry(m, np.zeros_like(m), FS, LATENCY, source="synthetic")


@pytest.fixture(scope="module")
def report(telemetry):
    return design_from_telemetry(telemetry, "datadriven", options={"order": 3, "n_jobs": 1})


def test_design_meets_the_margin_and_lies_between_the_bounds(report):
    # Oracles: (1) every loop is certified stable with min |1 + GK| >= 0.5 (the design's
    # constraint; 1e-3 for its verification tolerance); (2) no causal linear controller beats
    # the Wiener bound, and none meeting the margin beats the constrained bound (up to its
    # FIR truncation and constraint-grid relaxation: 2 %); the constrained bound is above
    # the Wiener bound; (3) the data-driven design starts from the optimal-gain integrator,
    # so it is not worse than the reference (rounding).
    assert isinstance(report, TelemetryDesign) and report.n_modes == N_MODES
    assert report.stable.all()
    assert np.all(report.achieved_modulus_margin >= 0.5 * (1 - 1e-3))
    assert np.all(report.constrained_variance >= report.wiener_variance * (1 - 1e-6))
    assert np.all(report.residual_variance >= report.constrained_variance * (1 - 0.02))
    assert np.all(report.residual_variance <= report.reference_residual_variance * (1 + 1e-9))
    assert report.estimate.method == "prewhitened"
    rows = report.rows()
    assert [r["mode"] for r in rows] == [0, 1, 2]
    assert all(r["ratio_to_constrained"] >= 0.98 for r in rows)
    assert set(report.timings) >= {"estimate", "design", "margins", "bounds"}


def test_pipeline_equals_its_steps_done_by_hand(telemetry, report):
    # Two paths: the estimate, the registry's design, the margins and the residuals computed
    # one by one give the report's numbers exactly.
    plant = loop_plant(FS, LATENCY)
    est = disturbance_from_telemetry(telemetry.measurements, telemetry.commands, plant)
    np.testing.assert_array_equal(est.psd, report.estimate.psd)
    ref = optimal_modal_gain(plant, est.freqs, est.psd, est.noise_psd, modulus_margin=0.5)
    np.testing.assert_array_equal(ref.gain, report.reference.gain)
    var = residual_variance(plant, report.controller, est.freqs, est.psd, est.noise_psd)
    np.testing.assert_array_equal(var, report.residual_variance)
    assert margins(plant, report.controller, mode=1) == report.margins[1]
    assert report.details is not None and report.details.controller is report.controller


def test_plain_welch_is_an_option_and_a_psd_estimate_is_accepted(telemetry):
    rep = design_from_telemetry(telemetry, "omgi", estimator="welch", bounds=())
    assert rep.estimate.method == "welch"
    assert np.all(np.isnan(rep.wiener_variance)) and np.isnan(rep.constrained_rms)
    again = design_from_telemetry(rep.estimate, "omgi", latency_frames=LATENCY, bounds=())
    np.testing.assert_array_equal(again.controller.gain, rep.controller.gain)
    # A (measurements, commands) pair with the rate and latency given.
    pair = design_from_telemetry(
        (telemetry.measurements, telemetry.commands),
        "integrator",
        fs=FS,
        latency_frames=LATENCY,
        reference_gain=0.3,
        bounds=(),
    )
    np.testing.assert_array_equal(pair.controller.gain, np.full(N_MODES, 0.3))


def test_one_registry_for_study_and_synthesis(telemetry):
    # The comparison's registry is the control layer's: a controller registered through
    # study is designed by design_from_telemetry.
    assert compare.CONTROLLERS is CONTROLLERS and compare.DesignInputs is DesignInputs
    spec = ControllerSpec("half-integrator-test", lambda inp: CONTROLLERS["reference"].design(
        dataclasses.replace(inp, reference_gain=0.25)))  # fmt: skip
    compare.register_controller(spec)
    try:
        rep = design_from_telemetry(telemetry, "half-integrator-test", bounds=())
        np.testing.assert_array_equal(rep.controller.gain, np.full(N_MODES, 0.25))
    finally:
        del CONTROLLERS["half-integrator-test"]
    with pytest.raises(ValueError, match="already registered"):
        register_controller(CONTROLLERS["omgi"])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"controller": "pid"}, r"controller must be one of \[.*'datadriven'.*\], got 'pid'"),
        ({"options": {"order": 3}}, r"options \['order'\] are not options of controller 'omgi'"),
        ({"bounds": ("hinf",)}, r"bounds must be among \['wiener', 'constrained'\]"),
        ({"modulus_margin": 1.5}, r"modulus_margin must be in \(0.0, 1.0\], got 1.5"),
        ({"estimator": "periodogram"}, r"method must be one of"),
    ],
)
def test_bad_arguments_are_named(telemetry, kwargs, match):
    args = {"controller": "omgi", "bounds": (), **kwargs}
    with pytest.raises(ValueError, match=match):
        design_from_telemetry(telemetry, **args)


def test_missing_latency_names_the_telemetry():
    m = np.zeros((256, 2))
    with pytest.raises(ValueError, match=r"latency_frames.*\(lab bench\)"):
        design_from_telemetry(LoopTelemetry(m, m, FS, None, source="lab bench"), "omgi")
    with pytest.raises(ValueError, match="fs"):
        design_from_telemetry((m, m), "omgi")
    with pytest.raises(ValueError, match=r"commands of run\.fits.*same shape"):
        LoopTelemetry(m, np.zeros((256, 3)), FS, 0.5, source="run.fits")


def test_report_checks_its_shapes(report):
    with pytest.raises(ValueError, match=r"wiener_variance must have shape \(3,\)"):
        dataclasses.replace(report, wiener_variance=np.zeros(2))


def test_a_mode_whose_margins_fail_is_nan_not_made_up(telemetry, monkeypatch, caplog):
    # analysis.margins raising for one mode (as it did for integrators of gain < 4e-4, a
    # gain crossover inside its first grid interval) must not stop the design nor invent a
    # margin: that mode reports nan margins, the is_stable verdict, and fails meets_margin.
    from aocontrol.synthesis import _pipeline

    real = _pipeline.margins

    def flaky(plant, bank, *, mode=0, **kw):
        if mode == 1:
            raise ValueError("The function value at x=0.0 is NaN")
        return real(plant, bank, mode=mode, **kw)

    monkeypatch.setattr(_pipeline, "margins", flaky)
    with caplog.at_level("WARNING", logger="aocontrol.synthesis._pipeline"):
        rep = design_from_telemetry(telemetry, "omgi", bounds=())
    assert np.isnan(rep.achieved_modulus_margin[1]) and rep.stable[1]
    assert list(rep.meets_margin) == [True, False, True]
    assert "modes [1]" in caplog.text


def test_robust_margins_are_reported_for_any_controller(telemetry):
    # Issue 29: the same robustness figure for every controller. Oracle: each reported value
    # equals robust_margin on the design's plant and bank, and at the box's corners the loop's
    # modulus margin (exact, margins()) is not below it; the nominal margin bounds it above.
    from aocontrol.analysis import UncertaintySet, robust_margin
    from aocontrol.plant import with_latency

    uset = UncertaintySet(gain=(0.8, 1.2), latency=(-0.2, 0.2))
    rep = design_from_telemetry(telemetry, "omgi", bounds=(), uncertainty=uset)
    assert rep.uncertainty == uset and len(rep.robust_margins) == N_MODES
    for i, r in enumerate(rep.robust_margins):
        direct = robust_margin(rep.plant, rep.controller, uset, mode=i)
        assert r.value == pytest.approx(direct.value, rel=1e-12)
        assert r.value <= rep.margins[i].modulus_margin + 1e-12
        for k in uset.gain:
            for d in uset.latency:
                corner = with_latency(rep.plant, LATENCY + d) * k
                assert margins(corner, rep.controller, mode=i).modulus_margin >= r.value - 1e-9
    ref = [r.value for r in rep.reference_robust_margins]
    assert rep.rows()[0]["robust_margin"] == pytest.approx(rep.robust_modulus_margin[0])
    assert np.all(np.isfinite(ref))
    plain = design_from_telemetry(telemetry, "omgi", bounds=())
    assert plain.robust_margins is None and np.isnan(plain.rows()[0]["robust_margin"])
    with pytest.raises(TypeError, match="uncertainty must be an UncertaintySet"):
        design_from_telemetry(telemetry, "omgi", bounds=(), uncertainty=(0.8, 1.2))


def test_margins_and_bounds_on_workers_equal_one_process(telemetry, monkeypatch):
    # Invariant (issue 34): steps 3 and 4 run per mode in chunks on worker processes; each
    # mode's figures are the same arithmetic on the same row whatever the chunking, so the
    # report is bit for bit the one computed in this process in one chunk.
    from aocontrol.synthesis import _pipeline

    est = disturbance_from_telemetry(
        telemetry.measurements, telemetry.commands, loop_plant(FS, LATENCY)
    )
    kw = {"plant": loop_plant(FS, LATENCY), "bounds": ("wiener", "constrained"), "n_taps": 32}
    one = design_from_telemetry(est, "omgi", n_jobs=1, **kw)
    monkeypatch.setattr(_pipeline, "_CERTIFY_CHUNK", 1)  # three chunks, two workers
    split = design_from_telemetry(est, "omgi", n_jobs=2, **kw)
    for name in ("wiener_variance", "constrained_variance", "residual_variance"):
        assert np.array_equal(getattr(one, name), getattr(split, name)), name
    pairs = zip(
        one.margins + one.reference_margins, split.margins + split.reference_margins, strict=True
    )
    for a, b in pairs:
        assert dataclasses.astuple(a) == dataclasses.astuple(b) or repr(a) == repr(b)
    # Twin: a changed bound is seen by the same comparison.
    assert not np.array_equal(one.constrained_variance, one.constrained_variance * (1 + 1e-15))


def test_modes_sharing_a_filter_get_its_margins(telemetry):
    # Steps 3 and 4 certify a filter that several modes share once (a data-driven bank gives
    # neighbouring modes one controller). Oracle: every mode's margins are those of
    # analysis.margins on its own row, bit for bit, on a bank where modes 0 and 2, 1 and 4
    # share filters and the three filters' margins differ (a wrong mode-to-filter map is
    # seen).
    est = disturbance_from_telemetry(
        telemetry.measurements, telemetry.commands, loop_plant(FS, LATENCY)
    )
    idx = [0, 1, 0, 2, 1]
    dup = dataclasses.replace(
        est,
        psd=est.psd[idx],
        noise_psd=np.asarray(est.noise_psd)[idx],
        pol_psd=est.pol_psd[idx],
        pseudo_open_loop=est.pseudo_open_loop[:, idx],
    )
    plant = loop_plant(FS, LATENCY)
    rep = design_from_telemetry(dup, "omgi", plant=plant, bounds=(), n_jobs=1)
    bank_b, bank_a = rep.controller.b, rep.controller.a
    rows = {(bank_b[i].tobytes(), bank_a[i].tobytes()) for i in range(len(idx))}
    assert len(rows) == 3
    for name in ("margins", "reference_margins"):
        bank = rep.controller if name == "margins" else rep.reference
        got = getattr(rep, name)
        for i in range(len(idx)):
            assert repr(got[i]) == repr(margins(plant, bank, mode=i)), (name, i)
        assert len({repr(m) for m in got}) == 3
