"""Multi-mode (EOF / LMMSE) predictor: oracles, integral action, real-time path,
certificate, bad input.

Loop conventions of :mod:`aocontrol.plant`: ``G = z^-1 ((1 - f) z^-k + f z^-(k+1))``, the
pseudo-open loop ``p = m + G u = z^-1 d + n`` and the command ``u = sum_j A_j p[k-j]``.
The oracles of a zero-mean stationary process (VAR(1), AR(2)) are those of the free
least-squares predictor (``integral_action=False``): its best predictor has a DC gain
``F(1) != I``, which the default (``F(1) = I``, ``S(1) = 0``) forbids.
"""

from __future__ import annotations

import numpy as np
import pytest

from aocontrol import loop_plant
from aocontrol.analysis import (
    multimode_certificate,
    multimode_closed_loop_poles,
    wiener_bound,
)
from aocontrol.controllers import (
    Integrator,
    LQGBank,
    MultiModeBank,
    load_controller,
    save_controller,
)
from aocontrol.plant import split_latency
from aocontrol.sim import LinearModalSensor, ModalTimeSeries, Stage, TurbulenceSource, run_loop
from aocontrol.sim.atmosphere import Atmosphere, Layer
from aocontrol.sim.dm import DeformableMirror, ModalDM
from aocontrol.sim.modes import kl_basis
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.synthesis import (
    EOF_HISTORY,
    EOF_MAX_HISTORY,
    EOF_REGRESSORS,
    DesignInputs,
    DisturbanceModel,
    EOFNotCertifiedError,
    LoopTelemetry,
    disturbance_from_telemetry,
    eof_default_history,
    eof_from_pseudo_open_loop,
    eof_predictor,
    get_controller,
    lqg_from_telemetry,
    lqg_state_space,
    pseudo_open_loop,
)

FS = 1000.0
# The oracle tolerance: a trained predictor within 2 % of the optimal residual.
ORACLE_RTOL = 0.02


def _closed_loop_residual(ctrl, d, latency, *, settle=100, noise=0.0, rng=None):
    """Residual variance per mode of ``ctrl`` on the disturbance record ``d`` (simulator)."""
    stage = Stage(ctrl, LinearModalSensor(1.0, noise), latency)
    res = run_loop(stage, ModalTimeSeries(d, FS), d.shape[0], rng=rng, record=("residuals",),
                   settle_frames=settle)  # fmt: skip
    return np.asarray(res.telemetry["residuals"][settle:], dtype=float)


def _telemetry(d, latency, gain=0.3):
    """Closed-loop telemetry of an integrator on ``d`` (no noise), as an instrument has it."""
    n = d.shape[1]
    stage = Stage(Integrator(gain, fs=FS, n_modes=n), LinearModalSensor(1.0, 0.0), latency)
    res = run_loop(stage, ModalTimeSeries(d, FS), d.shape[0],
                   record=("measurements", "commands"))  # fmt: skip
    m = np.asarray(res.telemetry["measurements"], dtype=float)
    u = np.asarray(res.telemetry["commands"], dtype=float)
    return LoopTelemetry(m, u, FS, latency)


# -- oracles ---------------------------------------------------------------------------------


def _var1(n_frames, rng, phi, chol):
    """VAR(1) ``d[t] = phi d[t-1] + w[t]``, ``cov(w) = chol chol^T``: (d, w), stationary."""
    n = phi.shape[0]
    burn = 500
    w = rng.standard_normal((n_frames + burn, n)) @ chol.T
    d = np.zeros_like(w)
    for t in range(1, n_frames + burn):
        d[t] = phi @ d[t - 1] + w[t]
    return d[burn:], w[burn:]


@pytest.fixture(scope="module")
def var1():
    # Six modes coupled by a known matrix: eigenvalues 0.2..0.85 in a random basis plus an
    # asymmetric coupling (spectral radius < 0.9), innovation covariance with correlations.
    rng = np.random.default_rng(11)
    n = 6
    q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    phi = q @ np.diag(np.linspace(0.2, 0.85, n)) @ q.T + 0.08 * rng.standard_normal((n, n))
    assert np.abs(np.linalg.eigvals(phi)).max() < 0.95
    chol = np.tril(0.3 * rng.standard_normal((n, n)), -1) + np.eye(n)
    train, _ = _var1(20_000, rng, phi, chol)
    test, w = _var1(20_000, rng, phi, chol)
    return phi, train, test, w


def test_var1_predictor_reaches_the_one_step_prediction_error(var1):
    # Oracle: at latency 0 the loop must predict d[t] from d[t-1], d[t-2], ...; the best
    # linear predictor is phi d[t-1] and its error is the innovation w[t] exactly. The
    # predictor is trained on the closed-loop telemetry of an integrator (noise-free) and run
    # in the simulator on a fresh record: its residual over the innovation's, same frames.
    # The free predictor: phi's DC gain is not I.
    phi, train, test, w = var1
    res = eof_predictor(_telemetry(train, 0.0), history=2, modulus_margin=0.3,
                        integral_action=False)  # fmt: skip
    assert res.regularisation == res.validation_regularisation  # the margin did not bind
    np.testing.assert_allclose(res.controller.taps[0], phi, atol=0.05)
    e = _closed_loop_residual(res.controller, test, 0.0)
    ratio = np.sum(e**2) / np.sum(w[100:] ** 2)
    assert abs(ratio - 1.0) < ORACLE_RTOL, ratio


