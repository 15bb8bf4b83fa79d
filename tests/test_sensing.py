"""The sensor protocol in the loop: diffractive vs linear sensors, optical-gain tracking."""

import logging

import numpy as np
import pytest

from aocontrol.controllers import Integrator
from aocontrol.sim.atmosphere import Atmosphere, Layer
from aocontrol.sim.dm import DeformableMirror
from aocontrol.sim.loop import (
    DiffractiveSensor,
    DitherGainTracker,
    LinearModalSensor,
    ModalTimeSeries,
    Stage,
    TurbulenceSource,
    run_cascade,
    run_loop,
)
from aocontrol.sim.modes import kl_basis
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.sim.wfs import PyramidWFS, calibrate, optical_gains

FS = 3000.0


@pytest.fixture(scope="module")
def small_pyramid():
    # Small and cheap: 16-px pupil, 8x8 pyramid pixels, 12 modulation points, 6 KL modes.
    pupil = vlt_pupil(16)
    basis = kl_basis(DeformableMirror(pupil, n_actuators=9), 6, r0=0.15)
    pyr = PyramidWFS(pupil, 1.04e-6, n_subapertures=8, modulation=3.0, n_modulation_points=12)
    cal = calibrate(pyr, basis, amplitude=2.0, method="derivative")
    return pupil, basis, pyr, cal


def _red_modes(n_frames, n_modes, seed, rms, pole=0.99):
    """A red (AR(1)) modal disturbance of the given RMS per mode."""
    from scipy import signal

    w = np.random.default_rng(seed).standard_normal((n_frames, n_modes))
    d = signal.lfilter([1.0], [1.0, -pole], w, axis=0)
    return d * (rms / d.std(axis=0))


# ------------------------------------------------------------------------ gain tracking
@pytest.mark.parametrize("latency", [0.83, 1.5])
def test_tracked_gains_converge_to_the_sensor_gains(latency):
    # Oracle: a linear sensor of known optical gains g; the dither's instrumental-variable
    # estimate is unbiased whatever the controller does, so it converges to g. Statistical
    # error: sigma_m / (a sqrt(N)) ~ 1.5 / (1 sqrt(24000)) ~ 1 %, tolerance 4 % (~4 sigma).
    g = np.array([0.45, 0.8, 1.0, 1.3])
    n = 24000
    tracker = DitherGainTracker(amplitude=1.0, update_every=1000, memory=1e9)
    stage = Stage(
        Integrator(0.3, fs=FS, n_modes=4), LinearModalSensor(g, 0.5), latency, gain_tracker=tracker
    )
    res = run_loop(stage, ModalTimeSeries(_red_modes(n, 4, 1, 3.0), fs=FS), n, rng=2)
    est = np.array(res.metadata["gain_tracker_estimate"])
    np.testing.assert_allclose(est, g, rtol=0.04)
    # It converges: the first estimate is further from g than the last (a check that can fail).
    first = np.array(res.metadata["gain_tracker_history"][0])
    assert np.max(np.abs(first / g - 1)) > np.max(np.abs(est / g - 1))
    assert res.metadata["gain_tracker_rejected"] == [0, 0, 0, 0]


def test_tracked_compensation_restores_the_loop_gain():
    # Invariant: with the estimate compensated, a sensor of gain 0.5 and a controller of gain
    # 0.4 reject like a unit-gain sensor with the same controller (in the steady state).
    n = 30000
    d = _red_modes(n, 2, 4, 40.0, pole=0.999)
    tracker = DitherGainTracker(amplitude=0.3, update_every=500, initial=0.5)

    def run(sensor, tr):
        stage = Stage(Integrator(0.4, fs=FS, n_modes=2), sensor, 0.83, gain_tracker=tr)
        return run_loop(stage, ModalTimeSeries(d, fs=FS), n, rng=3, settle_frames=5000)

    tracked = run(LinearModalSensor(0.5, 0.0), tracker)
    unit = run(LinearModalSensor(1.0, 0.0), DitherGainTracker(amplitude=0.3, update_every=500))
    raw = run(LinearModalSensor(0.5, 0.0), None)
    ratio = tracked.residual_variance / unit.residual_variance
    np.testing.assert_allclose(ratio, 1.0, rtol=0.1)
    assert np.all(raw.residual_variance > 1.3 * unit.residual_variance)  # halved loop gain


