"""The adaptive-control study (aocontrol.study.adapt) and its command ``aocontrol adapt``.

Quick scenes (24 stage-2 modes) and the modal-gain strategy (fast designs) keep these short;
the data-driven strategies are exercised by tests/test_adaptive.py and notebook 05.
"""

from __future__ import annotations

import numpy as np
import pytest

from aocontrol.sim.drift import Drift
from aocontrol.study import adapt
from aocontrol.study.adapt import SCENARIOS, AdaptRow, AdaptStudy, run_adapt, scenario_drift
from aocontrol.study.cli import main


def test_scenarios():
    # The two scripted scenarios of the issue: the wind doubles, the seeing worsens 1.5x,
    # both by the middle of the run; the stochastic one has the Paranal statistics.
    wind = scenario_drift("wind-doubles", 60.0, 0.4)
    assert wind.wind_at(0.0, 1)[0] == 1.0 and wind.wind_at(30.0, 1)[0] == 2.0
    seeing = scenario_drift("seeing-worsens", 60.0, 0.4)
    assert seeing.seeing_at(60.0) == 1.5 and seeing.wind_at(60.0, 1)[0] == 1.0
    stoch = scenario_drift("stochastic", 60.0, 0.4, seed=1)
    assert np.all(stoch.seeing > 0) and stoch.times[-1] >= 60.0
    assert set(SCENARIOS) >= {"wind-doubles", "seeing-worsens", "stochastic", "case"}
    with pytest.raises(ValueError, match="scenario must be one of"):
        scenario_drift("storm", 60.0, 0.4)
    with pytest.raises(ValueError, match=r"needs a case with an \[atmosphere.drift\]"):
        scenario_drift("case", 60.0, 0.4)


@pytest.mark.slow
def test_adaptive_modal_gain_study_runs_and_adapts():
    # 1.2 s at 3 kHz, the wind doubling between 0.24 and 0.6 s: the modal gain redesigned
    # every 0.2 s switches in certified banks, and the table reports every row.
    study = run_adapt(
        "bright1-best",
        scenario="wind-doubles",
        periods=(0.2,),
        windows=(0.2,),
        duration=1.2,
        strategies=("modal-gain",),
        latency=0.05,
        quick=True,
    )
    row = study.row("modal-gain")
    assert row.n_switches == 5 and row.n_rejected_banks == 0
    assert 0 < row.residual < 1e6 and "modal-gain" in study.table()
    # Every switch is 600 frames from the next: each is measured (50 frames either side) and
    # each midpoint between two is a reference; the ratios are energies' ratios, positive.
    assert row.transient_worst >= row.transient_median > 0
    assert row.reference_worst >= row.reference_median > 0 and 0 <= row.transient_p <= 1


def test_bad_study_arguments():
    with pytest.raises(ValueError, match="window must be in"):
        run_adapt("bright1-best", windows=(5.0,), duration=2.0, quick=True)
    with pytest.raises(ValueError, match="strategies must be among"):
        run_adapt("bright1-best", strategies=("pid",), quick=True)
    # Refused before any run (the fixed design's period is its window), naming both values.
    with pytest.raises(ValueError, match=r"latency=0.5 s and window=0.5 s"):
        run_adapt("bright1-best", windows=(1.0, 0.5), periods=(2.0,), latency=0.5, quick=True)
    with pytest.raises(ValueError, match=r"latency=0.5 s and period=0.5 s"):
        run_adapt("bright1-best", strategies=("oracle",), periods=(0.5,), latency=0.5, quick=True)


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--period", "-1"], "--period must be positive"),
        (["--window", "a,b"], "--window must be comma-separated"),
        (["--latency", "2", "--period", "1"], "--latency 2 s must be shorter"),
        (["--scenario", "storm", "--seconds", "1", "--window", "0.5"], "scenario must be one"),
    ],
)
def test_adapt_command_refuses_bad_input(argv, words, capsys):
    assert main(["adapt", "bright1-best", "--quick", *argv]) == 2
    assert words in capsys.readouterr().err