def test_var1_per_mode_predictor_fails_the_same_check(var1):
    # Twin: the best per-mode predictors (each mode from its own past only, same history)
    # miss the coupling, so the check above can fail.
    phi, train, test, w = var1
    tel = _telemetry(train, 0.0)
    pol = pseudo_open_loop(tel.measurements, tel.commands, loop_plant(FS, 0.0))[2:]
    n = phi.shape[0]
    taps = np.zeros((2, n, n))
    for i in range(n):
        one = eof_from_pseudo_open_loop(pol[:, [i]], FS, 0.0, history=2, modulus_margin=0.3,
                                        integral_action=False)  # fmt: skip
        taps[:, i, i] = one.controller.taps[:, 0, 0]
    e = _closed_loop_residual(MultiModeBank(taps, FS, 0.0), test, 0.0)
    assert np.sum(e**2) / np.sum(w[100:] ** 2) > 1.0 + 5 * ORACLE_RTOL


@pytest.fixture(scope="module")
def ar2_modes():
    # Independent modes, AR(2) double poles (turbulence-like, f^-4 beyond the corner).
    poles = np.array([0.8, 0.9, 0.95, 0.97])
    n = poles.size
    empty = np.zeros((n, 0))
    model = DisturbanceModel(np.column_stack([2 * poles, -(poles**2)]), np.ones(n), empty,
                             empty, empty, fs=FS)  # fmt: skip
    rng = np.random.default_rng(5)
    return model, model.simulate(20_000, rng), model.simulate(50_000, rng)


LATENCY_AR = 1.3  # two whole frames of delay in total, plus a fractional 0.3


def test_independent_ar_modes_match_wiener_bound_and_lqg(ar2_modes):
    # Oracle: per mode the best causal linear controller's residual is the Wiener bound
    # (k-step prediction error; the fractional part handled exactly), and the LQG with the
    # true model reaches it. The predictor, trained on telemetry, must reach both within 2 %.
    # Sampling: 50,000 test frames (relative scatter of the summed variance ~0.5 %); the LQG
    # runs on the same record, so that ratio is free of the scatter. The free predictor: the
    # Wiener predictor of a stationary AR process has F(1) != I.
    model, train, test = ar2_modes
    plant = loop_plant(FS, LATENCY_AR)
    f = np.linspace(0.0, FS / 2, 20_001)
    bound = wiener_bound(plant, f, model.psd(f)).sum()
    res = eof_predictor(_telemetry(train, LATENCY_AR), history=5, modulus_margin=0.1,
                        integral_action=False)  # fmt: skip
    assert res.regularisation == res.validation_regularisation  # the margin did not bind
    eof = np.sum(_closed_loop_residual(res.controller, test, LATENCY_AR) ** 2, axis=0)
    lqg = LQGBank(lqg_state_space(model, LATENCY_AR, 0.0))
    ref = np.sum(_closed_loop_residual(lqg, test, LATENCY_AR) ** 2, axis=0)
    n_frames = test.shape[0] - 100
    assert abs(eof.sum() / n_frames / bound - 1.0) < ORACLE_RTOL
    assert abs(eof.sum() / ref.sum() - 1.0) < ORACLE_RTOL


def test_one_frame_history_misses_the_ar2_optimum(ar2_modes):
    # Twin: an AR(2) needs two past values; with one the residual is far above the bound.
    model, train, test = ar2_modes
    f = np.linspace(0.0, FS / 2, 20_001)
    bound = wiener_bound(loop_plant(FS, LATENCY_AR), f, model.psd(f)).sum()
    res = eof_predictor(_telemetry(train, LATENCY_AR), history=1, modulus_margin=0.1,
                        integral_action=False)  # fmt: skip
    e = _closed_loop_residual(res.controller, test, LATENCY_AR)
    assert np.sum(e**2) / e.shape[0] / bound > 1.0 + 5 * ORACLE_RTOL


def test_integral_action_misses_the_ar2_optimum_by_its_price(ar2_modes):
    # Twin of the Wiener oracle: with F(1) = I the predictor cannot be the Wiener predictor
    # of a stationary AR process (whose DC gain is below 1), so the 2 % check fails; the
    # price of integral action on these modes stays small (measured 1.080 of the bound).
    model, train, test = ar2_modes
    f = np.linspace(0.0, FS / 2, 20_001)
    bound = wiener_bound(loop_plant(FS, LATENCY_AR), f, model.psd(f)).sum()
    res = eof_predictor(_telemetry(train, LATENCY_AR), history=5, modulus_margin=0.1)
    e = _closed_loop_residual(res.controller, test, LATENCY_AR)
    ratio = np.sum(e**2) / e.shape[0] / bound
    assert 1.0 + ORACLE_RTOL < ratio < 1.15, ratio


# -- frozen flow -----------------------------------------------------------------------------

FF_MODES, FF_LATENCY, FF_NOISE, FF_HISTORY, FF_MARGIN = 20, 1.0, 1.0, 20, 0.4


