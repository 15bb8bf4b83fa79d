"""Model errors in the simulator (issue 29, part 2): each one a setting of the run.

Oracles: the measured rejection of a loop whose instrument differs from the model is |S|^2
of the *true* plant with the controller designed on the nominal one (latency error: the true
latency's plant; DM response: ``G H``; optical-gain error: ``og G``); neutral settings give the
nominal run bit for bit.
"""

import numpy as np
import pytest
from scipy import signal

from aocontrol import loop_plant
from aocontrol.analysis import sensitivity
from aocontrol.controllers import IIRBank, Integrator
from aocontrol.sim import DMResponse, OpticalGainError, misregistration_matrix, vlt_pupil
from aocontrol.sim.dm import DeformableMirror, ModalDM
from aocontrol.sim.loop import LinearModalSensor, ModalTimeSeries, Stage, run_loop
from aocontrol.sim.modes import kl_basis

FS = 3000.0
N_FRAMES = 16384


def _white(n_frames, n_modes, seed=0):
    return np.random.default_rng(seed).standard_normal((n_frames, n_modes))


def _bank(n_modes=3):
    # A data-driven-like filter (a lead on an integrator) at three gains.
    g = np.linspace(0.6, 1.0, n_modes)[:, None]
    return IIRBank(np.array([0.45, -0.15]) * g, [1.0, -1.0], fs=FS)


def _h1(res):
    e = res.telemetry["residuals"][res.settle_frames :].astype(float)
    d = res.telemetry["disturbance"][res.settle_frames :].astype(float)
    f, p_de = signal.csd(d, e, fs=res.fs, nperseg=1024, axis=0)
    _, p_dd = signal.welch(d, fs=res.fs, nperseg=1024, axis=0)
    return f, (p_de / p_dd).T


def _run(stage, n_modes=3, seed=0):
    return run_loop(stage, ModalTimeSeries(_white(N_FRAMES, n_modes, seed)), N_FRAMES,
                    settle_frames=100)  # fmt: skip


# Window leakage of a 1024-point Hann window: ~1e-4 typical, ~2e-2 next to DC where S is
# steep (the nominal loop's check in test_loop.py); a model error's effect is ~0.1-1.
H1_TOL = 0.03


@pytest.mark.parametrize(("design", "true"), [(0.83, 1.13), (0.83, 0.5), (1.0, 1.7)])
def test_latency_error_reproduces_the_true_plant_s_sensitivity(design, true):
    # The controller of the design latency runs on a loop of another: the measured S is the
    # true plant's with that controller, and not the design's.
    ctrl = _bank()
    res = _run(Stage(ctrl, latency_frames=true))
    f, H = _h1(res)
    S_true = sensitivity(loop_plant(FS, true), ctrl, f)
    S_design = sensitivity(loop_plant(FS, design), ctrl, f)
    assert np.max(np.abs(H - S_true)[:, 1:-1]) < H1_TOL
    assert np.max(np.abs(H - S_design)[:, 1:-1]) > 5 * H1_TOL  # the twin: the error is seen


@pytest.mark.parametrize(
    "response",
    [DMResponse(time_constant=2e-4), DMResponse(resonance_hz=1300.0, damping=0.3),
     DMResponse(time_constant=1e-4, resonance_hz=1200.0, damping=0.4)],
)  # fmt: skip
def test_dm_response_reproduces_g_h(response):
    ctrl = _bank()
    dm = ModalDM(3, response=response)
    res = _run(Stage(ctrl, latency_frames=0.83, dm=dm))
    f, H = _h1(res)
    true = loop_plant(FS, 0.83) * response.transfer_function(FS)
    assert np.max(np.abs(H - sensitivity(true, ctrl, f))[:, 1:-1]) < H1_TOL
    nominal = sensitivity(loop_plant(FS, 0.83), ctrl, f)
    assert np.max(np.abs(H - nominal)[:, 1:-1]) > 3 * H1_TOL


def test_optical_gain_error_scales_the_signal_not_the_noise():
    # og G with a factor 0.7: the rejection of the loop with og * 0.7; and the noise enters
    # unscaled (white noise alone: the residual is the noise through T of the scaled loop).
    ctrl = _bank()
    err = OpticalGainError(factor=[0.7, 1.3, 0.5])
    res = _run(Stage(ctrl, latency_frames=0.83, optical_gain_error=err))
    f, H = _h1(res)
    for i, g in enumerate(err.factor):
        S = np.atleast_2d(
            sensitivity(loop_plant(FS, 0.83) * float(g), ctrl.transfer_function(i), f)
        )[0]
        assert np.max(np.abs(H[i] - S)[1:-1]) < H1_TOL
    noise = run_loop(
        Stage(Integrator(0.4, fs=FS), LinearModalSensor(1.0, 2.0), 0.83,
              optical_gain_error=OpticalGainError(factor=0.5)),
        ModalTimeSeries(np.zeros((N_FRAMES, 1))), N_FRAMES, rng=np.random.default_rng(3),
    )  # fmt: skip
    scaled = run_loop(
        Stage(Integrator(0.2, fs=FS), LinearModalSensor(1.0, 2.0), 0.83),
        ModalTimeSeries(np.zeros((N_FRAMES, 1))), N_FRAMES, rng=np.random.default_rng(3),
    )  # fmt: skip
    # factor 0.5 on the signal = gain 0.2 on a unit-gain loop with noise * 0.5 ... the
    # noise is NOT scaled: the residual equals a loop of gain 0.4 * 0.5 fed with 2x the
    # noise relative to its signal; compare with the unit-gain loop of gain 0.2 driven by the
    # same noise multiplied by 2 (the noise reaches the controller unscaled, gain 0.4).
    np.testing.assert_allclose(
        noise.telemetry["residuals"], 2.0 * scaled.telemetry["residuals"], rtol=1e-5, atol=1e-4
    )