@pytest.mark.slow
def test_adapt_command_writes_table_hdf5_and_plot(tmp_path, capsys):
    # Two scenarios, the modal gain at two periods: the table's rows are in the HDF5 file
    # (xarray opens it, units kept) and the plot is written.
    import xarray as xr

    argv = ["adapt", "bright1-best", "--quick", "--scenario", "wind-doubles,seeing-worsens"]
    argv += ["--seconds", "1.2", "--period", "0.2,0.4", "--window", "0.2"]
    argv += ["--latency", "0.05", "--strategies", "modal-gain", "--out", str(tmp_path)]
    assert main(argv) == 0
    for scenario in ("wind-doubles", "seeing-worsens"):
        ds = xr.open_dataset(tmp_path / f"adapt_bright1-best_{scenario}.h5", engine="h5netcdf")
        assert list(ds["period"].values) == [0.2, 0.4]
        assert ds["residual"].attrs["units"] == "nm^2" and ds.attrs["scenario"] == scenario
        assert np.all(ds["n_switches"].values > 0)
        ds.close()
    assert (tmp_path / "adapt_bright1-best.png").stat().st_size > 1000


def test_the_predictor_strategies_train_once_or_every_period():
    # The multi-mode predictor on the quick scene (24 modes, history 20): trained on the
    # first 0.3-s window and kept, or retrained every 0.3 s; each training certified (the
    # study's margin) and switched in after the latency.
    study = run_adapt(
        "bright1-best",
        scenario="wind-doubles",
        periods=(0.3,),
        windows=(0.3,),
        duration=1.2,
        strategies=("eof-fixed", "eof"),
        latency=0.05,
        quick=True,
    )
    once, every = study.row("eof-fixed"), study.row("eof")
    assert once.n_switches == 1 and every.n_switches == 3
    assert once.n_rejected_banks == every.n_rejected_banks == 0
    assert 0 < every.residual < 1e6 and "eof" in study.table()


@pytest.mark.slow
def test_cascade_study_reports_residual_and_contrast():
    # Stage 2 of the bright1-best cascade (quick scene) with the adaptive modal gain, stage 1's
    # integrator in the loop: certified switches, a finite residual and both contrasts (raw
    # contrast of a perfect coronagraph: in (0, 1)).
    from aocontrol.study.adapt import run_adapt_cascade

    study = run_adapt_cascade(
        "bright1-best",
        periods=(0.3,),
        window=0.3,
        duration=0.9,
        strategies=("modal-gain",),
        latency=0.05,
    )
    (row,) = study.rows
    assert row.n_switches >= 2 and row.n_rejected_modes == 0
    assert 0 < row.residual < 1e6
    assert 0 < row.contrast < 1 and 0 < row.contrast_inner < 1
    assert "modal-gain" in study.table()


def test_bad_cascade_study_arguments():
    from aocontrol.study.adapt import run_adapt_cascade

    with pytest.raises(ValueError, match="strategies must be among"):
        run_adapt_cascade("bright1-best", strategies=("pid",))
    with pytest.raises(ValueError, match="scheme must be"):
        run_adapt_cascade("bright1-best", scheme="serial")
    with pytest.raises(ValueError, match=r"latency=0.5 s and period=0.5 s"):
        run_adapt_cascade("bright1-best", periods=(0.5,), latency=0.5)


def test_window_rule_and_seed_summary():
    # The window rules of the study and the adaptive loop's ratios over seeds (mean and
    # sample spread), on hand-made rows: no loop is run.
    from aocontrol.study.adapt import AdaptRow, AdaptStudy, seed_summary, window_rule

    assert [window_rule(r, 1.0) for r in ("1.5", "T", "max(T, 2)")] == [1.5, 1.0, 2.0]
    assert window_rule("max(T,2)", 5.0) == 5.0
    for bad in ("min(T,2)", "-1", "W"):
        with pytest.raises(ValueError, match="window rule must be"):
            window_rule(bad, 1.0)

    def study(seed, fixed, adaptive, oracle):
        rows = [
            AdaptRow("fixed", 1.0, 1.0, fixed, 0.0, 1, 0, 0, 0.0),
            AdaptRow("adaptive", 2.0, 1.0, adaptive, 0.0, 1, 0, 0, 0.0),
            AdaptRow("oracle", 2.0, 1.0, oracle, 0.0, 1, 0, 0, 0.0),
        ]
        return AdaptStudy("c", "wind-doubles", 60.0, tuple(rows), {"seed": seed})

    (row,) = seed_summary([study(0, 10.0, 8.0, 8.0), study(1, 20.0, 12.0, 10.0)])
    assert (row["period"], row["window"], row["seeds"]) == (2.0, 1.0, [0, 1])
    assert row["fixed"] == [0.8, 0.6] and row["oracle"] == [1.0, 1.2]
    assert row["fixed_mean"] == pytest.approx(0.7)
    assert row["oracle_std"] == pytest.approx(np.std([1.0, 1.2], ddof=1))
    (common,) = seed_summary([study(0, 10.0, 8.0, 8.0)], fixed_window=2.0)
    assert np.isnan(common["fixed_mean"])  # no fixed design at W = 2 s: no ratio
    (one,) = seed_summary([study(3, 10.0, 8.0, 8.0)], fixed_window=1.0)
    assert one["fixed"] == [0.8]
    assert np.isnan(one["fixed_std"])