@pytest.fixture(scope="module")
def frozen_flow():
    """Telemetry of an integrator on one frozen-flow layer (20 m/s), 1 nm of noise per frame,
    and a function running a controller on a fresh part of the sky (another seed)."""
    pupil = vlt_pupil(32)
    basis = kl_basis(DeformableMirror(pupil, n_actuators=11), FF_MODES, r0=0.15)

    def run(ctrl, seed, record=()):
        # Bicubic screen interpolation: the bilinear one adds a pixel-crossing modulation
        # that no time-invariant predictor can follow (it floors every predictor alike).
        atm = Atmosphere(pupil, 0.15, [Layer(0.0, 1.0, 20.0, 30.0)], FS, rng=seed,
                         interpolation="cubic")  # fmt: skip
        stage = Stage(ctrl, LinearModalSensor(1.0, FF_NOISE), FF_LATENCY)
        return run_loop(stage, TurbulenceSource(atm, basis), 6000, rng=seed + 100,
                        record=record, settle_frames=200)  # fmt: skip

    res = run(Integrator(0.4, fs=FS, n_modes=FF_MODES), 1, ("measurements", "commands"))
    m = np.asarray(res.telemetry["measurements"], dtype=float)
    u = np.asarray(res.telemetry["commands"], dtype=float)
    return LoopTelemetry(m, u, FS, FF_LATENCY), run


def test_frozen_flow_predictor_beats_the_modal_lqg(frozen_flow):
    # The multi-mode predictor, certified at a multivariable margin of 0.4, against the LQG
    # designed from the same telemetry (AR(2) per mode, noise from the telemetry), both at
    # latency 1 frame, scored on another stretch of sky. Measured: 1.83x (seeds 1/2; 2.08x
    # for the free predictor on this stationary sky).
    tel, run = frozen_flow
    eof = eof_predictor(tel, history=FF_HISTORY, modulus_margin=FF_MARGIN)
    assert eof.certificate.certified and eof.certificate.margin >= FF_MARGIN
    lqg = lqg_from_telemetry(tel.measurements, tel.commands, loop_plant(FS, FF_LATENCY),
                             n_vibrations=0)  # fmt: skip
    r_eof = run(eof.controller, 2).residual_variance.sum()
    r_lqg = run(lqg, 2).residual_variance.sum()
    assert r_lqg / r_eof > 1.5, (r_lqg, r_eof)


def test_frozen_flow_gain_needs_the_other_modes(frozen_flow):
    # Twin: the same training per mode (each mode from its own past, same history and
    # margin) loses part of the gain; the coupling across modes is worth > 15 % here
    # (measured 1.22x; 1.34x for the free predictors).
    tel, run = frozen_flow
    full = eof_predictor(tel, history=FF_HISTORY, modulus_margin=FF_MARGIN).controller
    pol = pseudo_open_loop(tel.measurements, tel.commands, loop_plant(FS, FF_LATENCY))[3:]
    taps = np.zeros((FF_HISTORY, FF_MODES, FF_MODES))
    for i in range(FF_MODES):
        one = eof_from_pseudo_open_loop(pol[:, [i]], FS, FF_LATENCY, history=FF_HISTORY,
                                        modulus_margin=FF_MARGIN)  # fmt: skip
        taps[:, i, i] = one.controller.taps[:, 0, 0]
    per_mode = MultiModeBank(taps, FS, FF_LATENCY)
    r_full = run(full, 2).residual_variance.sum()
    r_diag = run(per_mode, 2).residual_variance.sum()
    assert r_diag / r_full > 1.15, (r_diag, r_full)


# -- integral action -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ar2_telemetry(ar2_modes):
    """6,000 frames of integrator telemetry on the AR(2) modes (zero-mean, stationary)."""
    _, train, _ = ar2_modes
    return _telemetry(train[:6000], LATENCY_AR)


@pytest.mark.parametrize("regularisation", [1e-8, 1e-2, 1.0, 1e4, None])
def test_integral_action_puts_a_zero_of_the_sensitivity_at_dc(ar2_telemetry, regularisation):
    # Oracle: G(1) = 1, so S(1) = I - sum_j A_j, and the constraint F(1) = I makes it 0 to
    # rounding whatever the weight (given, or chosen on data and raised to a margin of 0.5).
    # Twin: the free predictor of these zero-mean stationary modes has a DC gain well below I.
    res = eof_predictor(ar2_telemetry, history=3, regularisation=regularisation,
                        modulus_margin=0.5)  # fmt: skip
    assert res.integral_action and res.certificate.certified
    s_dc = np.eye(4) - res.controller.taps.sum(axis=0)
    assert np.abs(s_dc).max() < 1e-12
    free = eof_predictor(ar2_telemetry, history=3, regularisation=regularisation,
                         modulus_margin=0.5, integral_action=False)  # fmt: skip
    assert np.abs(np.eye(4) - free.controller.taps.sum(axis=0)).max() > 0.05


def test_an_offset_is_rejected_exactly_with_integral_action(ar2_telemetry):
    # Oracle: S = I - G F is FIR of degree D = k + 1 + ceil(f) + h - 1, so from frame D on the
    # residual of a constant disturbance c is exactly S(1) c: 0 with integral action, and
    # (I - F(1)) c for the free predictor trained on zero-mean data (the static error of a
    # loop without integral action, on an offset the training record did not hold).
    # Float64 real-time path; the recorded residual is float32 (relative rounding 6e-8).
    c = np.array([100.0, -50.0, 30.0, 80.0])
    d = np.tile(c, (60, 1))
    h = 3
    k0, f = split_latency(LATENCY_AR)
    degree = k0 + 1 + (1 if f > 0 else 0) + h - 1
    for integral in (True, False):
        res = eof_predictor(ar2_telemetry, history=h, modulus_margin=0.5, precision="float64",
                            integral_action=integral)  # fmt: skip
        e = _closed_loop_residual(res.controller, d, LATENCY_AR, settle=0)[degree:]
        expected = (np.eye(4) - res.controller.taps.sum(axis=0)) @ c
        np.testing.assert_allclose(e, np.tile(expected, (e.shape[0], 1)), rtol=0,
                                   atol=1e-6 * np.abs(c).max())  # fmt: skip
        if not integral:
            assert np.abs(expected).max() > 0.05 * np.abs(c).max()


