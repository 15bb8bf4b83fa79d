"""Tests of the photon budget and detector noise (aocontrol.sim.noise)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aocontrol.sim.noise import (
    BANDS,
    add_detector_noise,
    band_zero_point,
    photons_per_frame,
    snr,
)


def test_photons_for_reference_magnitude_match_hand_calculation():
    # Oracle, by hand from Cohen et al. (2003) table 2 for 2MASS J: F_lambda = 3.129e-13
    # W cm^-2 um^-1 at 1.235 um over 0.162 um. Photon energy h c / lambda = 1.6085e-19 J, so
    # J = 0 gives 3.129e-13 * 1e4 * 0.162 / 1.6085e-19 = 3.151e9 photons s^-1 m^-2.
    # J = 8.5 (red 1 fast), VLT 8 m with a 14 % obstruction (49.28 m^2), 3 kHz, 25 % throughput.
    hand_tol = 1e-3  # rounding of the hand constants
    zero = 3.129e-13 * 1e4 * 0.162 / (6.62607015e-34 * 299792458.0 / 1.235e-6)
    assert abs(zero / 3.151e9 - 1) < hand_tol
    area = math.pi * 16.0 * (1 - 0.14**2)
    expected = zero * 10 ** (-0.4 * 8.5) * area * 0.25 / 3000.0
    n = photons_per_frame(8.5, "J", fs=3000.0, throughput=0.25)
    assert abs(n / expected - 1) < hand_tol
    # the same with a frame time and an explicit area
    n2 = photons_per_frame(8.5, "J", frame_time=1 / 3000.0, area=area, throughput=0.25)
    assert abs(n2 / expected - 1) < 1e-12


def test_v_band_zero_point_is_the_textbook_value():
    # Oracle: a V = 0 star gives ~1000 photons s^-1 cm^-2 A^-1 at 545 nm (Bessell 1998:
    # 3.631e-9 erg s^-1 cm^-2 A^-1 / 3.645e-12 erg) = 9.96e10 photons s^-1 m^-2 um^-1.
    v = band_zero_point("V")
    assert abs(v.zero_point / (v.bandwidth * 1e6) / 9.96e10 - 1) < 2e-3


def test_magnitude_scaling_and_bandwidth():
    # Oracle: 5 magnitudes = factor 100 exactly; the flux scales with the WFS bandwidth.
    a = photons_per_frame(5.0, "G", fs=1000.0)
    b = photons_per_frame(10.0, "G", fs=1000.0)
    assert abs(a / b / 100.0 - 1) < 1e-12
    half = photons_per_frame(5.0, "J", fs=1000.0, bandwidth=BANDS["J"].bandwidth / 2)
    assert abs(half / photons_per_frame(5.0, "J", fs=1000.0) - 0.5) < 1e-12
    # negative magnitudes (bright stars) are valid
    assert photons_per_frame(-1.0, "J", fs=1000.0) > photons_per_frame(0.0, "J", fs=1000.0)


def test_gaia_g_zero_point():
    # Oracle: Gaia DR3 ZP_G = 25.6874 (Vega, e-/s) over Gaia's 0.7278 m^2 pupil.
    assert abs(BANDS["G"].zero_point / (10 ** (0.4 * 25.6874) / 0.7278) - 1) < 1e-12
    assert abs(BANDS["G"].zero_point / 2.589e10 - 1) < 1e-3


def test_detector_noise_statistics():
    # Oracle: Poisson(I) + N(0, s^2) has mean I and variance I + s^2. With 200000 samples the
    # standard error of the variance is ~0.3 %; STAT_TOL = 2 %.
    stat_tol = 0.02
    rng = np.random.default_rng(1)
    x = add_detector_noise(np.full(200_000, 3.0), 0.8, rng)
    assert abs(x.mean() / 3.0 - 1) < stat_tol
    assert abs(x.var() / (3.0 + 0.64) - 1) < stat_tol


def test_detector_noise_same_seed_same_numbers():
    img = np.linspace(0, 10, 50).reshape(5, 10)
    a = add_detector_noise(img, 0.3, np.random.default_rng(3))
    b = add_detector_noise(img, 0.3, np.random.default_rng(3))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, add_detector_noise(img, 0.3, np.random.default_rng(4)))


def test_snr_paper_definition():
    # Oracle: SNR = N / sqrt(N + 4 Nr^2) (paper, section "Noise").
    assert snr(100.0, 0.0) == 10.0
    assert abs(snr(100.0, 5.0) - 100.0 / math.sqrt(200.0)) < 1e-12
    assert abs(snr(100.0, 5.0, n_pixels=1) - 100.0 / math.sqrt(125.0)) < 1e-12
    assert snr(0.0, 0.0) == 0.0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(fs=0.0), r"fs must be a finite number > 0, got 0.0"),
        (dict(fs=-10.0), r"fs must be a finite number > 0, got -10.0"),
        (dict(frame_time=-1e-3), r"frame_time must be a finite number > 0, got -0.001"),
        (dict(fs=1e3, frame_time=1e-3), r"exactly one of fs and frame_time"),
        (dict(), r"exactly one of fs and frame_time"),
        (dict(fs=1e3, area=-1.0), r"area must be a finite number > 0, got -1.0"),
        (dict(fs=1e3, diameter=-8.0), r"diameter must be a finite number > 0, got -8.0"),
        (dict(fs=1e3, throughput=-0.1), r"throughput must be in \(0.0, 1.0\], got -0.1"),
        (dict(fs=1e3, throughput=1.5), r"throughput must be in \(0.0, 1.0\], got 1.5"),
        (dict(fs=1e3, bandwidth=-1e-7), r"bandwidth must be a finite number > 0"),
    ],
)
def test_photons_per_frame_bad_input(kwargs, message):
    with pytest.raises(ValueError, match=message):
        photons_per_frame(10.0, "J", **kwargs)


def test_bad_band_magnitude_and_noise_inputs():
    with pytest.raises(ValueError, match=r"band must be one of .* got 'Z'"):
        photons_per_frame(10.0, "Z", fs=1e3)
    with pytest.raises(ValueError, match=r"magnitude must be finite, got nan"):
        photons_per_frame(float("nan"), "J", fs=1e3)
    with pytest.raises(ValueError, match=r"read_noise must be a finite number >= 0, got -0.1"):
        add_detector_noise(np.ones(3), -0.1, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"intensity must be >= 0"):
        add_detector_noise(-np.ones(3), 0.1, np.random.default_rng(0))
    with pytest.raises(TypeError, match=r"rng must be a numpy.random.Generator"):
        add_detector_noise(np.ones(3), 0.1, 42)
    with pytest.raises(ValueError, match=r"n_photons must be a finite number >= 0"):
        snr(-1.0, 0.1)