def test_a_diverging_tracker_is_reported_and_not_used(caplog):
    # Estimates outside the accepted bounds (true gain 0.5, bounds from 0.9) are rejected:
    # the compensation keeps its initial value, the rejections are counted and logged.
    n = 4000
    tracker = DitherGainTracker(amplitude=1.0, update_every=500, bounds=(0.9, 3.0))
    stage = Stage(
        Integrator(0.3, fs=FS, n_modes=2), LinearModalSensor(0.5, 0.2), 0.83, gain_tracker=tracker
    )
    with caplog.at_level(logging.WARNING, logger="aocontrol.sim._gain_tracking"):
        res = run_loop(stage, ModalTimeSeries(_red_modes(n, 2, 5, 2.0), fs=FS), n, rng=1)
    assert res.metadata["gain_tracker_rejected"] == [8, 8]
    assert res.metadata["gain_tracker_estimate"] == [1.0, 1.0]
    assert "estimate rejected" in caplog.text


def test_probed_modes_and_interpolation():
    # Two dithered modes of four: the others are interpolated linearly in mode index.
    g = np.array([0.4, 0.6, 0.8, 1.0])
    n = 20000
    tracker = DitherGainTracker(amplitude=1.0, update_every=1000, memory=1e9, modes=[0, 3])
    stage = Stage(
        Integrator(0.3, fs=FS, n_modes=4), LinearModalSensor(g, 0.3), 0.83, gain_tracker=tracker
    )
    res = run_loop(stage, ModalTimeSeries(_red_modes(n, 4, 6, 2.0), fs=FS), n, rng=4)
    est = np.array(res.metadata["gain_tracker_estimate"])
    np.testing.assert_allclose(est[[0, 3]], g[[0, 3]], rtol=0.05)
    np.testing.assert_allclose(est[1:3], np.interp([1, 2], [0, 3], est[[0, 3]]), rtol=1e-12)
    # The un-dithered modes carry no dither in their commands.
    assert res.metadata["gain_tracker_rejected"] == [0, 0, 0, 0]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"amplitude": 0.0}, "amplitude must be > 0"),
        ({"update_every": 3}, "update_every must be an integer >= 10"),
        ({"memory": 0.5}, "memory must be >= 1"),
        ({"bounds": (1.0, 0.5)}, "bounds must be"),
        ({"initial": 5.0}, "initial must be within bounds"),
        ({"modes": [3, 1]}, "modes must be increasing"),
        ({"precision": 1.5}, "precision must be in"),
    ],
)
def test_tracker_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        DitherGainTracker(**kwargs)


def test_tracker_needs_rng_and_matching_sizes():
    d = ModalTimeSeries(np.zeros((100, 2)), fs=FS)
    stage = Stage(Integrator(0.3, fs=FS, n_modes=2), gain_tracker=DitherGainTracker())
    with pytest.raises(ValueError, match="rng is required .*optical-gain tracker"):
        run_loop(stage, d, 100)
    bad = Stage(Integrator(0.3, fs=FS, n_modes=2), gain_tracker=DitherGainTracker(modes=[5]))
    with pytest.raises(ValueError, match="modes must be < n_modes=2"):
        run_loop(bad, d, 100, rng=0)
    with pytest.raises(TypeError, match="gain_tracker must be a DitherGainTracker"):
        Stage(Integrator(0.3, fs=FS), gain_tracker="dither")


