"""Tests of the adaptive controller (aocontrol.adaptive) run by the simulator's loop.

Oracles and invariants: a switch to the same controller changes nothing (the bumpless state
reproduces the running filter exactly); an uncertified proposal never reaches the loop (the
run equals the fixed one, while the same controller used directly diverges); the Direct-Form I
history continues a run exactly; the adaptive loop beats the fixed design on a disturbance
whose bandwidth doubles; the schedule of designs and switches follows period, window and
latency.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from aocontrol import loop_plant
from aocontrol.adaptive import (
    AdaptiveController,
    Proposal,
    bumpless_outputs,
    certify,
    datadriven_designer,
    modal_gain_designer,
    select_modes,
)
from aocontrol.controllers import IIRBank, Integrator
from aocontrol.sim import LinearModalSensor, LoopDivergedError, ModalTimeSeries, Stage, run_loop
from aocontrol.synthesis import TelemetryPSD

FS = 1000.0
LATENCY = 0.83
N_MODES = 3
N_FRAMES = 3000


def _drifting(n_frames: int = N_FRAMES, seed: int = 0) -> np.ndarray:
    """Low-pass (2nd-order Butterworth) turbulence-like modes whose bandwidth doubles
    (5 -> 10 Hz) half-way: the wind doubles."""
    rng = np.random.default_rng(seed)
    w = rng.standard_normal((n_frames, N_MODES)) * 100.0
    half = n_frames // 2
    out = np.empty_like(w)
    for part, fc in ((slice(0, half), 5.0), (slice(half, n_frames), 10.0)):
        b, a = signal.butter(2, fc / (FS / 2))
        out[part] = signal.lfilter(b, a, w[part], axis=0)
    return out


def _run(ctrl, d, sigma=0.5):
    stage = Stage(ctrl, LinearModalSensor(1.0, sigma), LATENCY)
    return run_loop(stage, ModalTimeSeries(d, FS), d.shape[0], rng=1)


def _same(tel, plant, current):
    return Proposal(IIRBank(current.b, current.a, current.fs))


def _adaptive(designer, **kw):
    kw = {"period": 0.5, "window": 0.5, "latency": 0.01, **kw}
    return AdaptiveController(
        Integrator(0.3, fs=FS, n_modes=N_MODES), loop_plant(FS, LATENCY), designer, **kw
    )


# ---------------------------------------------------------------------------- state
def test_set_history_continues_a_run_exactly():
    # Invariant: a filter whose Direct-Form I history is set from a run's past measurements
    # and commands continues that run bit for bit.
    rng = np.random.default_rng(0)
    b = rng.normal(size=(3, 4))
    a = np.c_[np.ones(3), 0.1 * rng.normal(size=(3, 3))]
    ref = IIRBank(b, a, FS)
    m = rng.normal(size=(50, 3))
    u = np.array([ref.step(x) for x in m])
    new = IIRBank(b, a, FS)
    new.set_history(m[:30], u[:30])
    np.testing.assert_array_equal([new.step(x) for x in m[30:]], u[30:])
    with pytest.raises(ValueError, match=r"commands must have shape \(n_frames, 3\)"):
        new.set_history(m, u[:, :2])


def test_bumpless_outputs_of_the_running_filter_are_its_commands():
    # Oracle: for the filter that produced the commands, the least-squares fit of its past
    # outputs is exact (the applied commands solve it with zero residual).
    rng = np.random.default_rng(1)
    b = np.array([[0.4, -0.1, 0.05]] * 2)
    a = np.array([[1.0, -1.2, 0.25]] * 2)
    bank = IIRBank(b, a, FS)
    m = rng.normal(size=(120, 2))
    u = np.array([bank.step(x) for x in m])
    got = bumpless_outputs(IIRBank(b, a, FS), m, u, fit_frames=100)
    np.testing.assert_allclose(got, u[20:], rtol=1e-8, atol=1e-8)


def test_switch_to_the_same_controller_changes_nothing():
    # Invariant: redesigns that propose the running bank itself, switched in bumplessly,
    # leave every command and residual as in the fixed run.
    d = _drifting()
    ctrl = _adaptive(_same)
    res = _run(ctrl, d)
    fixed = _run(Integrator(0.3, fs=FS, n_modes=N_MODES), d)
    assert ctrl.last_run.n_switches == 5
    np.testing.assert_allclose(
        res.telemetry["commands"], fixed.telemetry["commands"], rtol=0, atol=1e-3
    )
    # Twin: a cold switch (the new filter's state at zero) makes the command jump.
    cold = IIRBank(ctrl.current.b, ctrl.current.a, FS)
    assert abs(cold.step(np.zeros(N_MODES))).max() == 0.0  # restarts from zero, not from ~d


# ---------------------------------------------------------------------------- certificates
def test_uncertified_controller_is_never_switched_in():
    # A proposal of gain 1.5 on a 1.83-frame loop (stability limit ~1) fails the certificate
    # for every mode: the run equals the fixed run and every proposal is counted as rejected.
    d = _drifting()

    def unstable(tel, plant, current):
        return Proposal(Integrator(1.5, fs=FS, n_modes=N_MODES))

    ctrl = _adaptive(unstable)
    res = _run(ctrl, d)
    fixed = _run(Integrator(0.3, fs=FS, n_modes=N_MODES), d)
    run = ctrl.last_run
    assert run.n_switches == 0 and run.n_rejected_banks == len(run.redesigns) == 5
    assert all("unstable" in msg for r in run.redesigns for msg in r.reasons.values())
    np.testing.assert_array_equal(res.telemetry["commands"], fixed.telemetry["commands"])
    # Twin: that controller, used directly, diverges.
    with pytest.raises(LoopDivergedError):
        _run(Integrator(1.5, fs=FS, n_modes=N_MODES), d)


def test_failed_and_uncertified_modes_keep_their_controller():
    # Mode 0 gets a certified gain, mode 1 an unstable one, mode 2 a design failure: only
    # mode 0 changes; the other two are reported and keep the initial integrator.
    d = _drifting()

    def mixed(tel, plant, current):
        return Proposal(Integrator([0.5, 1.5, 0.5], fs=FS), failed={2: "solver failed"})

    ctrl = _adaptive(mixed)
    res = _run(ctrl, d)
    fixed = _run(Integrator(0.3, fs=FS, n_modes=N_MODES), d)
    np.testing.assert_allclose(ctrl.last_run.final.b[:, 0], [0.5, 0.3, 0.3])
    redesign = ctrl.last_run.redesigns[0]
    assert redesign.certified.tolist() == [True, False, False]
    assert "unstable" in redesign.reasons[1] and "solver failed" in redesign.reasons[2]
    cmd, ref = res.telemetry["commands"], fixed.telemetry["commands"]
    np.testing.assert_allclose(cmd[:, 1:], ref[:, 1:], rtol=0, atol=1e-3)
    assert not np.allclose(cmd[600:, 0], ref[600:, 0], atol=1e-3)


def test_certify_checks_margin_and_controller_poles():
    plant = loop_plant(FS, LATENCY)
    bank = IIRBank([[0.3, 0.0], [0.3, 0.0], [0.05, 0.0]], [[1, -1.0], [1, -1.0], [1, -1.02]], FS)
    ok, margin, reasons = certify(plant, bank, modulus_margin=0.5)
    assert ok.tolist() == [True, True, False] and "pole radius 1.02" in reasons[2]
    ok, _, reasons = certify(plant, bank, modulus_margin=0.99, modes=[0])
    assert ok.tolist() == [False, False, False] and "modulus margin" in reasons[0]
    assert 0.5 < margin[0] < 1.0


def test_certify_reuses_a_designers_certified_margin():
    # A margin the designer certified is not recomputed: it is still compared with the
    # margin asked for, and the pole radius is still checked (the third controller's pole at
    # 1.02 is refused whatever margin is claimed); nan: certified here.
    plant = loop_plant(FS, LATENCY)
    bank = IIRBank([[0.3, 0.0], [0.3, 0.0], [0.05, 0.0]], [[1, -1.0], [1, -1.0], [1, -1.02]], FS)
    _, margin, _ = certify(plant, bank, modulus_margin=0.5)
    claimed = np.array([0.4, np.nan, 0.9])
    ok, got, reasons = certify(plant, bank, modulus_margin=0.5, certified_margin=claimed)
    assert ok.tolist() == [False, True, False]
    assert "modulus margin 0.4" in reasons[0] and "pole radius 1.02" in reasons[2]
    assert got[0] == 0.4 and got[1] == margin[1]
    with pytest.raises(ValueError, match="certified_margin"):
        certify(plant, bank, modulus_margin=0.5, certified_margin=np.ones(2))


def test_datadriven_designer_passes_on_the_certified_margins():
    # Oracle: the margins the synthesis certified (and the designer passes on, so that the
    # adaptive layer does not certify them again) are those of the analysis layer's
    # certificate of the proposed controllers, and their closed loops are stable.
    from aocontrol.analysis import is_stable, modulus_certificate

    plant = loop_plant(FS, LATENCY)
    f = np.linspace(0.0, FS / 2, 129)
    psd = 1.0 / (1.0 + (f[None, :] / np.array([[5.0], [20.0]])) ** 2)
    noise = np.full(2, 1e-3)
    tel = TelemetryPSD(f, psd, noise, np.zeros((8, 2)), psd, FS, (0.8, 1.0))
    design = datadriven_designer(order=2, n_grid=16, max_iter=4)
    prop = design(tel, plant, Integrator(0.3, fs=FS, n_modes=2))
    assert prop.margin is not None and np.all(prop.margin >= 0.5 * (1 - 1e-9))
    for i in range(2):
        K = prop.controller.transfer_function(i)
        assert is_stable(plant, K)
        assert prop.margin[i] == pytest.approx(modulus_certificate(plant, K).value, rel=1e-9)


# ---------------------------------------------------------------------------- adaptation
def test_schedule_and_impulse_response():
    # The first design once a window is available (700 frames), then every period (400);
    # switches latency frames later;
    # before the first switch the real-time path is the initial bank's transfer function.
    d = _drifting()
    ctrl = _adaptive(_same, period=0.4, window=0.7, latency=0.05)
    _run(ctrl, d)
    frames = [r.frame for r in ctrl.last_run.redesigns]
    assert frames == [700, 1100, 1500, 1900, 2300, 2700]
    assert ctrl.last_run.switch_frames == [f + 50 for f in frames]
    h = ctrl.impulse_response(40)
    np.testing.assert_allclose(h[:, 0], 0.3, rtol=1e-12)  # g / (1 - z^-1): steps of g


def test_adaptive_modal_gain_beats_the_fixed_design_after_the_wind_doubles():
    # The integrator gain re-optimised on the loop's own telemetry lowers the residual
    # variance of the second half (wind doubled) relative to the fixed gain 0.3, and the
    # switches are smooth: the residual energy in the 50 frames after the switches is within
    # 1.3x of that in the 50 before, pooled over the 7 switches (a 50-frame estimate of a
    # low-pass residual scatters by ~50 %, the pool by ~20 %; a cold restart is 65x).
    d = _drifting(4000)
    ctrl = _adaptive(modal_gain_designer())
    res = _run(ctrl, d)
    fixed = _run(Integrator(0.3, fs=FS, n_modes=N_MODES), d)
    e, e0 = res.telemetry["residuals"][2500:], fixed.telemetry["residuals"][2500:]
    assert np.mean(e**2) < 0.8 * np.mean(e0**2), (np.mean(e**2), np.mean(e0**2))
    full = res.telemetry["residuals"]
    switches = ctrl.last_run.switch_frames
    assert len(switches) == 7
    before = np.mean([np.mean(full[k - 50 : k] ** 2) for k in switches])
    after = np.mean([np.mean(full[k : k + 50] ** 2) for k in switches])
    assert after < 1.3 * before, (before, after)
    # Twin: the same switches made cold (the new filter's state at zero) restart the loop
    # from zero correction: the residual after them is the disturbance itself, > 10x.
    cold = np.mean([np.mean(d[k : k + 50] ** 2) for k in switches])
    assert cold > 10 * before


@pytest.mark.slow
def test_adaptive_datadriven_beats_the_fixed_design():
    # Data-driven order-3 banks warm-started from the running one: certified, switched, and
    # the residual of the second half below 60 % of the fixed integrator's.
    d = _drifting(3000)
    ctrl = _adaptive(datadriven_designer(order=3), period=1.0, window=1.0)
    res = _run(ctrl, d)
    fixed = _run(Integrator(0.3, fs=FS, n_modes=N_MODES), d)
    assert ctrl.last_run.n_switches >= 1
    e, e0 = res.telemetry["residuals"][2000:], fixed.telemetry["residuals"][2000:]
    assert np.mean(e**2) < 0.6 * np.mean(e0**2), (np.mean(e**2), np.mean(e0**2))


# ---------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("kw", "words"),
    [
        ({"window": 0.01}, "window must hold at least 64 frames"),
        ({"latency": 0.5}, "latency must be shorter than period"),
        ({"nperseg": 1024}, "window must hold at least nperseg=1024"),
        ({"period": -1.0}, "period"),
        ({"modulus_margin": 1.5}, "modulus_margin"),
    ],
)
def test_bad_adaptive_arguments(kw, words):
    with pytest.raises(ValueError, match=words):
        _adaptive(_same, **kw)


# ---------------------------------------------------------------------------- selection
def test_select_modes_covers_the_share_largest_first():
    # Oracle by hand: gains 5, 3, 1, 1 (total 10): a share of 0.75 needs 5 + 3 (8 >= 7.5);
    # 0.8 needs 5 + 3 (8 >= 8: the third mode starts at 8, not below 8); 0.81 needs three.
    # A mode never designed (inf) is always taken, a zero gain never.
    gain = np.array([1.0, 5.0, 0.0, 3.0, 1.0, np.inf])
    np.testing.assert_array_equal(select_modes(gain, 0.75), [0, 1, 0, 1, 0, 1])
    np.testing.assert_array_equal(select_modes(gain, 0.8), [0, 1, 0, 1, 0, 1])
    assert select_modes(gain, 0.81).sum() == 4
    assert select_modes(gain, 1.0).sum() == 5  # every positive gain
    np.testing.assert_array_equal(select_modes(gain, 1.0, max_modes=2), [0, 1, 0, 0, 0, 1])


def test_selection_redesigns_only_modes_whose_disturbance_changed():
    # Invariant: with the true PSD given (oracle), a second design on the same PSD is predicted
    # to gain nothing (the current controllers are those designed on it): no mode is
    # redesigned, nothing is switched, nothing counted as rejected. When only mode 1's
    # bandwidth doubles, mode 1 is the one redesigned.
    f = np.linspace(0.0, FS / 2, 257)
    fc = np.array([5.0, 5.0, 5.0])
    # Noise of 1000 units^2 per frame: the optimal gain (0.42 at 5 Hz, 0.53 at 10 Hz, the
    # margin's limit) depends on the bandwidth.
    noise = np.full(N_MODES, 2 * 1000.0 / FS)

    def psd(frame):
        c = fc * np.where((np.arange(N_MODES) == 1) & (frame >= 2000), 2.0, 1.0)
        p = 1e4 / (1.0 + (f[None, :] / c[:, None]) ** 4)
        return TelemetryPSD(f, p, noise, np.zeros((8, N_MODES)), p, FS, (0.8, 1.0))

    ctrl = _adaptive(modal_gain_designer(), oracle=psd, select=0.9)
    _run(ctrl, _drifting())
    sel = [r.selected for r in ctrl.last_run.redesigns]
    assert sel[0].all()  # never designed: every mode
    assert not sel[1].any() and not sel[2].any()  # frames 1000, 1500: nothing changed
    np.testing.assert_array_equal(sel[3], [False, True, False])  # frame 2000: mode 1
    assert not ctrl.last_run.redesigns[1].switched
    assert ctrl.last_run.n_rejected_banks == 0
    assert ctrl.last_run.n_designed_modes == N_MODES + 1 + sum(s.sum() for s in sel[4:])


def test_recoverable_gain_ignores_a_change_of_scale_and_ranks_a_mistuned_mode():
    # Invariants: the Wiener bound and the residual both scale with the disturbance and noise
    # (linear filters), so a change of scale alone (the seeing) leaves nothing to recover;
    # a mode never designed has an infinite gain. Oracle: with every controller designed on
    # 5 Hz and mode 1's bandwidth doubled, mode 1 is predicted to gain and the others not,
    # and the prediction is below its residual (a gain is never more than the residual).
    from aocontrol.adaptive import recoverable_gain
    from aocontrol.synthesis import optimal_modal_gain

    f = np.linspace(0.0, FS / 2, 257)
    plant = loop_plant(FS, LATENCY)
    noise = np.full(N_MODES, 2 * 100.0 / FS)

    def tel(fc, scale=1.0):
        p = scale * 1e4 / (1.0 + (f[None, :] / np.asarray(fc)[:, None]) ** 4)
        return TelemetryPSD(f, p, scale * noise, np.zeros((8, N_MODES)), p, FS, (0.8, 1.0))

    t0 = tel([5.0, 5.0, 5.0])
    bank = optimal_modal_gain(plant, f, t0.psd, t0.noise_psd)
    gain0, eta = recoverable_gain(bank, plant, t0, np.full(N_MODES, np.nan))
    assert np.all(np.isinf(gain0)) and np.all(eta >= 1.0)
    scaled, _ = recoverable_gain(bank, plant, tel([5.0, 5.0, 5.0], 2.25), eta)
    np.testing.assert_allclose(scaled, 0.0, atol=1e-9 * np.trapezoid(t0.psd, f).max())
    t1 = tel([5.0, 10.0, 5.0])
    gain, _ = recoverable_gain(bank, plant, t1, eta)
    j1 = np.trapezoid(t1.psd[1], f)
    assert gain[1] > 0 and gain[1] < j1
    np.testing.assert_allclose(gain[[0, 2]], 0.0, atol=1e-9 * j1)
    with pytest.raises(ValueError, match="rank must be one of"):
        _adaptive(_same, select=0.5, rank="luck")


def test_warm_design_settings_are_checked():
    with pytest.raises(ValueError, match="warm_n_grid"):
        datadriven_designer(warm_n_grid=4)
    with pytest.raises(ValueError, match="warm_max_iter"):
        datadriven_designer(warm_max_iter=0)


def test_joined_proposals_keep_each_parts_kept_modes_in_bank_numbering():
    # The warm data-driven designer designs the integrating and the other modes apart and
    # joins the two proposals: the modes each part kept (indices into the part) must come
    # out as the bank's mode numbers, so that Update.kept counts them (it was empty).
    from aocontrol.adaptive._redesign import _join

    fs = 1000.0
    current = IIRBank(np.full((4, 2), 0.3), np.tile([1.0, -1.0], (4, 1)), fs)
    part = IIRBank(np.full((2, 2), 0.4), np.tile([1.0, -1.0], (2, 1)), fs)
    joined = _join(
        current,
        [
            (np.array([0, 2]), Proposal(part, kept=(1,))),
            (np.array([1, 3]), Proposal(part, kept=(0,))),
        ],
    )
    assert joined.kept == (1, 2)
    assert _join(current, [(np.array([0, 2]), Proposal(part))]).kept == ()
