"""Single-stage closed loop: the simulator and the control layer agree on timing."""

import numpy as np
import pytest
from scipy import signal

from aocontrol import loop_plant
from aocontrol.analysis import residual_variance, sensitivity, white_noise_psd
from aocontrol.controllers import ControllerBank, IIRBank, Integrator
from aocontrol.sim.dm import ModalDM
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
        Stage(Integrator(0.5, fs=FS, n_modes=2), latency_frames=0.0, dm=ModalDM(2, 1.0)),
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
    with pytest.warns(DeprecationWarning, match="convert_npz"):  # the older form, still read
        res.save(path)
    back = LoopResult.load(path)
    assert back.metadata["case"] == "unit-test"
    np.testing.assert_array_equal(back.telemetry["residuals"], res.telemetry["residuals"])
    np.testing.assert_array_equal(back.residual_variance, res.residual_variance)
    assert not list(tmp_path.glob("*.tmp"))


def test_save_is_all_or_nothing(tmp_path, monkeypatch):
    # The failure is injected where the file is written (after some bytes reached the
    # temporary file): the previous result stays intact and no temporary file is left.
    res = run_loop(Stage(Integrator(0.4, fs=FS)), ModalTimeSeries(_white(200, 1)), 200)
    target = tmp_path / "run.npz"
    with pytest.warns(DeprecationWarning):
        res.save(target)
    before = target.read_bytes()

    def failing_savez(fh, **arrays):
        fh.write(b"partial data")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", failing_savez)
    with pytest.raises(OSError, match="disk full"), pytest.warns(DeprecationWarning):
        res.save(target)
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.npz"]
    monkeypatch.undo()
    back = LoopResult.load(target)
    np.testing.assert_array_equal(back.telemetry["residuals"], res.telemetry["residuals"])


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


# ----------------------------------------------------------- the engine vs golden arrays
# Oracle: arrays recorded from the engine before the one-driver refactoring (which had been
# checked bit for bit against the loop before the stage/runner engine); regenerate with
# tests/_golden_loop.py only for an intended change of the numbers.
def _golden(prefix):
    import _golden_loop

    with np.load(_golden_loop.PATH) as z:
        return {k[len(prefix) :]: z[k] for k in z.files if k.startswith(prefix)}


def _assert_same(res, gold):
    # Telemetry and counts bit for bit. The statistics reduced from them over frames
    # (residual variance, ...) within 1e-13: numpy's SIMD reductions dispatch on the CPU's
    # instruction set, so their last bits differ between host generations (measured: 1.3e-15
    # on one of four arrays), while the telemetry they reduce is the same bit for bit.
    assert gold, "no golden arrays for this configuration"
    for name, want in gold.items():
        if name in res.telemetry or not np.issubdtype(want.dtype, np.floating):
            got = res.telemetry[name] if name in res.telemetry else getattr(res, name)
            np.testing.assert_array_equal(np.asarray(got), want, err_msg=name)
        else:
            np.testing.assert_allclose(getattr(res, name), want, rtol=1e-13, err_msg=name)


@pytest.mark.parametrize("name", ["lin_a", "lin_b", "lin_c", "lin_d"])
def test_engine_is_bit_identical_to_the_golden_runs(name):
    # Every telemetry array and saturation count equal bit for bit, statistics to 1e-13.
    import _golden_loop

    gold = _golden(f"{name}/")
    _assert_same(_golden_loop.linear_run(_golden_loop.LINEAR[name]), gold)
    config = _golden_loop.LINEAR[name]
    if config.get("stroke"):
        assert gold["saturation"].sum() > 0  # the clipping was exercised
    if config.get("dm_stroke"):
        assert gold["actuator_saturation"].sum() > 0


def _arrays(res, names):
    """The arrays ``names`` of a LoopResult (telemetry, else attributes, else science)."""
    out = {}
    for name in names:
        if name in res.telemetry:
            out[name] = res.telemetry[name]
        elif name in ("strehl", "contrast_profile"):
            out[name] = getattr(res.science, name)
        else:
            out[name] = getattr(res, name)
    return out


def test_engine_with_science_matches_the_golden_run():
    # Projected phase screens: to the stated tolerance (_golden_loop.GOLDEN_RTOL: float32
    # projection, BLAS thread count), the science's Strehl and contrast profile included.
    import _golden_loop

    gold = _golden("science/")
    assert {"strehl", "contrast_profile", "measurements", "residual_variance"} <= set(gold)
    res = _golden_loop.science_run()
    _golden_loop.assert_close_to_golden(_arrays(res, gold), gold)