# ------------------------------------------------------------ diffractive vs linear sensor
class _ModalPhase:
    """Phase inside a basis (no fitting error: nothing for the pyramid to alias)."""

    def __init__(self, basis, coeffs, fs):
        self.fs = fs
        self.phase = coeffs @ basis.modes
        self._pos = 0

    def phase_vectors(self, n):
        out = self.phase[self._pos : self._pos + n]
        self._pos += n
        return out


@pytest.mark.parametrize("scheme", ["standalone", "dcao"])
def test_diffractive_stage_2_follows_the_linear_one_on_a_weak_residual(small_pyramid, scheme):
    # Two implementations: on a weak residual inside the calibrated basis (~3 nm, 0.02 rad
    # at 1.04 um) the calibrated pyramid measures the modal residual to second order in the
    # phase, so the cascade with the diffractive stage 2 has the residual statistics of the
    # cascade with a unit-gain linear stage 2. Tolerance 2 % on each mode's residual variance
    # (second-order terms ~ phase^2 ~ 5e-4; the difference is between two runs of the same
    # realisation, not a statistical one).
    pupil, basis, pyr, cal = small_pyramid
    n = 900
    coeffs = _red_modes(n, basis.n_modes, 7, 3.0)

    def run(sensor):
        s1 = Stage(
            Integrator(0.3, fs=1000.0, n_modes=basis.n_modes),
            latency_frames=0.84,
            basis=basis,
            name="SAXO",
        )
        s2 = Stage(
            Integrator(0.4, fs=FS, n_modes=basis.n_modes), sensor, 0.83, basis=basis, name="SAXO+"
        )
        return run_cascade(
            s1, s2, _ModalPhase(basis, coeffs, FS), n, scheme=scheme, settle_frames=90
        )

    lin = run(LinearModalSensor(1.0, 0.0)).stages[1]
    dif = run(DiffractiveSensor(pyr, cal.recon)).stages[1]
    np.testing.assert_allclose(dif.residual_variance, lin.residual_variance, rtol=0.02)
    assert np.max(lin.residual_variance) > 0.1  # not a trivially flat run


def test_diffractive_stage_1_integrates_its_frame(small_pyramid):
    # Stage 1 (a third of the rate) with the pyramid: its WFS sees the mean residual map of
    # its frame, which on a weak residual inside the basis measures the frame-mean modal
    # residual: the same statistics as a unit-gain linear stage 1 (tolerance as above).
    pupil, basis, pyr, cal = small_pyramid
    n = 900
    coeffs = _red_modes(n, basis.n_modes, 8, 3.0)

    def run(sensor):
        s1 = Stage(
            Integrator(0.4, fs=1000.0, n_modes=basis.n_modes),
            sensor,
            0.84,
            basis=basis,
            name="SAXO",
        )
        s2 = Stage(Integrator(0.3, fs=FS, n_modes=basis.n_modes), latency_frames=0.83, basis=basis)
        res = run_cascade(
            s1, s2, _ModalPhase(basis, coeffs, FS), n, scheme="standalone", settle_frames=90
        )
        return res.stages[0]

    lin = run(LinearModalSensor(1.0, 0.0))
    dif = run(DiffractiveSensor(pyr, cal.recon))
    np.testing.assert_allclose(dif.residual_variance, lin.residual_variance, rtol=0.02)
    assert np.max(lin.residual_variance) > 0.1


