"""Single-stage closed loop: the simulator and the control layer agree on timing."""

import numpy as np
import pytest
from scipy import signal

from aocontrol import loop_plant
from aocontrol.analysis import residual_variance, sensitivity, white_noise_psd
from aocontrol.controllers import IIRBank, Integrator
from aocontrol.sim.loop import (
    LinearModalSensor,
    LoopDivergedError,
    LoopResult,
    ModalTimeSeries,
    Stage,
    run_loop,
)

FS = 3000.0


def _white(n_frames, n_modes, seed=0):
    return np.random.default_rng(seed).standard_normal((n_frames, n_modes))


def _h1_estimate(res):
    """H1 cross-spectral estimate of the transfer from disturbance to residual."""
    e = res.telemetry["residuals"][res.settle_frames :].astype(float)
    d = res.telemetry["disturbance"][res.settle_frames :].astype(float)
    f, p_de = signal.csd(d, e, fs=res.fs, nperseg=1024, axis=0)
    _, p_dd = signal.welch(d, fs=res.fs, nperseg=1024, axis=0)
    return f, (p_de / p_dd).T


@pytest.mark.parametrize("latency", [0.0, 0.83, 1.0, 1.5])
def test_measured_rejection_equals_sensitivity(latency):
    # Oracle: the loop is LTI from d to e with transfer S = 1/(1+GK), G = loop_plant(...).
    # The H1 estimate P_de/P_dd recovers the complex S (magnitude and phase: the timing);
    # the Welch PSD ratio recovers |S|^2.
    n_frames, n_modes = 16384, 6
    ctrl = IIRBank(
        np.tile([0.35, -0.05], (n_modes, 1)) * np.linspace(0.5, 1.2, n_modes)[:, None],
        [1.0, -1.0],
        fs=FS,
    )
    res = run_loop(
        Stage(ctrl, latency_frames=latency),
        ModalTimeSeries(_white(n_frames, n_modes)),
        n_frames,
        settle_frames=100,
    )
    f, H = _h1_estimate(res)
    S = sensitivity(loop_plant(FS, latency), ctrl, f)
    # Window leakage of a 1024-point Hann window: ~1e-4 typical, ~2e-2 next to DC where S
    # is steep; a timing error of a quarter frame gives ~0.5 at high frequency. The DC and
    # Nyquist bins are excluded (Welch removes the mean of each segment).
    assert np.max(np.abs(H - S)[:, 1:-1]) < 0.03
    assert np.median(np.abs(H - S)[:, 1:-1] / np.abs(S[:, 1:-1])) < 1e-3
    _, pe = res.psd("residuals")
    _, pd = res.psd("disturbance")
    above = f > 30.0  # |S|^2 spans decades below ~30 Hz: leakage-dominated PSD ratio there
    ratio = (pe / pd)[:, above] / np.abs(S[:, above]) ** 2
    assert np.median(np.abs(ratio - 1)) < 2e-3
    assert np.max(np.abs(ratio - 1)) < 0.05


def test_wrong_timing_would_be_detected():
    # The same check against the plant of another latency fails: the test above can fail.
    n_frames = 16384
    ctrl = Integrator(0.5, fs=FS)
    res = run_loop(Stage(ctrl, latency_frames=0.83), ModalTimeSeries(_white(n_frames, 1)), n_frames)
    f, H = _h1_estimate(res)
    assert np.max(np.abs(H - sensitivity(loop_plant(FS, 0.5), ctrl, f))[:, 1:-1]) > 0.1


def test_noise_propagates_through_T():
    # Oracle: residual variance with white measurement noise only = integral |T|^2 noise_psd.
    n_frames, n_modes = 60000, 3
    sigma = np.array([1.0, 2.0, 5.0])
    ctrl = Integrator([0.2, 0.4, 0.6], fs=FS)
    res = run_loop(
        Stage(ctrl, LinearModalSensor(1.0, sigma), 0.83),
        ModalTimeSeries(np.zeros((n_frames, n_modes))),
        n_frames,
        rng=np.random.default_rng(5),
    )
    f = np.linspace(0, FS / 2, 20001)
    plant = loop_plant(FS, 0.83)
    expected = np.array(
        [
            residual_variance(
                plant, ctrl.transfer_function(i), f, np.zeros_like(f), white_noise_psd(s**2, FS)
            )
            for i, s in enumerate(sigma)
        ]
    )
    # 60000 correlated samples: relative standard error of a variance ~ 2-3%.
    assert np.all(np.abs(res.residual_variance / expected - 1) < 0.08)