def test_drifting_optical_gain_follows_its_schedule():
    # A modulated gain: the loop's measurement of a constant residual is g(t) e.
    err = OpticalGainError(factor=1.0, drift=0.3, period=0.01, phase=[0.0, np.pi / 2])
    t = np.arange(5) / FS
    g = np.array([err.gains(x, 2) for x in t])
    np.testing.assert_allclose(g[:, 0], 1 + 0.3 * np.sin(2 * np.pi * t / 0.01))
    np.testing.assert_allclose(g[:, 1], 1 + 0.3 * np.cos(2 * np.pi * t / 0.01))
    res = run_loop(
        Stage(IIRBank([1e-9], [1.0, -1.0], fs=FS, n_modes=2), latency_frames=0.0,
              optical_gain_error=err),
        ModalTimeSeries(np.ones((40, 2))), 40,
    )  # fmt: skip
    m = res.telemetry["measurements"].astype(float)
    k = np.arange(1, 40)  # frame k reads the residual of frame k - 1 (~1, the loop barely acts)
    expected = np.array([err.gains(x / FS, 2) for x in k])
    np.testing.assert_allclose(m[1:], expected, rtol=1e-6)


def test_neutral_errors_give_the_nominal_run_bit_for_bit():
    ctrl = _bank()
    data = _white(8000, 3, seed=7)
    nominal = run_loop(Stage(ctrl, LinearModalSensor(1.0, 0.5), 0.83), ModalTimeSeries(data), 4000,
                       rng=np.random.default_rng(1))  # fmt: skip
    neutral = run_loop(
        Stage(ctrl, LinearModalSensor(1.0, 0.5), 0.83,
              dm=ModalDM(3, response=DMResponse(), mixing=np.eye(3)),
              optical_gain_error=OpticalGainError()),
        ModalTimeSeries(data), 4000, rng=np.random.default_rng(1),
    )  # fmt: skip
    for name in ("residuals", "measurements", "commands"):
        np.testing.assert_array_equal(neutral.telemetry[name], nominal.telemetry[name])


def test_misregistration_matrix_is_a_small_rotation_of_the_basis():
    pupil = vlt_pupil(32)
    dm = DeformableMirror(pupil, n_actuators=12)
    basis = kl_basis(dm, 30)
    sub = 8.0 / 11  # a subaperture per actuator pitch [m]
    M0 = misregistration_matrix(dm, basis, subaperture=sub)
    np.testing.assert_array_equal(M0, np.eye(30))
    # The model of the exact DM: a zero move through the influence functions is the identity
    # to the basis' m2c fit (the piston the modes leave out apart).
    M_tiny = misregistration_matrix(dm, basis, shift_x=1e-9, subaperture=sub)
    np.testing.assert_allclose(M_tiny, np.eye(30), atol=1e-6)
    M = misregistration_matrix(dm, basis, shift_x=0.2, rotation=1.0, subaperture=sub)
    # Low-order modes barely move under a fifth of a subaperture; high-order ones couple.
    assert np.all(np.diag(M)[:3] > 0.98)
    assert np.max(np.abs(M - np.eye(30))) > 0.05
    # Norms about 1 or below (part of a moved mode leaves the basis).
    # (to the m2c fit of the modes: a DM makes its modes to ~1e-3, their piston apart)
    assert np.all(np.linalg.norm(M, axis=0) <= 1.01)
    # Shifting x by +s then -s nearly undoes it (interpolation only).
    back = misregistration_matrix(
        dm, basis, shift_x=-0.2, subaperture=sub
    ) @ misregistration_matrix(dm, basis, shift_x=0.2, subaperture=sub)
    assert np.max(np.abs(back - np.eye(30))[:10, :10]) < 0.05