def test_random_walks_certified_at_half_margin_beat_the_best_integrator():
    # Four random walks (all power at low frequency, like turbulence seen by a slow loop) plus
    # 1 nm of white measurement noise, latency 1 frame. The predictor, trained on 6,000 frames
    # of integrator telemetry and certified at a margin of 0.5, against the best integrator
    # (gain scanned, no margin required) on the same fresh record and noise. Measured 10.6
    # against 11.3 nm^2 (gain 0.40). Twin: the free predictor, whose DC gain misses I by
    # ~1 %, keeps a static error on the walks and loses to the integrator (13.0 nm^2).
    rng = np.random.default_rng(7)
    train = np.cumsum(rng.standard_normal((6000, 4)), axis=0)
    test = np.cumsum(rng.standard_normal((20_000, 4)), axis=0)
    latency, noise = 1.0, 1.0
    stage = Stage(Integrator(0.3, fs=FS, n_modes=4), LinearModalSensor(1.0, noise), latency)
    tel = run_loop(stage, ModalTimeSeries(train, FS), train.shape[0], rng=1,
                   record=("measurements", "commands")).telemetry  # fmt: skip
    tel = LoopTelemetry(np.asarray(tel["measurements"], dtype=float),
                        np.asarray(tel["commands"], dtype=float), FS, latency)  # fmt: skip

    def score(ctrl):
        e = _closed_loop_residual(ctrl, test, latency, settle=200, noise=noise, rng=2)
        return float(np.mean(np.sum(e**2, axis=1)))

    gains = np.arange(0.25, 0.6, 0.05)
    integrators = [score(Integrator(g, fs=FS, n_modes=4)) for g in gains]
    best = int(np.argmin(integrators))
    assert 0 < best < gains.size - 1  # the scan brackets the best gain
    eof = eof_predictor(tel, history=5, modulus_margin=0.5)
    assert eof.certificate.certified and eof.certificate.margin >= 0.5
    assert score(eof.controller) <= integrators[best]
    free = eof_predictor(tel, history=5, modulus_margin=0.5, integral_action=False)
    assert score(free.controller) > integrators[best]


@pytest.mark.parametrize(("history", "latency"), [(2, 1.0), (4, LATENCY_AR), (5, 3.0)])
def test_large_weight_limit_is_the_mean_of_the_history(ar2_modes, history, latency):
    # Oracle: lam -> inf gives A_j = I / h (the smallest ||A|| with F(1) = I), whose loop
    # S = (1 - G M_h) I has the margin 1 / max |1 - G M_h| (brute force on 100,001
    # frequencies), above 1/2 for h >= 2; the certificate brackets it.
    _, train, _ = ar2_modes
    res = eof_from_pseudo_open_loop(train[:3000], FS, latency, history=history,
                                    regularisation=1e12, modulus_margin=0.5)  # fmt: skip
    np.testing.assert_allclose(res.controller.taps, np.tile(np.eye(4) / history, (history, 1, 1)),
                               rtol=0, atol=1e-9)  # fmt: skip
    theta = np.linspace(0.0, np.pi, 100_001)
    zi = np.exp(-1j * theta)
    k0, f = split_latency(latency)
    g = zi ** (k0 + 1) * ((1 - f) + f * zi)
    mean = np.mean(zi[:, None] ** np.arange(history), axis=1)
    brute = 1.0 / np.abs(1.0 - g * mean).max()
    cert = res.certificate
    assert 0.5 < brute and cert.margin <= brute <= cert.margin_upper * (1 + 1e-12)


def test_a_margin_beyond_the_limit_is_refused_at_once(ar2_modes):
    # History 1 with integral action is persistence: S = 1 - z^-2 at latency 1, margin 1/2
    # exactly, which a certificate cannot prove; history 2 has the limit margin 0.549 (the
    # oracle above): 0.6 is refused naming the limit, 0.5 is certified.
    _, train, _ = ar2_modes
    pol = train[:3000]
    with pytest.raises(EOFNotCertifiedError, match="limit for a large regularisation"):
        eof_from_pseudo_open_loop(pol, FS, 1.0, history=1, modulus_margin=0.5)
    with pytest.raises(EOFNotCertifiedError, match=r"mean of the last 2 frames\) at most 0\.5"):
        eof_from_pseudo_open_loop(pol, FS, 1.0, history=2, modulus_margin=0.6)
    ok = eof_from_pseudo_open_loop(pol, FS, 1.0, history=2, modulus_margin=0.5)
    assert ok.certificate.certified and ok.certificate.margin >= 0.5


# -- real-time path --------------------------------------------------------------------------


def _reference(taps, latency, m, limit=None):
    """The documented recursion in plain numpy, float64: POL from the applied commands."""
    h, n, _ = taps.shape
    k0, f = split_latency(latency)
    u = np.zeros((m.shape[0], n))
    p = np.zeros_like(u)
    for k in range(m.shape[0]):
        p[k] = m[k]
        if k - 1 - k0 >= 0:
            p[k] += (1 - f) * u[k - 1 - k0]
        if k - 2 - k0 >= 0:
            p[k] += f * u[k - 2 - k0]
        u[k] = sum(taps[j] @ p[k - j] for j in range(h) if k - j >= 0)
        if limit is not None:
            u[k] = np.clip(u[k], -limit, limit)
    return u


