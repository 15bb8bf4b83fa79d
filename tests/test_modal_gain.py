"""Tests of aocontrol.synthesis.optimal_modal_gain (Gendron & Lena 1994 modal gains)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import integrator_stability_limit

from aocontrol.analysis import is_stable, margins, residual_variance, white_noise_psd
from aocontrol.controllers import Integrator
from aocontrol.disturbance import synthetic_turbulence_psd
from aocontrol.plant import frequency_response, loop_plant, measured_plant
from aocontrol.synthesis import integrator_gain_limit, optimal_modal_gain

FS = 1000.0


def _random_walk_psd(f, fs, innovation_var=1.0):
    """One-sided PSD of d[k] = d[k-1] + w[k]: (2 s_w^2/fs) / |1 - z^-1|^2."""
    zi = np.exp(-2j * np.pi * f / fs)
    return 2 * innovation_var / fs / np.abs(1 - zi) ** 2


def test_white_noise_only_drives_gain_to_zero():
    # Oracle: G = z^-1, noise only: J(g) = s2 g / (2 - g), increasing in g, so the optimum is
    # the lowest admissible gain (1e-6 of the limit 2). (At such a gain T is a 3e-4 Hz wide
    # peak at 0 that a 0.25 Hz grid cannot resolve: J itself is checked at a larger gain.)
    tol = 3e-6  # the limit itself is backed off by 1e-6
    f = np.linspace(0.0, FS / 2, 2001)
    G = loop_plant(FS, 0.0)
    noise = white_noise_psd(1.0, FS)
    K = optimal_modal_gain(G, f, np.zeros_like(f), noise)
    assert abs(K.gain[0] / 2e-6 - 1) < tol
    v = residual_variance(G, Integrator(0.5, fs=FS), f, np.zeros_like(f), noise)
    assert abs(v / (0.5 / 1.5) - 1) < tol


def test_white_noise_only_with_leak_gives_zero_gain():
    # Oracle: with a leak, g = 0 is stable and J(0) = 0 is the minimum of J(g) >= 0.
    f = np.linspace(0.0, FS / 2, 2001)
    K = optimal_modal_gain(loop_plant(FS, 1.0), f, np.zeros_like(f), 1e-3, leak=0.05)
    assert K.gain[0] == 0.0
    assert K.leak == 0.05


@pytest.mark.parametrize("r", [0.01, 1.0, 30.0])
def test_random_walk_in_white_noise_matches_kalman_gain(r):
    # Oracle: G = z^-1, d random walk (innovation var r), white noise (var 1):
    # J(g) = (r/g + g)/(2 - g), minimised at g* = (-r + sqrt(r^2 + 4r))/2, the steady-state
    # Kalman gain. Tolerance: the grid starts at 1e-4 Hz (the PSD is infinite at 0).
    tol = 1e-3
    f = np.linspace(1e-4, FS / 2, 20001)
    G = loop_plant(FS, 0.0)
    K = optimal_modal_gain(G, f, _random_walk_psd(f, FS, r), white_noise_psd(1.0, FS))
    g_star = (-r + np.sqrt(r * r + 4 * r)) / 2
    assert abs(K.gain[0] / g_star - 1) < tol
    j = float(residual_variance(G, K, f, _random_walk_psd(f, FS, r), white_noise_psd(1.0, FS))[0])
    assert abs(j / ((r / g_star + g_star) / (2 - g_star)) - 1) < tol


def test_matches_brute_force_over_dense_gain_grid():
    # Oracle: residual_variance evaluated on 800 gains up to the stability limit; the
    # optimiser is at least as good as the best grid gain and within one grid step of it.
    tol = 1e-9
    G = loop_plant(FS, 0.83)
    f = np.linspace(0.0, FS / 2, 3001)
    psd = synthetic_turbulence_psd(f, 30, wind_speed=15.0, fs=FS)[[0, 5, 29]]
    noise = white_noise_psd(np.array([1.0, 20.0, 5.0]), FS)
    K = optimal_modal_gain(G, f, psd, noise)
    limit = integrator_gain_limit(G)
    grid = np.linspace(1e-4, limit, 800)
    for m in range(3):
        brute = residual_variance(
            G, Integrator(grid, fs=FS), f, psd[m], noise[m], check_stability=False
        )
        j_opt = residual_variance(G, Integrator(K.gain[m], fs=FS), f, psd[m], noise[m])[0]
        assert j_opt <= brute.min() * (1 + tol)
        assert abs(K.gain[m] - grid[np.argmin(brute)]) <= grid[1] - grid[0]


@pytest.mark.parametrize("d", [1, 2, 3])
def test_gain_limit_matches_integer_delay_formula(d):
    # Oracle: g/(1 - z^-1) with G = z^-d is stable iff g < 2 sin(pi / (2 (2d - 1))).
    tol = 2e-6  # the limit is backed off by 1e-6
    limit = integrator_gain_limit(loop_plant(FS, d - 1.0))
    assert abs(limit / integrator_stability_limit(d) - 1) < tol


def test_gains_stay_below_stability_limit_for_high_snr():
    # Invariant: a huge disturbance and no noise push every gain to the limit, never beyond.
    G = loop_plant(FS, 0.83)
    f = np.linspace(1e-3, FS / 2, 2001)
    psd = 1e6 * _random_walk_psd(f, FS)
    K = optimal_modal_gain(G, f, np.vstack([psd, psd * f / FS]))
    assert np.all(K.gain <= integrator_gain_limit(G))
    assert all(is_stable(G, K, mode=m) for m in range(K.n_modes))


def test_modulus_margin_is_honoured_and_active():
    # Oracle: for G = z^-1, min |1 + L| = 1 - g/2 (reached at Nyquist), so mu = 0.6 caps the
    # gain at 2 (1 - mu) = 0.8; a high-SNR mode sits at the cap, a faint one below it.
    tol = 1e-6
    G = loop_plant(FS, 0.0)
    f = np.linspace(1e-3, FS / 2, 4001)
    psd = np.vstack([1e3 * _random_walk_psd(f, FS), 1e-3 * _random_walk_psd(f, FS)])
    K = optimal_modal_gain(G, f, psd, white_noise_psd(1.0, FS), modulus_margin=0.6)
    assert abs(K.gain[0] / 0.8 - 1) < tol
    assert K.gain[1] < 0.5
    for mode in range(2):
        assert margins(G, K, mode=mode).modulus_margin >= 0.6 * (1 - 1e-9)


def test_modulus_margin_fractional_delay():
    # Invariant (checked by the independent margins()): mu honoured for a 1.83-frame plant.
    G = loop_plant(3000.0, 0.83)
    f = np.linspace(0.0, 1500.0, 3001)
    psd = synthetic_turbulence_psd(f, 4, wind_speed=30.0, fs=3000.0)
    K = optimal_modal_gain(G, f, psd, 1e-9, modulus_margin=0.5)
    mm = [margins(G, K, mode=m).modulus_margin for m in range(4)]
    assert min(mm) >= 0.5 * (1 - 1e-9)
    assert abs(max(K.gain) / integrator_gain_limit(G, modulus_margin=0.5) - 1) < 1e-6


def test_vectorised_equals_one_mode_at_a_time():
    # Invariant: the bank solve equals separate single-mode solves.
    G = loop_plant(FS, 0.5)
    f = np.linspace(0.0, FS / 2, 2001)
    psd = synthetic_turbulence_psd(f, 6, fs=FS)
    noise = white_noise_psd(np.linspace(1.0, 50.0, 6), FS)
    K = optimal_modal_gain(G, f, psd, noise)
    for m in range(6):
        k1 = optimal_modal_gain(G, f, psd[m], noise[m])
        assert abs(k1.gain[0] / K.gain[m] - 1) < 1e-9


def test_measured_plant_gives_the_same_gains():
    # Invariant: an FRD sampled from the TF plant (dense grid) gives the same optimum.
    tol = 1e-3
    G = loop_plant(FS, 0.83)
    fg = np.linspace(0.0, FS / 2, 4097)
    Gm = measured_plant(fg, frequency_response(G, fg), FS)
    f = np.linspace(0.0, FS / 2, 2001)
    psd = synthetic_turbulence_psd(f, 3, fs=FS)
    noise = white_noise_psd(10.0, FS)
    a = optimal_modal_gain(G, f, psd, noise)
    b = optimal_modal_gain(Gm, f, psd, noise)
    assert np.max(np.abs(b.gain / a.gain - 1)) < tol


@pytest.mark.parametrize(
    ("kwargs", "err", "match"),
    [
        ({"psd": np.full(11, np.nan)}, ValueError, "psd must contain only finite"),
        ({"psd": -np.ones(11)}, ValueError, "psd must be >= 0"),
        ({"psd": np.ones(10)}, ValueError, "one per frequency"),
        ({"freqs": np.linspace(0.0, 600.0, 11)}, ValueError, "Nyquist"),
        ({"freqs": np.linspace(500.0, 0.0, 11)}, ValueError, "strictly increasing"),
        ({"noise_psd": -1.0}, ValueError, "noise_psd must be >= 0"),
        ({"noise_psd": np.ones(7)}, ValueError, "noise_psd"),
        ({"modulus_margin": 1.5}, ValueError, r"modulus_margin must be in \(0.0, 1.0\)"),
        ({"leak": 1.0}, ValueError, "leak"),
        ({"plant": "z^-1"}, TypeError, "plant"),
    ],
)
def test_bad_input(kwargs, err, match):
    args = {
        "plant": loop_plant(FS, 0.0),
        "freqs": np.linspace(0.0, 500.0, 11),
        "psd": np.ones(11),
        **kwargs,
    }
    with pytest.raises(err, match=match):
        optimal_modal_gain(args.pop("plant"), args.pop("freqs"), args.pop("psd"), **args)