def test_measure_from_is_checked():
    with pytest.raises(ValueError, match=r"measure_from must be in \[0, duration=2\) s"):
        run_adapt("bright1-best", windows=(1.0,), duration=2.0, measure_from=2.0, quick=True)


def _fake_run_adapt(calls):
    def fake(case, **kw):
        calls.append(kw)
        rows = tuple(
            AdaptRow(s, p, w, 1.0, 1.0, 3, 0, 0, 0.1, n_kept_modes=2)
            for s in kw["strategies"]
            for p in kw["periods"]
            for w in kw["windows"]
        )
        return AdaptStudy("bright1-best", kw["scenario"], kw["duration"], rows, {})

    return fake


def test_adapt_command_defaults_are_the_recommended_configuration(tmp_path, monkeypatch, capsys):
    # Issue 33: with no option the command runs the documented configuration, T = 2 s,
    # W = T, latency 0.5 s, and the study's design settings (quick: order 2, 24 points), and
    # --help says so; the designs kept worse than the running controller are one line.
    calls = []
    monkeypatch.setattr(adapt, "run_adapt", _fake_run_adapt(calls))
    argv = ["adapt", "bright1-best", "--quick", "--seconds", "20", "--strategies", "adaptive"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    (kw,) = calls
    assert kw["periods"] == (2.0,) and kw["windows"] == (2.0,) and kw["latency"] == 0.5
    assert kw["order"] == 2 and kw["design_options"] == {"n_grid": 24}
    out = capsys.readouterr().out
    assert "2 mode redesign(s) were worse than the running controller" in out
    # W = T at several periods: one window per period, not every pair.
    calls.clear()
    assert main([*argv, "--period", "1,5", "--out", str(tmp_path)]) == 0
    assert [(k["periods"], k["windows"]) for k in calls] == [((1.0,), (1.0,)), ((5.0,), (5.0,))]
    assert main([*argv[:2], "--seconds", "20", "--out", str(tmp_path)]) == 0
    assert calls[-1]["order"] == 5 and calls[-1]["design_options"] == {}
    with pytest.raises(SystemExit):
        main(["adapt", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for default in ("(default 2)", "(default T:", "(default 0.5;", "default 2 with --quick"):
        assert default in text, default


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--seconds", "-5"], "--seconds must be > 0"),
        (["--scenario", "case"], "needs a case with an [atmosphere.drift]"),
        (["--strategies", "adaptive,pid"], "unknown strategy 'pid'"),
        (["--seconds", "1"], "window must be in (0, duration=1)"),
    ],
)
def test_adapt_command_checks_everything_before_creating_its_folder(tmp_path, argv, words, capsys):
    out = tmp_path / "never"
    assert main(["adapt", "bright1-best", "--quick", *argv, "--out", str(out)]) == 2
    assert words in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
def test_run_adapt_takes_a_drift_of_several_knots():
    # Two paths that must agree: the named scenario and the same history given as a Drift
    # (the API a drift of several knots takes); a different drift changes the residual.
    kw = dict(
        periods=(0.2,),
        windows=(0.2,),
        duration=1.0,
        strategies=("modal-gain",),
        latency=0.05,
        quick=True,
    )
    named = run_adapt("bright1-best", scenario="wind-doubles", **kw)
    same = run_adapt("bright1-best", scenario=Drift.ramp(0.2, 0.5, wind=2.0), **kw)
    assert same.row("modal-gain").residual == named.row("modal-gain").residual
    knots = Drift([0.1, 0.3, 0.6, 0.6], [1.0, 1.0, 1.0, 1.5], [1.0, 2.0, 2.0, 2.0], name="mix")
    mixed = run_adapt("bright1-best", scenario=knots, **kw)
    assert mixed.scenario == "mix" and mixed.settings["drift"][0] == [0.1, 0.3, 0.6, 0.6]
    assert mixed.row("modal-gain").residual > 1.05 * named.row("modal-gain").residual