def test_diffractive_optical_gains_measured_in_the_loop(small_pyramid):
    # Oracle: on a strong residual (turbulence far beyond the 6 corrected modes: ~0.4 um of
    # fitting error, the pyramid well out of its linear range) the optical gains measured in
    # the loop by the dither equal diag(R D_res) averaged around the loop's own residual
    # screens (aocontrol.sim.wfs.optical_gains). Tolerance 10 %: the dither estimate's
    # statistical error (~3-5 % here: the aliased fitting error acts as a measurement noise)
    # and a few screens for the average.
    pupil, basis, pyr, cal = small_pyramid
    n = 3000

    class _Keep:
        def __init__(self):
            self.maps = []

        def add(self, maps):
            self.maps.append(np.array(maps))

        def result(self):
            return np.concatenate(self.maps)

    atm = Atmosphere(pupil, 0.3, [Layer(0.0, 1.0, 10.0, 25.0)], FS, rng=3)
    keep = _Keep()
    tracker = DitherGainTracker(amplitude=8.0, update_every=500, memory=1e9)
    stage = Stage(
        Integrator(0.3, fs=FS, n_modes=basis.n_modes),
        DiffractiveSensor(pyr, cal.recon),
        0.83,
        basis=basis,
        gain_tracker=tracker,
    )
    res = run_loop(
        stage,
        TurbulenceSource(atm, basis),
        n,
        rng=5,
        science=keep,
        science_every=300,
        settle_frames=100,
    )
    maps = res.science
    assert np.sqrt(np.mean(pupil.to_vector(maps) ** 2)) > 300.0  # a strong residual [nm]
    og = optical_gains(pyr, basis, maps, recon=cal.recon, method="derivative")
    assert np.all(og < 0.95)  # the gains did fall (the check is not around a flat wavefront)
    est = np.array(res.metadata["gain_tracker_estimate"])
    np.testing.assert_allclose(est, og, rtol=0.1)


# ------------------------------------------------------------------ the study's settings
def test_case_sensor_keys_are_validated():
    from aocontrol.study.cases import CaseError, apply_overrides, load_case

    case = load_case("bright1-best")
    assert (case.stage2.sensor, case.stage2.optical_gain) == ("linear", "calibrated")
    c = apply_overrides(case, {"stage2.sensor": "diffractive", "stage2.optical_gain": "tracked"})
    assert (c.stage2.sensor, c.stage2.optical_gain) == ("diffractive", "tracked")
    with pytest.raises(
        CaseError, match=r"stage2.sensor.*must be one of \['linear', 'diffractive'\]"
    ):
        apply_overrides(case, {"stage2.sensor": "pyramid"})
    with pytest.raises(CaseError, match=r"stage1.sensor.*needs a pyramid WFS"):
        apply_overrides(case, {"stage1.sensor": "diffractive"})
    with pytest.raises(CaseError, match=r"stage2.optical_gain.*must be one of"):
        apply_overrides(case, {"stage2.optical_gain": "auto"})


@pytest.mark.slow
def test_scene_loop_sensors_per_setting():
    from aocontrol.study.scene import build_scene

    st = build_scene("bright1-best", quick=True).stage2
    og = st.calibrated_gains
    lin, tr = st.loop_sensor("linear", "calibrated")
    assert tr is None and np.all(lin.optical_gain == 1.0)
    raw, _ = st.loop_sensor("linear", "none")
    np.testing.assert_array_equal(raw.optical_gain, og)  # the loop sees the gains
    np.testing.assert_allclose(raw.noise_std, lin.noise_std * og)
    dif, _ = st.loop_sensor("diffractive", "calibrated")
    np.testing.assert_array_equal(dif.gain_compensation, og)
    assert dif.photons == st.photons and dif.wfs is st.wfs
    dif_raw, tracker = st.loop_sensor("diffractive", "tracked")
    assert dif_raw.gain_compensation is None
    np.testing.assert_allclose(tracker.initial, og)
    assert tracker.modes[0] == 0 and tracker.modes[-1] == st.n_modes - 1
    with pytest.raises(ValueError, match="optical_gain must be one of"):
        st.loop_sensor("linear", "adaptive")
    with pytest.raises(ValueError, match="sensor='diffractive' needs a pyramid stage"):
        build_scene("bright1-best", quick=True).stage1.loop_sensor("diffractive")