def test_optical_gain_scales_the_loop_gain():
    # Invariant: a sensor with optical gain og and controller g behaves as og * g.
    n = 8192
    d = _white(n, 1, seed=2)
    r1 = run_loop(
        Stage(Integrator(0.3, fs=FS), LinearModalSensor(0.5), 0.83), ModalTimeSeries(d), n
    )
    r2 = run_loop(
        Stage(Integrator(0.15, fs=FS), LinearModalSensor(1.0), 0.83), ModalTimeSeries(d), n
    )
    np.testing.assert_allclose(r1.telemetry["residuals"], r2.telemetry["residuals"], atol=1e-5)


def test_unstable_controller_stops_with_mode_and_frame():
    n_modes = 4
    gains = np.array([0.3, 0.3, 1.5, 0.3])  # limit ~1.0 for 1.83 frames of total delay
    with pytest.raises(LoopDivergedError, match=r"modes \[2\]") as info:
        run_loop(
            Stage(Integrator(gains, fs=FS), latency_frames=0.83),
            ModalTimeSeries(_white(5000, n_modes)),
            5000,
        )
    assert 0 < info.value.frame < 5000
    np.testing.assert_array_equal(info.value.modes, [2])


def test_same_seed_same_result_bit_for_bit():
    def run(seed):
        return run_loop(
            Stage(Integrator(0.4, fs=FS, n_modes=5), LinearModalSensor(1.0, 0.7), 0.83),
            ModalTimeSeries(_white(3000, 5)),
            3000,
            rng=seed,
        )

    a, b, c = run(11), run(11), run(12)
    for name in a.telemetry:
        np.testing.assert_array_equal(a.telemetry[name], b.telemetry[name])
    assert not np.array_equal(a.telemetry["measurements"], c.telemetry["measurements"])


def test_stroke_clipping_counts_saturation():
    n = 2000
    d = np.full((n, 2), 10.0)
    d[:, 1] = 0.5
    res = run_loop(
        Stage(Integrator(0.5, fs=FS, n_modes=2), latency_frames=0.0, stroke=1.0),
        ModalTimeSeries(d),
        n,
    )
    assert res.saturation[0] > n - 100 and res.saturation[1] == 0
    assert np.max(np.abs(res.telemetry["dm"])) <= 1.0
    # The clipped mode keeps a residual of 10 - 1 nm.
    assert res.telemetry["residuals"][-1, 0] == pytest.approx(9.0)


def test_save_and_load_round_trip(tmp_path):
    res = run_loop(
        Stage(Integrator(0.4, fs=FS, n_modes=3), LinearModalSensor(1.0, 0.1), 0.83),
        ModalTimeSeries(_white(1000, 3)),
        1000,
        rng=0,
        metadata={"case": "unit-test", "gain": 0.4},
    )
    path = tmp_path / "run.npz"
    res.save(path)
    back = LoopResult.load(path)
    assert back.metadata["case"] == "unit-test"
    np.testing.assert_array_equal(back.telemetry["residuals"], res.telemetry["residuals"])
    np.testing.assert_array_equal(back.residual_variance, res.residual_variance)
    assert not list(tmp_path.glob("*.tmp"))


def test_save_is_all_or_nothing(tmp_path):
    res = run_loop(Stage(Integrator(0.4, fs=FS)), ModalTimeSeries(_white(200, 1)), 200)
    object.__setattr__(res, "metadata", {"bad": object()})  # serialised as str: still fine
    res.save(tmp_path / "ok.npz")
    target = tmp_path / "missing-dir" / "run.npz"
    with pytest.raises(FileNotFoundError):
        res.save(target)
    assert not target.exists()


@pytest.mark.parametrize(
    ("kwargs", "exc", "match"),
    [
        ({"n_frames": 0}, ValueError, "n_frames must be an integer >= 1"),
        ({"record": ("residuals", "phase")}, ValueError, "unknown"),
        ({"settle_frames": 500}, ValueError, "settle_frames=500 must be < n_frames=500"),
    ],
)
def test_run_loop_bad_input(kwargs, exc, match):
    args = dict(n_frames=500)
    args.update(kwargs)
    with pytest.raises(exc, match=match):
        run_loop(Stage(Integrator(0.4, fs=FS)), ModalTimeSeries(_white(600, 1)), **args)


def test_mode_count_and_noise_rng_checked():
    with pytest.raises(ValueError, match="disturbance has 2 modes, the controller 1"):
        run_loop(Stage(Integrator(0.4, fs=FS)), ModalTimeSeries(_white(10, 2)), 10)
    with pytest.raises(ValueError, match="rng is required"):
        run_loop(
            Stage(Integrator(0.4, fs=FS), LinearModalSensor(1.0, 1.0)),
            ModalTimeSeries(_white(10, 1)),
            10,
        )
    with pytest.raises(ValueError, match="optical_gain must be finite and > 0"):
        Stage(Integrator(0.4, fs=FS), LinearModalSensor(0.0, 1.0))
    with pytest.raises(TypeError, match="controller must be a ControllerBank"):
        Stage("integrator")
