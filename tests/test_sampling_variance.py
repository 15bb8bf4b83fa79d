"""The sampling variance of a record's mean square (issue 15: how far apart a predicted and a
measured residual may be by chance).

Oracles: for a Gaussian AR(1) record ``x[k] = a x[k-1] + w[k]`` the exact variance of the
mean of ``x^2`` over ``n`` samples is ``(2 / n^2) sum_{j,k} R(j - k)^2`` with ``R(tau) =
s_x^2 a^|tau|`` (Isserlis), and a Monte Carlo over independent records measures it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from aocontrol.analysis import mean_square_sampling_variance
from aocontrol.study.compare import Cell

FS, A, SIGMA_W = 1000.0, 0.9, 1.5


def _ar1_psd(f: np.ndarray) -> np.ndarray:
    z1 = np.exp(-2j * np.pi * f / FS)
    return SIGMA_W**2 * 2.0 / FS / np.abs(1 - A * z1) ** 2


def _exact(n: int) -> float:
    """(2 / n^2) sum_{j,k} R(j-k)^2, R(tau) = s_x^2 a^|tau|, summed in closed form over lags."""
    sx2 = SIGMA_W**2 / (1 - A**2)
    lags = np.arange(1, n)
    return 2 * sx2**2 / n**2 * (n + 2 * np.sum((n - lags) * A ** (2 * lags)))


def test_matches_exact_ar1_variance():
    f = np.linspace(0, FS / 2, 200_001)
    for n in (2000, 20_000):
        v = mean_square_sampling_variance(f, _ar1_psd(f), n / FS)
        # The formula is the n >> correlation time (~10 samples) limit: O(10 / n) apart.
        assert v == pytest.approx(_exact(n), rel=20 / n)


def test_matches_monte_carlo_and_modes_add():
    rng = np.random.default_rng(15)
    n_rec, n = 4000, 2000
    w = SIGMA_W * rng.standard_normal((n_rec, n + 200))
    x = signal.lfilter([1.0], [1.0, -A], w, axis=1)[:, 200:]
    ms = (x**2).mean(axis=1)
    f = np.linspace(0, FS / 2, 100_001)
    v = mean_square_sampling_variance(f, _ar1_psd(f), n / FS)
    # The sample variance of 4000 near-Gaussian draws: relative sd sqrt(2 / 4000) = 2.2 %.
    assert ms.var(ddof=1) == pytest.approx(v, rel=0.1)
    # Two modes (rows): per-mode variances, each the row's.
    two = mean_square_sampling_variance(f, np.stack([_ar1_psd(f), 4 * _ar1_psd(f)]), n / FS)
    assert two.shape == (2,) and two[1] == pytest.approx(16 * two[0], rel=1e-12)
    assert two[0] == pytest.approx(v, rel=1e-12)


def test_bad_input_named():
    f = np.linspace(0, 500, 11)
    with pytest.raises(ValueError, match="seconds"):
        mean_square_sampling_variance(f, np.ones(11), 0.0)
    with pytest.raises(ValueError, match="psd must be >= 0"):
        mean_square_sampling_variance(f, -np.ones(11), 1.0)
    with pytest.raises(ValueError, match=r"psd must have shape \(11,\)"):
        mean_square_sampling_variance(f, np.ones(10), 1.0)
    with pytest.raises(ValueError, match="freqs"):
        mean_square_sampling_variance(f[::-1], np.ones(11), 1.0)


def _cell(pred, meas, se_pred=math.nan, se_meas=math.nan):
    return Cell(
        "reference", "standalone", 0.5, 1e-5, meas, pred, np.zeros(2), np.zeros(2),
        predicted_rms_se_nm=se_pred, residual_rms_se_nm=se_meas,
    )  # fmt: skip


def test_cell_ratio_interval():
    # 12 nm predicted +- 0.36 (3 %), 10 nm measured +- 0.4 (4 %): s = 5 %.
    r, lo, hi = _cell(12.0, 10.0, 0.36, 0.4).ratio_interval()
    assert r == pytest.approx(1.2) and lo == pytest.approx(1.2 * 0.9) and hi == pytest.approx(1.32)
    r, lo, hi = _cell(12.0, 10.0, 0.36, 0.4).ratio_interval(z=1)
    assert (lo, hi) == pytest.approx((1.2 * 0.95, 1.2 * 1.05))
    r, lo, hi = _cell(12.0, 10.0).ratio_interval()
    assert r == pytest.approx(1.2) and math.isnan(lo) and math.isnan(hi)
    with pytest.raises(ValueError, match="z must be"):
        _cell(12.0, 10.0).ratio_interval(z=0)
