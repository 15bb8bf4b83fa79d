"""The certificate's Newton polish, the design grid's seeds and warm starts (issue 14, speed).

Oracles: a brute-force minimum of ``|num| / |den|`` on the circle (a dense grid, then zooming
100x per level around its minimum), independent of the stationary-point polynomial; and the
definition of a seed (a local minimum of ``|1 + G K|`` with ``|S| > 1``).
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.polynomial import polynomial as poly

from aocontrol import loop_plant
from aocontrol.analysis import polynomial_certificate
from aocontrol.analysis._certificate import _newton_polish, rational_modulus_minima
from aocontrol.synthesis import _datadriven as dd
from aocontrol.synthesis._dd_certify import _ModeCertifier

# Newton converges quadratically to the stationary point: the value agrees with the brute
# force to round-off, far below this (the issue asks 1e-9 relative).
POLISH_RTOL = 1e-9


def _ratio(num, den, theta):
    w = np.exp(-1j * np.asarray(theta, dtype=float))
    with np.errstate(divide="ignore"):
        return np.abs(poly.polyval(w, num)) / np.abs(poly.polyval(w, den))


def _brute_min(num, den, centre=None, n=1_000_001):
    """min over [0, pi] of |num| / |den| (w = exp(-j theta)): a grid, then 12 zoom levels."""
    theta = np.linspace(0.0, np.pi, n)
    d = _ratio(num, den, theta)
    i = int(np.argmin(d))
    best, c, half = float(d[i]), theta[i], 4 * np.pi / (n - 1)
    centres = [c] if centre is None else [c, centre]
    for c in centres:
        h = half
        for _ in range(12):
            t = np.clip(np.linspace(c - h, c + h, 2001), 0.0, np.pi)
            dt = _ratio(num, den, t)
            j = int(np.argmin(dt))
            best, c, h = min(best, float(dt[j])), t[j], h / 100
    return best


def _pole_case(radius=0.9999, f0=915.0, fs=3000.0):
    """|1 + G K| = |P| / |Y| with a controller pole pair at ``radius`` and a closed-loop pair
    at the same radius 0.3 Hz away: a dip ~(1 - r) fs / pi wide, ~1e-4 deep."""
    th_k, th_p = 2 * np.pi * f0 / fs, 2 * np.pi * (f0 + 0.3) / fs
    Y = np.convolve([1.0, -1.0], [1.0, -2 * radius * np.cos(th_k), radius**2])
    P = np.convolve([1.0, -2 * radius * np.cos(th_p), radius**2], [1.0, 0.5])
    return P, Y, th_p


@pytest.mark.parametrize("radius", [0.9999, 0.99999])
def test_newton_polish_equals_the_brute_force_minimum(radius):
    num, den, th_p = _pole_case(radius)
    theta, vals = rational_modulus_minima(num, den)
    truth = _brute_min(num, den, centre=th_p)
    assert vals.min() <= truth * (1 + POLISH_RTOL)
    assert vals.min() == pytest.approx(truth, rel=POLISH_RTOL)
    # The values are those of the exact expression at the returned angles (away from the
    # integrator's pole at 0 Hz, where both are round-off over zero).
    exact = _ratio(num, den, theta)
    finite = exact < 1e6
    np.testing.assert_allclose(vals[finite], exact[finite], rtol=POLISH_RTOL)


def test_newton_polish_recovers_a_displaced_stationary_point():
    # Started 8e-5 rad off the minimum (the dip's width at radius 0.9999 is ~1e-4 rad), the
    # raw value is far above the minimum (relative 1e-3 >> 1e-9); the polish brings it back
    # to the brute force.
    num, den, th_p = _pole_case(0.9999)
    truth = _brute_min(num, den, centre=th_p)
    theta, vals = rational_modulus_minima(num, den)
    t0 = theta[np.argmin(vals)] + 8e-5
    raw = _ratio(num, den, [t0])
    assert raw[0] > (1 + 1e-3) * truth  # the twin: unpolished, it overstates the margin
    t, v = _newton_polish(num / den.max(), den / den.max(), np.array([t0]), raw)
    assert v[0] == pytest.approx(truth, rel=POLISH_RTOL)
    assert abs(t[0] - theta[np.argmin(vals)]) < 1e-8


def test_newton_polish_never_raises_a_value():
    # At a local maximum (negative curvature) no step is taken; elsewhere the value kept is
    # the smallest seen.
    rng = np.random.default_rng(3)
    for _ in range(20):
        num, den = rng.normal(size=7), rng.normal(size=7) + np.r_[3.0, np.zeros(6)]
        theta = rng.uniform(0.0, np.pi, 5)
        vals = _ratio(num, den, theta)
        t, v = _newton_polish(num, den, theta, vals)
        assert np.all(v <= vals)
        np.testing.assert_allclose(v, _ratio(num, den, t), rtol=POLISH_RTOL)


def test_seeds_are_the_start_s_peaks_inside_the_input_range():
    fs = 3000.0
    plant = loop_plant(fs, 0.83)
    f = np.concatenate([[0.0], np.geomspace(0.01, fs / 2, 400)])
    psd = 1.0 / (1.0 + (f / 20.0) ** 2) ** (11 / 6)
    # The same preparation as the public call below (datadriven's defaults, order 5).
    setup = dd._prepare(plant, f, psd[None, :], order=5, noise_psd=1e-6)
    res = dd.datadriven(plant, f, psd, order=5, noise_psd=1e-6, n_jobs=1, progress=False)
    item = setup.items[0]
    ctx = setup.ctx.with_structure(item.fixed_factor, 5)
    dense = ctx.grid_data(ctx.dense_freqs, ctx.dense_response, ctx.modulus_margin)
    # v_ref = 1: the objective's normalisation does not move the seeds (|S| peaks).
    cert = _ModeCertifier(
        ctx, item.psd, item.noise, v_ref=1.0, b0=item.b0, a0=item.a0, dense=dense,
        mu_d=ctx.design_margin,
    )  # fmt: skip
    v = ctx.to_v(res.controller.b[0], res.controller.a[0])
    assert v is not None
    seeds = cert.seeds(v)
    full = polynomial_certificate(*ctx.plant_coefficients, *ctx.from_v(v), fs)
    # Oracle: every local minimum of |1 + G K| below 1 inside (f[0], f[-1]) off the H2 grid,
    # worst first, at most 4; they become H2 points.
    m = full.minima
    want = (m < 1.0) & (full.minima_hz > f[0]) & (full.minima_hz < f[-1])
    want &= ~np.isin(full.minima_hz, ctx.h2_freqs)
    expected = full.minima_hz[want][np.argsort(m[want])][:4]
    assert seeds.size >= 1  # a loop with a margin has |S| > 1 somewhere (waterbed)
    np.testing.assert_array_equal(seeds, expected)
    assert np.all(np.isin(seeds, cert.h2_extra))


def test_warm_start_with_integral_action_becomes_leaky_in_the_free_structure():
    # Oracle: the definition. A design with a pole at z = 1 is outside the radius of a mode
    # whose poles are all free; its integrator becomes 1 - (1 - leak) z^-1, the rest kept.
    fs = 3000.0
    plant = loop_plant(fs, 0.83)
    f = np.linspace(0.0, fs / 2, 200)
    # Every pole free (fixed_denominator [1]) inside the default radius.
    psd = (1.0 / (1.0 + (f / 50.0) ** 2))[None, :]
    setup = dd._prepare(plant, f, psd, noise_psd=1e-3, fixed_denominator=[1.0])
    ctx = setup.ctx
    rest = np.convolve([1.0, -0.5], [1.0, 0.2])  # the other poles: 0.5 and -0.2
    a = np.convolve([1.0, -1.0], rest)
    b = np.array([0.3, -0.1, 0.05])
    assert ctx.to_v(b, a) is not None  # in the set, but its pole at 1 is outside
    leak = 1e-3
    v = ctx.warm_v(b, a, leak)
    b2, a2 = ctx.from_v(v)
    np.testing.assert_allclose(b2[: b.size], b, rtol=1e-12)
    expected = np.convolve([1.0, -(1.0 - leak)], rest)
    np.testing.assert_allclose(a2[: expected.size], expected, rtol=1e-12, atol=1e-15)
    assert np.all(np.abs(a2[expected.size :]) < 1e-15)
    # A design already inside the radius is kept as it is.
    inside = np.convolve([1.0, -0.9], rest)
    np.testing.assert_array_equal(ctx.warm_v(b, inside, leak), ctx.to_v(b, inside))