def test_golden_tolerance_check_can_fail():
    # The tolerance comparison sees a change of one value by 10x the tolerance (of the
    # array's scale), and a change of the run itself (the noise 0.1 % larger).
    import _golden_loop

    gold = _golden("lin_a/")
    res = _golden_loop.linear_run(_golden_loop.LINEAR["lin_a"])
    got = _arrays(res, gold)
    _golden_loop.assert_close_to_golden(got, gold)
    bad = dict(got, measurements=np.array(got["measurements"], dtype=float))
    scale = np.max(np.abs(gold["measurements"]))
    bad["measurements"][123, 1] += 10 * _golden_loop.GOLDEN_RTOL * scale
    with pytest.raises(AssertionError, match="measurements"):
        _golden_loop.assert_close_to_golden(bad, gold)
    other = _golden_loop.linear_run(dict(_golden_loop.LINEAR["lin_a"], noise=1.5 * 1.001))
    with pytest.raises(AssertionError):
        _golden_loop.assert_close_to_golden(_arrays(other, gold), gold)


def test_diffractive_loop_matches_the_golden_run(monkeypatch):
    # The golden run was recorded with the pyramid's former FFT propagation: the engine is
    # checked with it (tests/_pyramid_reference.py) to the stated tolerance of a run on
    # projected phase screens (_golden_loop.GOLDEN_RTOL; the sensor's own arrays bit for
    # bit); today's propagation agrees with it to a stated tolerance
    # (tests/test_pyramid_products.py).
    import _golden_loop
    from _pyramid_reference import FFTPyramid

    import aocontrol.sim.wfs
    from aocontrol.sim.wfs import DiffractiveSensor

    monkeypatch.setattr(aocontrol.sim.wfs, "PyramidWFS", FFTPyramid)

    def factory(wfs, recon, photons, read_noise):
        return DiffractiveSensor(wfs, recon, photons=photons, read_noise=read_noise)

    res = _golden_loop.diffractive_run(factory)
    gold = _golden("diffractive/")
    _golden_loop.assert_close_to_golden(_arrays(res, gold), gold)
    # The sensor reads the phase maps, not the projection: its measurements agree to the
    # float32 rounding of the DM shape and of the reconstructor product
    # (aocontrol.sim._phase_maps, DiffractiveSensor): measured 1.2e-7 of the largest.
    m, want = res.telemetry["measurements"], gold["measurements"]
    np.testing.assert_allclose(m, want, rtol=0, atol=1e-6 * np.abs(want).max())


def test_golden_check_can_fail():
    # The comparison sees a change of one frame's noise: another seed differs.
    import _golden_loop

    gold = _golden("lin_a/")
    res = _golden_loop.linear_run(dict(_golden_loop.LINEAR["lin_a"], noise=1.5000001))
    with pytest.raises(AssertionError):
        _assert_same(res, gold)


# ------------------------------------------------------------------- rates and bad inputs
def test_disturbance_rate_checked_against_the_stage():
    with pytest.raises(ValueError, match="fs=1000 Hz but stage 'stage' runs at 3000 Hz"):
        run_loop(Stage(Integrator(0.4, fs=FS)), ModalTimeSeries(_white(10, 1), fs=1000.0), 10)
    res = run_loop(Stage(Integrator(0.4, fs=FS)), ModalTimeSeries(_white(50, 1), fs=FS), 50)
    assert res.n_frames == 50


def test_non_finite_disturbance_is_named_as_such():
    class _Bad:
        n_modes, fs = 2, FS

        def next(self, n):
            d = np.zeros((n, 2))
            d[5, 1] = np.nan
            return d, None

    with pytest.raises(ValueError, match=r"disturbance is not finite .* frame 5, modes \[1\]"):
        run_loop(Stage(Integrator(0.4, fs=FS, n_modes=2)), _Bad(), 100)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"latency_frames": -0.5}, "latency_frames"),
        ({"latency_frames": 1e9}, "latency_frames must be <= 1000"),
        ({"latency_frames": np.nan}, "latency_frames"),
    ],
)
def test_stage_validates_physical_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Stage(Integrator(0.4, fs=FS), **kwargs)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"modal_stroke": -1.0}, r"modal_stroke must be > 0 \[nm\] for every mode, got min -1.0"),
        ({"modal_stroke": np.nan}, "modal_stroke must contain only finite values"),
        ({"modal_stroke": [1.0, 2.0]}, r"modal_stroke must be a float or have shape \(1,\)"),
        ({"actuator_stroke": 0.0}, "actuator_stroke must be a finite number > 0, got 0.0"),
        ({"actuator_stroke": np.inf, "m2c": np.ones((3, 1))}, "actuator_stroke must be a finite"),
        ({"actuator_stroke": 100.0}, "actuator_stroke needs m2c of shape"),
    ],
)
def test_dm_refuses_a_bad_stroke_naming_the_argument(kwargs, match):
    # The DM owns the stroke: it checks it, and the message names the DM's argument.
    with pytest.raises(ValueError, match=match):
        ModalDM(1, **kwargs)


@pytest.mark.parametrize(
    ("og", "noise", "match"),
    [
        (np.nan, 1.0, "optical_gain must contain only finite values"),
        (-1.0, 1.0, "optical_gain must be finite and > 0"),
        (1.0, -0.1, "noise_std must be >= 0"),
        (1.0, np.inf, "noise_std must contain only finite values"),
    ],
)
def test_sensor_validates_its_parameters(og, noise, match):
    with pytest.raises(ValueError, match=match):
        LinearModalSensor(og, noise)