def test_sweep_spec_takes_the_sensor_settings():
    from aocontrol.study.sweep import SweepSpec

    spec = SweepSpec.from_dict(
        {
            "cases": ["bright1-best"],
            "controllers": ["reference"],
            "schemes": ["standalone"],
            "seeds": [0],
            "overrides": {"stage2.sensor": ["linear", "diffractive"]},
        }
    )
    runs = spec.runs()
    assert [r.settings["overrides"]["stage2.sensor"] for r in runs] == ["linear", "diffractive"]
    assert runs[0].hash != runs[1].hash


@pytest.mark.slow
def test_run_configuration_with_the_diffractive_pyramid(tmp_path):
    # The whole chain in diffractive mode (quick scene, reference integrator, short run):
    # the pyramid in the loop, the optical-gain tracker, the settings recorded.
    from aocontrol.study.compare import run_configuration

    out = run_configuration(
        "bright1-best",
        controller="reference",
        scheme="standalone",
        seconds=0.05,
        quick=True,
        sensor="diffractive",
        optical_gain="tracked",
    )
    assert out.settings["case_values"]["stage2"]["sensor"] == "diffractive"
    meta = out.result.stages[1].metadata
    assert meta["gain_tracker"] == "dither" and meta["gain_tracker_updates"] >= 1
    assert 0.0 < out.summary["strehl"] < 1.0


@pytest.mark.slow
def test_two_pass_optical_gains_are_those_of_the_closed_loop_residual():
    # The closed-loop residual (fitting error plus servo-lag and noise) is larger than the
    # fitting error alone, so the two-pass gains are lower than the fitting-error ones
    # (the pyramid's gains fall as the residual grows); they are what optical_gains gives
    # around the first pass's residual maps by construction, so the check is on the physics.
    from aocontrol.study.compare import two_pass_scene
    from aocontrol.study.scene import build_scene

    scene = build_scene("red5-best", quick=True)
    two = two_pass_scene(scene, "standalone", scene.case.stage2.gain, seconds=0.05, seed=3)
    og0, og1 = scene.stage2.calibrated_gains, two.stage2.calibrated_gains
    assert np.median(og1) < np.median(og0)
    np.testing.assert_allclose(two.stage2.sensor.noise_std * og1, scene.stage2.raw_noise_std)
    assert two.stage1 is scene.stage1


def test_an_imprecise_estimate_is_not_used():
    # A dither far below the measurement noise: after 2000 frames the estimate's relative
    # error (~ sigma_m / (a sqrt(N)) ~ 10 / (0.2 * 45) ~ 1) is far above 10 %: the tracker
    # keeps its initial gains instead of compensating with a random number.
    n = 2000
    tracker = DitherGainTracker(amplitude=0.2, update_every=500, initial=0.7)
    stage = Stage(
        Integrator(0.3, fs=FS, n_modes=2),
        LinearModalSensor(0.5, 10.0),
        0.83,
        gain_tracker=tracker,
    )
    res = run_loop(stage, ModalTimeSeries(_red_modes(n, 2, 9, 2.0), fs=FS), n, rng=1)
    assert res.metadata["gain_tracker_estimate"] == [0.7, 0.7]
    assert res.metadata["gain_tracker_imprecise_modes"] == 2
    assert res.metadata["gain_tracker_rejected"] == [0, 0]


def test_cli_sensor_options(capsys):
    from aocontrol.study.cli import main

    for command in ("run", "compare"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        out = capsys.readouterr().out
        assert "--sensor {linear,diffractive}" in out
        assert "--optical-gain {none,calibrated,tracked,two-pass}" in out
    with pytest.raises(SystemExit) as info:
        main(["run", "bright1-best", "--controller", "reference", "--scheme", "dcao",
              "--sensor", "pyramid"])  # fmt: skip
    assert info.value.code == 2
    assert "invalid choice: 'pyramid'" in capsys.readouterr().err