def _random_bank_inputs(n=7, h=4, seed=3):
    rng = np.random.default_rng(seed)
    taps = 0.25 * rng.standard_normal((h, n, n)) / np.sqrt(n)
    return taps, rng.standard_normal((300, n))


@pytest.mark.parametrize("latency", [0.0, 0.4, 1.0, 2.7])
def test_step_equals_plain_numpy_reference_float64(latency):
    # Two paths, one recursion: equal to rounding (summation order differs).
    taps, m = _random_bank_inputs()
    bank = MultiModeBank(taps, FS, latency, precision="float64")
    u = np.array([bank.step(x) for x in m])
    ref = _reference(taps, latency, m)
    np.testing.assert_allclose(u, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_step_float32_error_is_within_its_stated_bound():
    # The float32 product's error: ~sqrt(h n) 2^-24 of the command scale typically, bounded
    # in the class docstring; 1e-4 of the command scale is the stated test bound (measured
    # ~1e-6 here). The float64 twin is 1e-6 times closer, so the bound is not vacuous.
    taps, m = _random_bank_inputs(n=40, h=5)
    ref = _reference(taps, 0.83, m)
    u32 = np.array([x for x in map(MultiModeBank(taps, FS, 0.83).step, m)])
    u64 = np.array([x for x in map(MultiModeBank(taps, FS, 0.83, precision="float64").step, m)])
    scale = np.abs(ref).max()
    err32 = np.abs(u32 - ref).max() / scale
    assert 1e-9 < err32 < 1e-4
    assert np.abs(u64 - ref).max() / scale < 1e-6 * err32


def test_command_limit_clips_and_feeds_the_applied_command_back():
    # Anti-windup: the POL is rebuilt from the applied (clipped) commands; oracle the plain
    # numpy recursion with the clip inside the loop. Saturations are counted per mode.
    taps, m = _random_bank_inputs()
    limit = np.full(7, 0.3)
    limit[0] = 100.0  # never reached
    bank = MultiModeBank(taps, FS, 1.4, command_limit=limit, precision="float64")
    u = np.array([bank.step(10 * x) for x in m])
    ref = _reference(taps, 1.4, 10 * m, limit)
    np.testing.assert_allclose(u, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert np.all(np.abs(u) <= limit)
    assert bank.n_saturated[0] == 0 and np.all(bank.n_saturated[1:] > 0)
    assert not np.allclose(ref, _reference(taps, 1.4, 10 * m)[:, :].clip(-limit, limit))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nonfinite_frame_is_rejected_and_state_kept_clean(bad):
    # The project's policy: the run with a bad frame at j equals the run with frame j removed,
    # the command of frame j being the held command (bit for bit).
    taps, m = _random_bank_inputs()
    bank = MultiModeBank(taps, FS, 0.83)
    j = 41
    bad_m = m.copy()
    bad_m[j, 3] = bad
    y_bad = np.array([bank.step(x) for x in bad_m])
    assert bank.n_rejected == 1
    bank.reset()
    assert bank.n_rejected == 0
    y_ref = np.array([bank.step(x) for x in np.delete(m, j, axis=0)])
    np.testing.assert_array_equal(y_bad[:j], y_ref[:j])
    np.testing.assert_array_equal(y_bad[j], y_bad[j - 1])
    np.testing.assert_array_equal(y_bad[j + 1 :], y_ref[j:])


def test_impulse_matrix_matches_step_and_frequency_response():
    # The real-time path's response to a unit impulse on mode c is column c of the transfer
    # matrix's impulse response; its DFT is the frequency response K = (I - F G)^-1 F (a
    # stable controller: small taps).
    taps, _ = _random_bank_inputs(n=5, h=3)
    bank = MultiModeBank(taps, FS, 1.4, precision="float64")
    K = bank.impulse_matrix(400)
    for c in range(5):
        bank.reset()
        x = np.zeros((40, 5))
        x[0, c] = 1.0
        y = np.array([bank.step(v) for v in x])
        np.testing.assert_allclose(y, K[:40, :, c], rtol=0, atol=1e-14)
    np.testing.assert_allclose(bank.impulse_response(40), K[:40].sum(axis=2), atol=1e-14)
    assert np.abs(K[-1]).max() < 1e-12  # decayed: the sum below is the full response
    f = np.linspace(0.0, FS / 2, 9)
    zi = np.exp(-2j * np.pi * f / FS)
    dft = np.tensordot(zi[:, None] ** np.arange(400), K, axes=(1, 0))
    np.testing.assert_allclose(bank.frequency_response(f), dft, atol=1e-10)


def test_set_history_is_bumpless():
    # A bank started from the last frames of a run continues exactly as the running bank.
    taps, m = _random_bank_inputs()
    running = MultiModeBank(taps, FS, 1.4, precision="float64")
    u = np.array([running.step(x) for x in m[:200]])
    fresh = MultiModeBank(taps, FS, 1.4, precision="float64")
    fresh.set_history(m[:200], u)
    for x in m[200:]:
        np.testing.assert_allclose(fresh.step(x), running.step(x), rtol=0, atol=1e-12)


def test_transfer_function_is_refused_with_a_pointer():
    bank = MultiModeBank(np.zeros((1, 2, 2)), FS, 0.0)
    with pytest.raises(NotImplementedError, match="frequency_response"):
        bank.transfer_function(0)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_save_load_round_trip(tmp_path, precision):
    taps, m = _random_bank_inputs()
    bank = MultiModeBank(taps, FS, 0.83, command_limit=0.5, precision=precision)
    path = save_controller(bank, tmp_path / "eof.h5")
    back = load_controller(path)
    assert isinstance(back, MultiModeBank) and back.precision == precision
    np.testing.assert_array_equal(back.taps, bank.taps)
    np.testing.assert_array_equal(back.command_limit, bank.command_limit)
    assert back.latency_frames == bank.latency_frames and back.fs == bank.fs
    np.testing.assert_array_equal([back.step(x) for x in m], [bank.step(x) for x in m])


# -- certificate -----------------------------------------------------------------------------


@pytest.mark.parametrize("latency", [0.0, 0.4, 1.0, 1.7])
def test_certified_margin_brackets_a_brute_force_scan(latency):
    # Oracle: 1 / max sigma_max(I - G F) over 100,001 frequencies by dense SVD. The certified
    # margin is below it, the best grid value above it, and they agree within rtol.
    rng = np.random.default_rng(int(10 * latency))
    taps = 0.2 * rng.standard_normal((3, 6, 6))
    bank = MultiModeBank(taps, FS, latency)
    cert = multimode_certificate(bank)
    theta = np.linspace(0.0, np.pi, 100_001)
    zi = np.exp(-1j * theta)
    k0, f = split_latency(latency)
    g = zi ** (k0 + 1) * ((1 - f) + f * zi)
    F = np.tensordot(zi[:, None] ** np.arange(3), taps, axes=(1, 0))
    brute = 1.0 / np.linalg.svd(np.eye(6) - g[:, None, None] * F, compute_uv=False)[:, 0].max()
    assert cert.stable and cert.converged
    assert cert.margin <= brute <= cert.margin_upper * (1 + 1e-12)
    assert cert.margin_upper / cert.margin - 1 <= cert.rtol * 1.01


@pytest.mark.parametrize("where", [0.2, 0.5, 0.8])
def test_a_requirement_inside_the_tolerance_is_decided_the_same_in_full(where):
    # A required margin between the certified bound and the best grid value (within rtol
    # of each other) is undecided at convergence: the full certificate refines on until it
    # decides, and decides as decide_only does; a certified verdict has margin >= required.
    # (Training returned an uncertified predictor before: the search decided, the final
    # full certificate stopped at its tolerance below the requirement.)
    rng = np.random.default_rng(3)
    bank = MultiModeBank(0.2 * rng.standard_normal((3, 6, 6)), FS, 0.4)
    free = multimode_certificate(bank)
    required = free.margin + where * (free.margin_upper - free.margin)
    full = multimode_certificate(bank, modulus_margin=required)
    decide = multimode_certificate(bank, modulus_margin=required, decide_only=True)
    assert full.certified == decide.certified
    assert (full.margin >= required) == full.certified
    assert full.certified or full.margin_upper < required


def test_certificate_refuses_a_predictor_built_to_be_unstable():
    # u = 3 p at latency 0: S = (1 - 3 z^-1) I, max |S| = 4 at Nyquist, margin 1/4 exactly.
    # Nominally every closed-loop map is FIR, but the controller 3 / (1 - 3 z^-1) is unstable
    # and a loop-gain error og moves the closed-loop pole to 3 (1 - og): og = 0.6 (a 40 %
    # perturbation, beyond the margin) diverges, og = 0.9 does not. Twin: u = 0.5 p passes.
    bad = MultiModeBank(3.0 * np.eye(3)[None], FS, 0.0)
    cert = multimode_certificate(bad, modulus_margin=0.5)
    assert not cert.certified and cert.margin <= 0.25 <= cert.margin_upper + 1e-12
    assert abs(np.abs(multimode_closed_loop_poles(bad, optical_gain=0.6)).max() - 1.2) < 1e-9
    assert np.abs(multimode_closed_loop_poles(bad, optical_gain=0.9)).max() < 1.0
    good = MultiModeBank(0.5 * np.eye(3)[None], FS, 0.0)
    assert multimode_certificate(good, modulus_margin=0.5).certified


def test_nominal_loop_flushes_and_mismatched_latency_is_decided_by_poles():
    # Structural stability, checked on the real-time path (the flush); with a true latency
    # one frame longer than the model the loop is no longer FIR and its poles decide.
    taps, _ = _random_bank_inputs(n=4, h=3)
    bank = MultiModeBank(taps, FS, 0.4)
    cert = multimode_certificate(bank)
    assert cert.stable and cert.flush_residual < 1e-12
    poles = multimode_closed_loop_poles(bank, latency_frames=1.4)
    assert np.abs(poles).max() > 1e-3  # not nilpotent any more
    unstable = MultiModeBank(3.0 * np.eye(2)[None], FS, 0.0)
    assert np.abs(multimode_closed_loop_poles(unstable, latency_frames=1.0)).max() > 1.0


def _loop_growth_rate(bank, latency, og, mixing, dm, n_frames=400):
    """Growth rate per frame of the commands of ``bank`` in closed loop with the true plant
    ``diag(og) M G_t H`` (d = n = 0), by an independent difference-equation loop: the DM
    filtered by ``scipy.signal.lfilter`` with its state carried, the delay line by hand."""
    from scipy.signal import lfilter, lfilter_zi

    rng = np.random.default_rng(5)
    n = bank.n_modes
    probe = MultiModeBank(bank.taps, bank.fs, bank.latency_frames, precision="float64")
    probe.set_history(rng.standard_normal((bank.history + 4, n)), np.zeros((bank.history + 4, n)))
    k, f = split_latency(latency)
    b, a = dm
    zi = np.zeros((max(len(a), len(b)) - 1, n)) * lfilter_zi(b, a)[:, None] if len(a) > 1 else None
    pos = [np.zeros(n)] * (k + 3)  # DM positions, newest first: pos[i] at frame j - i
    norms = []
    for _ in range(n_frames):
        m = -(og * (mixing @ ((1 - f) * pos[k] + f * pos[k + 1])))
        u = probe.step(m)
        if zi is None:
            x = b[0] / a[0] * u
        else:
            x, zi = lfilter(b, a, u[None, :], axis=0, zi=zi)
            x = x[0]
        pos = [x, *pos[:-1]]
        norms.append(np.linalg.norm(u))
    # The slope of log |u| over the second half (a least-squares line averages the beating
    # of a complex pair); 400 frames keep a decay from 0.5 per frame above underflow.
    half = n_frames // 2
    slope = np.polyfit(np.arange(half, n_frames), np.log(norms[half:]), 1)[0]
    return np.exp(slope)


@pytest.mark.parametrize(
    ("latency", "og", "tau", "shift"),
    [
        (1.2, 1.0, 0.0, 0.0),
        (0.5, 1.4, 0.0, 0.1),
        (0.5, 1.0, 0.6, 0.0),
        (0.9, 0.8, 0.3, 0.05),
        (2.5, 1.2, 0.5, 0.05),
        (0.5, 3.0, 0.0, 0.1),
    ],  # fmt: skip
)
def test_closed_loop_poles_with_dm_lag_and_mixing_match_a_time_domain_loop(latency, og, tau, shift):
    # The poles with a true plant other than the model (latency, per-mode optical gains, a DM
    # first-order lag, a mixing of the modes) against the growth rate of an independent loop:
    # the largest pole modulus is the commands' growth (or decay) per frame.
    from aocontrol.sim.model_errors import DMResponse

    rng = np.random.default_rng(11)
    n = 4
    bank = MultiModeBank(
        0.25 * rng.standard_normal((3, n, n)) + 0.4 * np.eye(n)[None] * [[[1]], [[0.5]], [[0]]],
        FS,
        0.5,
    )
    gains = og * np.linspace(0.9, 1.1, n)
    mixing = np.eye(n) + shift * rng.standard_normal((n, n))
    dm = DMResponse(time_constant=tau * 1e-3).coefficients(FS)
    poles = multimode_closed_loop_poles(
        bank, latency_frames=latency, optical_gain=gains, mixing=mixing, dm_coefficients=dm
    )
    radius = np.abs(poles).max()
    assert abs(radius - 1.0) > 0.01  # a decided case, not one on the edge
    assert _loop_growth_rate(bank, latency, gains, mixing, dm) == pytest.approx(radius, abs=5e-3)


def test_simulator_checks_a_multimode_loop_under_model_errors_before_the_run():
    # The simulator's pre-run check covers a MultiModeBank (the coupled loop's poles, the
    # DM's lag included): 0 on the nominal plant (structurally FIR), the analysis's radius
    # under a latency error and a DM lag, and a slowly diverging run is reported diverged
    # (the growth guards alone let this loop, pole radius 1.03, run 300 frames).
    from aocontrol.sim.loop import LoopDivergedError, closed_loop_pole_radius
    from aocontrol.sim.model_errors import DMResponse

    rng = np.random.default_rng(11)
    n = 4
    taps = 0.25 * rng.standard_normal((3, n, n)) + 0.4 * np.eye(n)[None] * [[[1]], [[0.5]], [[0]]]
    bank = MultiModeBank(taps, FS, 0.5)
    assert not np.any(closed_loop_pole_radius(Stage(bank, latency_frames=0.5), np.ones(n)))
    lag = DMResponse(time_constant=0.5e-3)
    stage = Stage(bank, latency_frames=2.5, dm=ModalDM(n, response=lag))
    radius = closed_loop_pole_radius(stage, 1.2 * np.ones(n))
    expected = np.abs(multimode_closed_loop_poles(
        bank, latency_frames=2.5, optical_gain=1.2, dm_coefficients=lag.coefficients(FS)
    )).max()  # fmt: skip
    np.testing.assert_allclose(radius, expected, rtol=1e-12)
    assert radius[0] > 1.0
    d = 1e-3 * rng.standard_normal((300, n))
    with pytest.raises(LoopDivergedError, match="linear closed loop is unstable"):
        run_loop(stage, ModalTimeSeries(d, FS), 300)


def test_closed_loop_poles_refuse_bad_plant_errors():
    bank = MultiModeBank(0.5 * np.eye(2)[None], FS, 0.5)
    with pytest.raises(ValueError, match="optical_gain"):
        multimode_closed_loop_poles(bank, optical_gain=[1.0, -1.0])
    with pytest.raises(ValueError, match="mixing must have shape"):
        multimode_closed_loop_poles(bank, mixing=np.eye(3))
    with pytest.raises(ValueError, match="dm_coefficients"):
        multimode_closed_loop_poles(bank, dm_coefficients=([1.0], [0.0, 1.0]))


def test_training_regularises_further_until_the_margin_is_certified(ar2_modes):
    # The AR(2) predictor's own margin is ~0.2: asking for 0.5 raises the weight above the
    # validation choice until the certificate passes; the validation choice alone fails.
    model, train, _ = ar2_modes
    tel = _telemetry(train[:6000], LATENCY_AR)
    res = eof_predictor(tel, history=3, modulus_margin=0.5)
    assert res.certificate.certified and res.certificate.margin >= 0.5
    assert res.regularisation > res.validation_regularisation
    plain = eof_predictor(tel, history=3, regularisation=res.validation_regularisation,
                          modulus_margin=0.01)  # fmt: skip
    assert plain.certificate.margin_upper < 0.5


def test_registry_entry_designs_from_the_telemetrys_pseudo_open_loop(ar2_modes):
    # The registry's "eof": the POL of the telemetry estimate, the plant's latency, the design
    # margin; the same predictor as eof_predictor on the same telemetry.
    _, train, _ = ar2_modes
    tel = _telemetry(train[:6000], LATENCY_AR)
    plant = loop_plant(FS, LATENCY_AR)
    est = disturbance_from_telemetry(tel.measurements, tel.commands, plant)
    inputs = DesignInputs(plant, est.freqs, est.psd, est.noise_psd, FS, 4, 0.3, telemetry=est,
                          modulus_margin=0.3, options={"history": 3})  # fmt: skip
    bank, details = get_controller("eof").build(inputs)
    assert isinstance(bank, MultiModeBank) and details.certificate.certified
    assert details.certificate.margin >= 0.3 and bank.history == 3
    direct = eof_predictor(tel, history=3, modulus_margin=0.3)
    np.testing.assert_allclose(bank.taps, direct.controller.taps, rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="needs telemetry"):
        get_controller("eof").build(DesignInputs(plant, est.freqs, est.psd, est.noise_psd, FS,
                                                 4, 0.3))  # fmt: skip
    # Without the option, the history the regressor budget allows: 4 modes -> the longest.
    default = DesignInputs(plant, est.freqs, est.psd, est.noise_psd, FS, 4, 0.3, telemetry=est,
                           modulus_margin=0.3)  # fmt: skip
    assert get_controller("eof").build(default)[0].history == EOF_MAX_HISTORY


@pytest.mark.parametrize(
    ("n_modes", "history"), [(1, EOF_MAX_HISTORY), (135, 20), (136, 19), (540, 5), (1200, 5)]
)
def test_default_history_keeps_the_regressors_within_budget(n_modes, history):
    assert eof_default_history(n_modes) == history
    assert history == EOF_HISTORY or n_modes * history <= EOF_REGRESSORS


@pytest.mark.parametrize("bad", [0, -3, 2.5, "24"])
def test_default_history_names_a_bad_mode_count(bad):
    with pytest.raises(ValueError, match="n_modes must be an integer >= 1"):
        eof_default_history(bad)


# -- bad input -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_pol():
    rng = np.random.default_rng(0)
    return rng.standard_normal((400, 4))


@pytest.mark.parametrize(
    ("kwargs", "exc", "match"),
    [
        ({"history": 0}, ValueError, "history must be an integer >= 1, got 0"),
        ({"history": -2}, ValueError, "history must be an integer >= 1, got -2"),
        ({"regularisation": -0.1}, ValueError, "regularisation must be a finite number >= 0"),
        ({"validation_fraction": 0.0}, ValueError, "validation_fraction must be in"),
        ({"modulus_margin": 1.0}, ValueError, "modulus_margin must be in"),
        ({"history": 2.5}, TypeError, "history must be an integer"),
    ],
)
def test_bad_arguments_are_named(small_pol, kwargs, exc, match):
    with pytest.raises(exc, match=match):
        eof_from_pseudo_open_loop(small_pol, FS, 0.5, **kwargs)


def test_short_telemetry_says_how_much_is_needed(small_pol):
    # 4 modes x history 30 = 120 unknowns per mode; with 20 % held back 151 equations, plus
    # history + k + 1 = 31 frames of start-up: 182 frames.
    with pytest.raises(ValueError, match="has 150 frames.*needs at least 182"):
        eof_from_pseudo_open_loop(small_pol[:150], FS, 0.5, history=30)
    eof_from_pseudo_open_loop(small_pol[:182], FS, 0.5, history=30, modulus_margin=0.01)
    with pytest.raises(ValueError, match="telemetry has 100 frames"):
        eof_predictor(LoopTelemetry(small_pol[:100], small_pol[:100], FS, 0.5), history=30)


def test_nan_frames_are_refused_naming_the_argument(small_pol):
    bad = small_pol.copy()
    bad[17, 2] = np.nan
    with pytest.raises(ValueError, match="pseudo_open_loop must contain only finite"):
        eof_from_pseudo_open_loop(bad, FS, 0.5)
    with pytest.raises(ValueError, match="measurements must contain only finite"):
        LoopTelemetry(bad, small_pol, FS, 0.5)


def test_unknown_latency_and_bad_taps_are_named(small_pol):
    with pytest.raises(ValueError, match="latency_frames must be given"):
        eof_predictor(LoopTelemetry(small_pol, small_pol, FS))
    with pytest.raises(ValueError, match=r"taps must have shape \(history, n_modes, n_modes\)"):
        MultiModeBank(np.zeros((2, 3, 4)), FS, 0.0)
    with pytest.raises(ValueError, match="precision must be one of"):
        MultiModeBank(np.zeros((1, 2, 2)), FS, 0.0, precision="float16")