def test_one_linear_sensor_class():
    import aocontrol.sim
    import aocontrol.sim.wfs

    for module in (aocontrol.sim.wfs, aocontrol.sim):
        with pytest.warns(DeprecationWarning, match="LinearModalWFS is deprecated"):
            assert module.LinearModalWFS is LinearModalSensor
    with pytest.raises(ValueError, match="the sensor has 3 modes .*the controller has 2"):
        Stage(Integrator(0.4, fs=FS, n_modes=2), LinearModalSensor(np.ones(3), np.zeros(3)))
    # The argument whose length is wrong is named.
    with pytest.raises(ValueError, match="optical_gain of length 2.*controller has 3"):
        Stage(Integrator(0.4, fs=FS, n_modes=3), LinearModalSensor(optical_gain=[1, 1]))


def test_slowly_diverging_loop_is_reported():
    # Just past the stability limit (integrator, 1.83 frames of delay: limit ~1.2): the
    # residual grows slowly (radius^n) and stays far below the 1e3 x guard within the run;
    # the pre-run pole check (radius > 1) reports it instead of returning huge variances.
    gain = 1.205
    stage = Stage(Integrator(gain, fs=FS), latency_frames=0.83)
    from aocontrol.sim.loop import closed_loop_pole_radius

    radius = closed_loop_pole_radius(stage, np.ones(1))[0]
    assert 1.0 < radius < 1.002  # slow: 1.002^3000 ~ 400 < 1e3
    with pytest.raises(LoopDivergedError, match="unstable") as info:
        run_loop(stage, ModalTimeSeries(_white(3000, 1)), 3000)
    np.testing.assert_array_equal(info.value.modes, [0])


class _Opaque(ControllerBank):
    """A controller bank that is not an IIRBank; optionally without a transfer function."""

    def __init__(self, inner, *, has_tf=True):
        self._inner = inner
        self._has_tf = has_tf

    n_modes = property(lambda self: self._inner.n_modes)
    fs = property(lambda self: self._inner.fs)

    def _step(self, measurement):
        return self._inner.step(measurement)

    def reset(self):
        self._inner.reset()

    def transfer_function(self, mode=0):
        if not self._has_tf:
            raise NotImplementedError("no linear model")
        return self._inner.transfer_function(mode)


def test_slow_divergence_found_through_any_controllers_transfer_function():
    # The pole check uses transfer_function() of a controller that is not an IIRBank.
    stage = Stage(_Opaque(Integrator(1.205, fs=FS)), latency_frames=0.83)
    with pytest.raises(LoopDivergedError, match="linear closed loop is unstable"):
        run_loop(stage, ModalTimeSeries(_white(3000, 1)), 3000)


def test_sustained_growth_is_reported_without_a_linear_model():
    # Pole radius ~1.0009 (integrator 1.207, 1.83 frames of delay) in a controller without a
    # transfer function: the residual energy grows ~6x per 1000-frame chunk; relative to the
    # disturbance it passes 30x, growing > 2x per chunk 3 times, well before the residual
    # reaches 1e3 x the disturbance: the sustained-growth check stops the run.
    stage = Stage(_Opaque(Integrator(1.207, fs=FS), has_tf=False), latency_frames=0.83)
    with pytest.raises(LoopDivergedError, match="sustained growth") as info:
        run_loop(stage, ModalTimeSeries(_white(12000, 1)), 12000)
    assert 3000 <= info.value.frame < 12000
    np.testing.assert_array_equal(info.value.modes, [0])
    # Stable loops of the same kind run through, with white or strongly varying disturbance.
    d = _white(6000, 2) * np.linspace(0.01, 10.0, 6000)[:, None] ** 3
    ok = run_loop(
        Stage(_Opaque(Integrator([0.5, 0.05], fs=FS), has_tf=False), latency_frames=0.83),
        ModalTimeSeries(d),
        6000,
    )
    assert np.all(ok.residual_variance < 2 * ok.disturbance_variance)


def test_controller_counters_survive_the_reset_after_a_run():
    # Two paths: the runner resets the controller after a run, so the clipped-command count is
    # kept in the metadata; replaying the recorded measurements through the same controller
    # counts the same clipped mode-frames.
    n_frames, n_modes = 400, 3
    bank = Integrator(0.4, fs=1000.0, n_modes=n_modes, command_limit=0.5)
    res = run_loop(
        Stage(bank, latency_frames=0.5),
        ModalTimeSeries(3.0 * _white(n_frames, n_modes)),
        n_frames,
        record=("measurements",),
    )
    counters = res.metadata["controller_counters"]
    assert bank.n_saturated.sum() == 0  # reset by the runner
    bank.reset()
    for m in res.telemetry["measurements"]:
        bank.step(m.astype(float))
    assert counters["n_saturated"] == int(bank.n_saturated.sum()) > 0
    assert counters["n_rejected"] == 0