def test_mixing_reaches_the_residual_as_the_matrix_says():
    # A permutation-like mixing on a controller-free loop (gain ~0): the DM shape is M u.
    mix = np.array([[0.9, 0.1], [-0.1, 0.9]])
    ctrl = IIRBank([0.5], [1.0, -1.0], fs=FS, n_modes=2)
    d = ModalTimeSeries(_white(2000, 2, seed=4))
    res = run_loop(Stage(ctrl, latency_frames=0.0, dm=ModalDM(2, mixing=mix)), d, 2000)
    u = res.telemetry["commands"].astype(float)
    e = res.telemetry["residuals"].astype(float)
    dd = _white(2000, 2, seed=4)
    # Latency 0 (G = z^-1, the WFS frame): the DM shape of frame k is frame k's command
    # (computed from the measurement of frame k - 1's residual), mixed.
    np.testing.assert_allclose(e, dd - u @ mix.T, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: DMResponse(time_constant=-1e-4), "time_constant must be"),
        (lambda: DMResponse(resonance_hz=900.0, damping=1.5), "damping must be in \\(0, 1\\)"),
        (lambda: DMResponse(resonance_hz=2e3).coefficients(3e3), "resonance_hz must be below"),
        (lambda: OpticalGainError(factor=0.0), "factor must be > 0"),
        (lambda: OpticalGainError(drift=1.2), "drift must be in \\[0, 1\\)"),
        (lambda: ModalDM(2, mixing=np.eye(3)), "mixing must have shape \\(2, 2\\)"),
        (lambda: Stage(Integrator(0.3, fs=FS, n_modes=2),
                       optical_gain_error=OpticalGainError(factor=[1.0, 1.0, 1.0])),
         "optical_gain_error.factor has 3 values"),
    ],
)  # fmt: skip
def test_bad_model_errors_are_named(make, match):
    with pytest.raises(ValueError, match=match):
        make()


# ----------------------------------------------------------------------------- study layer
def test_case_model_errors_are_checked_and_reach_the_loop_not_the_design():
    from aocontrol.study._simulate import scene_stage
    from aocontrol.study.cases import CaseError, apply_overrides, load_case
    from aocontrol.study.scene import build_scene, geometry_cache_key

    case = load_case("bright1-best")
    errs = {
        "stage2.latency_error": 0.3,
        "stage2.optical_gain_error": 0.7,
        "stage2.dm_time_constant": "0.2 ms",
        "stage2.dm_resonance": "1.2 kHz",
        "stage2.misregistration_shift_x": 0.25,
    }
    c = apply_overrides(case, errs)
    # The calibration is the nominal instrument's: the same cache entry.
    assert geometry_cache_key(c, True) == geometry_cache_key(case, True)
    scene = build_scene(c, quick=True)
    st = scene.stage2
    stage = scene_stage(st, Integrator(0.3, fs=st.fs, n_modes=st.n_modes), "stage 2")
    assert stage.latency_frames == pytest.approx(case.stage2.latency_frames + 0.3)
    np.testing.assert_array_equal(
        st.plant.num[0][0], build_scene(case, quick=True).stage2.plant.num[0][0]
    )  # the design's
    assert stage.dm.response.time_constant == pytest.approx(2e-4)
    assert stage.dm.response.resonance_hz == pytest.approx(1200.0)
    assert stage.dm.mixing is not None and stage.dm.mixing.shape == (st.n_modes,) * 2
    assert np.all(stage.optical_gain_error.factor == 0.7)
    nominal = scene_stage(
        build_scene(case, quick=True).stage2, Integrator(0.3, fs=st.fs, n_modes=st.n_modes), "s"
    )
    assert nominal.dm.response is None and nominal.dm.mixing is None
    assert nominal.optical_gain_error is None
    for key, value, match in [
        ("stage2.dm_time_constant", "-1 ms", "dm_time_constant: must be >= 0 s"),
        ("stage2.latency_error", -2.0, "latency_error: must be in \\[-latency_frames, 5\\]"),
        ("stage2.optical_gain_error", 0.0, "optical_gain_error: must be > 0"),
        ("stage2.dm_resonance", "2 kHz", "dm_resonance: must be in \\(0, fs/2\\)"),
    ]:
        with pytest.raises(CaseError, match=match):
            apply_overrides(case, {key: value})


def test_cli_set_passes_case_values(tmp_path, monkeypatch, capsys):
    # Through the command line: `compare --set KEY=VALUE` hands the case overrides to
    # compare_case (numbers as numbers, the rest strings), stubbed here to stop the run.
    from aocontrol.study import compare
    from aocontrol.study.cli import main

    seen = []

    def stub(case, *, overrides=None, **kwargs):
        seen.append(overrides)
        raise RuntimeError("stub: no run")

    monkeypatch.setattr(compare, "compare_case", stub)
    cmd = ["compare", "bright1-best", "--out", str(tmp_path)]
    sets = ["stage2.latency_error=0.3", "seeing=0.6", "stage2.dm_time_constant=0.2 ms"]
    assert main([*cmd, *(a for s in sets for a in ("--set", s))]) == 1
    assert seen.pop() == {
        "stage2.latency_error": 0.3,
        "seeing": 0.6,
        "stage2.dm_time_constant": "0.2 ms",
    }
    assert main(cmd) == 1
    assert seen.pop() is None
    capsys.readouterr()
    assert main([*cmd, "--set", "latency"]) == 2  # a user error, before any run
    assert "--set takes KEY=VALUE" in capsys.readouterr().err
    assert seen == []
