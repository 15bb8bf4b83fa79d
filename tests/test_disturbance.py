"""Tests of aocontrol.disturbance: turbulence-like modal PSDs and vibration PSDs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, signal, special

from aocontrol.disturbance import (
    modal_variances,
    psd_variance,
    radial_orders,
    resonator_ar2,
    synthetic_turbulence_psd,
    vibration_psd,
)

NM_PER_RAD_500 = 500.0 / (2 * np.pi)


def _slope(f, p, f1, f2):
    """Log-log slope of p between f1 and f2 (by interpolation on the grid)."""
    p1, p2 = np.interp([f1, f2], f, p)
    return np.log(p2 / p1) / np.log(f2 / f1)


def test_radial_orders_count_n_plus_one_modes_per_order():
    # Oracle: Zernike/KL ordering has n + 1 modes of radial order n (piston excluded).
    n = radial_orders(5000)
    orders, counts = np.unique(n, return_counts=True)
    assert orders[0] == 1
    assert np.all(np.diff(n) >= 0)
    assert np.array_equal(counts[:-1], orders[:-1] + 1)


def test_kolmogorov_variances_match_noll_table():
    # Oracle: Noll (1976) Table IV residuals Delta_J [(D/r0)^(5/3) rad^2]; the variance of
    # mode j is Delta_{j} - Delta_{j+1}: tip 1.0299-0.582, focus 0.134-0.111,
    # coma (j=7) 0.0648-0.0587. Table values have 3-4 digits.
    tol = 0.02
    d_r0 = 8.0 / 0.15
    v = modal_variances(6, diameter=8.0, r0=0.15, L0=np.inf) / NM_PER_RAD_500**2
    v /= d_r0 ** (5 / 3)
    for got, want in [(v[0], 1.0299 - 0.582), (v[2], 0.134 - 0.111), (v[5], 0.0648 - 0.0587)]:
        assert abs(got / want - 1) < tol


def test_kolmogorov_total_variance_matches_noll_residual():
    # Oracle: Noll: sum of all modes but piston = 1.0299 (D/r0)^(5/3); the residual after J
    # modes is ~0.2944 J^(-sqrt(3)/2) (D/r0)^(5/3). Tolerance: that residual is a fit, and
    # Noll's tilt (1.0299 - 0.582, 3 digits) is 0.2 % below the exact Gamma-function value.
    tol = 5e-3
    n = 1200
    v = modal_variances(n, diameter=8.0, r0=0.15, L0=np.inf) / NM_PER_RAD_500**2
    want = 1.0299 - 0.2944 * (n + 1) ** (-np.sqrt(3) / 2)
    assert abs(v.sum() / (8.0 / 0.15) ** (5 / 3) / want - 1) < tol


def test_von_karman_tilt_matches_direct_quadrature():
    # Oracle: an independent adaptive quadrature of the von Karman Zernike integral
    # int (x^2 + x0^2)^(-11/6) J_2(x)^2 / x dx over its Kolmogorov value (L0 = inf).
    tol = 1e-3
    x0 = np.pi * 8.0 / 25.0

    def integral(a):
        parts = [(0, 1), (1, 10), (10, 100), (100, 1000), (1000, np.inf)]
        return sum(
            integrate.quad(
                lambda x: (x * x + a * a) ** (-11 / 6) * special.jv(2, x) ** 2 / x,
                lo,
                hi,
                limit=500,
            )[0]
            for lo, hi in parts
        )

    want = integral(x0) / integral(0.0)
    got = modal_variances(1, L0=25.0)[0] / modal_variances(1, L0=np.inf)[0]
    assert abs(got / want - 1) < tol


def test_von_karman_tilt_small_outer_scale_series():
    # Oracle: small-D/L0 expansion of the tilt variance ratio, 1 - 1.42 (D/L0)^(1/3)
    # + 3.7 (D/L0)^2 (Tokovinin 2002, PASP 114, 1156); next-order terms ~1e-3 at D/L0 = 0.01.
    tol = 3e-3
    ratio = 0.01
    got = modal_variances(1, L0=8.0 / ratio)[0] / modal_variances(1, L0=np.inf)[0]
    assert abs(got / (1 - 1.42 * ratio ** (1 / 3) + 3.7 * ratio**2) - 1) < tol


def test_variances_decrease_and_outer_scale_hits_low_orders_most():
    # Invariant: variances non-increasing with mode index; L0 reduces low orders most.
    v = modal_variances(300, L0=25.0)
    vk = modal_variances(300, L0=np.inf)
    assert np.all(np.diff(v) <= 0)
    ratio = v / vk
    assert np.all(np.diff(ratio[np.r_[0, 2, 5, 9, 14, 299]]) > 0)
    assert np.all(ratio < 1)


def test_sampled_psd_integrates_to_modal_variance():
    # Oracle: with fs the aliased spectrum integrates over [0, fs/2] to the variance.
    tol = 1e-4
    fs = 1000.0
    f = np.linspace(0.0, fs / 2, 100001)
    psd = synthetic_turbulence_psd(f, 60, fs=fs, wind_speed=15.0)
    assert psd.shape == (60, f.size)
    var = np.trapezoid(psd, f, axis=-1)
    assert np.max(np.abs(var / modal_variances(60) - 1)) < tol


def test_continuous_psd_integrates_to_variance():
    # Oracle: continuous one-sided PSD integrates over [0, inf) to the variance; a log grid
    # from 1e-6 Hz to 1e5 Hz misses < 1e-5 of it for these cut-offs.
    tol = 1e-3
    f = np.concatenate([[0.0], np.geomspace(1e-6, 1e5, 200001)])
    psd = synthetic_turbulence_psd(f, 20)
    var = np.trapezoid(psd, f, axis=-1)
    assert np.max(np.abs(var / modal_variances(20) - 1)) < tol


def test_psd_asymptotic_slopes():
    # Oracle: Conan et al. (1995): f^(-17/3) above the cut-off 0.3 (n+1) V/D for every mode;
    # f^0 below it for n >= 2, f^(-2/3) for tilt (with L0 huge), flat below 2.15 V/L0.
    tol = 0.02
    f = np.geomspace(1e-5, 1e4, 4001)
    V, D = 10.0, 8.0
    psd = synthetic_turbulence_psd(f, 10, wind_speed=V, diameter=D, L0=1e5)
    fc = lambda n: 0.3 * (n + 1) * V / D  # noqa: E731
    for mode, n in [(0, 1), (2, 2), (9, 4)]:
        hi = _slope(f, psd[mode], 30 * fc(n), 100 * fc(n))
        assert abs(hi / (-17 / 3) - 1) < tol
    assert abs(_slope(f, psd[2], fc(2) / 1000, fc(2) / 100)) < tol
    f_l = 2.15 * V / 1e5
    assert abs(_slope(f, psd[0], 30 * f_l, fc(1) / 30) / (-2 / 3) - 1) < 3 * tol
    assert abs(_slope(f, psd[0], f_l / 1000, f_l / 100)) < tol


def test_psd_scales_with_wind_speed():
    # Oracle: frozen flow: doubling V stretches the spectrum by 2 (same variance):
    # P(f; 2V) = P(f/2; V) / 2 (cut-offs and the tilt outer-scale knee all scale with V).
    tol = 1e-10
    f = np.linspace(0.1, 200.0, 500)
    p1 = synthetic_turbulence_psd(f / 2, 12, wind_speed=8.0)
    p2 = synthetic_turbulence_psd(f, 12, wind_speed=16.0)
    assert np.max(np.abs(p2 / (p1 / 2) - 1)) < tol


def test_vibration_psd_continuous_integral_and_peak():
    # Oracle: int_0^inf of the normalised resonator PSD is the variance; the peak of
    # 1/((f0^2-f^2)^2 + (2 z f0 f)^2) is at f0 sqrt(1 - 2 z^2).
    tol = 1e-3
    f = np.linspace(0.0, 5000.0, 2_000_001)
    p = vibration_psd(f, 40.0, 9.0, 0.02)
    assert abs(np.trapezoid(p, f) / 9.0 - 1) < tol  # tail beyond 5 kHz ~ 1e-7
    peak = f[np.argmax(p)]
    assert abs(peak / (40.0 * np.sqrt(1 - 2 * 0.02**2)) - 1) < tol


def test_vibration_psd_ar2_matches_simulated_process():
    # Oracle: simulate the AR(2) recursion with lfilter; sample variance of 4e5 samples is
    # within ~3 % (correlated samples, damping 0.05) of the stated variance, and the AR(2)
    # PSD integrates exactly (to trapezoid error) over [0, fs/2].
    tol_exact, tol_stat = 1e-4, 0.05
    fs, f0, var, zeta = 1000.0, 60.0, 2.5, 0.05
    f = np.linspace(0.0, fs / 2, 200001)
    p = vibration_psd(f, f0, var, zeta, fs=fs)
    assert abs(np.trapezoid(p, f) / var - 1) < tol_exact
    a1, a2 = resonator_ar2(f0, zeta, fs)
    # Driving variance from the PSD level: P = 2 s_w^2 / fs / |A|^2.
    s_w2 = p[0] * fs / 2 * abs(1 - a1 - a2) ** 2
    rng = np.random.default_rng(7)
    x = signal.lfilter([1.0], [1.0, -a1, -a2], rng.normal(0, np.sqrt(s_w2), 400_000))
    assert abs(np.var(x[1000:]) / var - 1) < tol_stat
    # Continuous and sampled forms agree near the peak for f0 << fs (same resonance).
    pc = vibration_psd(f, f0, var, zeta)
    i = np.argmin(np.abs(f - f0))
    assert abs(p[i] / pc[i] - 1) < 0.05


def test_psd_variance_helper():
    # Oracle: trapezoid of a flat PSD is level * bandwidth.
    f = np.linspace(0.0, 500.0, 11)
    assert abs(float(psd_variance(f, np.full(11, 2e-3))) / 1.0 - 1) < 1e-12


@pytest.mark.parametrize(
    ("kwargs", "err", "match"),
    [
        ({"freqs": [1.0, 0.5]}, ValueError, "strictly increasing"),
        ({"freqs": [-1.0, 2.0]}, ValueError, ">= 0"),
        ({"freqs": [0.0, 600.0], "fs": 1000.0}, ValueError, "Nyquist"),
        ({"freqs": [0.0, np.nan]}, ValueError, "finite"),
        ({"freqs": [0.0, 1.0], "L0": np.inf}, ValueError, "L0 = inf"),
        ({"freqs": [1.0, 2.0], "r0": -0.1}, ValueError, "r0"),
        ({"freqs": [1.0, 2.0], "n_modes": 0}, ValueError, "n_modes"),
        ({"freqs": [1.0, 2.0], "n_modes": 2.5}, TypeError, "n_modes"),
    ],
)
def test_turbulence_psd_bad_input(kwargs, err, match):
    args = {"n_modes": 3, **kwargs}
    with pytest.raises(err, match=match):
        synthetic_turbulence_psd(args.pop("freqs"), args.pop("n_modes"), **args)


@pytest.mark.parametrize(
    ("args", "kwargs", "match"),
    [
        (([0.0, 1.0], 10.0, 1.0, 1.5), {}, "damping"),
        (([0.0, 1.0], 10.0, -1.0, 0.1), {}, "variance"),
        (([0.0, 1.0], -10.0, 1.0, 0.1), {}, "frequency"),
        (([0.0, 1.0], 600.0, 1.0, 0.1), {"fs": 1000.0}, "frequency"),
        (([0.0, 700.0], 60.0, 1.0, 0.1), {"fs": 1000.0}, "Nyquist"),
    ],
)
def test_vibration_psd_bad_input(args, kwargs, match):
    with pytest.raises(ValueError, match=match):
        vibration_psd(*args, **kwargs)
