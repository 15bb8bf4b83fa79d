"""Welch statistics of the telemetry estimator (:mod:`aocontrol.synthesis._telemetry`).

The equivalent degrees of freedom of a Welch estimate and what follows from them: the
median-to-mean correction of the noise level, the averaging of the noise-dominated bins
before the clip, the disturbance's lowest value, and the scatter-aware flatness check of the
noise band.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import signal, stats

# Noise band declared not flat (warning) when the median of its lower half exceeds that of
# its upper half by this factor (the chi-square scatter of the medians is a few % with 8 or
# more segments), or by 4 standard deviations of the ratio's scatter where that is wider
# (few segments: one segment's bins scatter as chi-square(2), and white noise alone passed
# 1.5 in 10 of 400 modes of a 1,500-frame record; :func:`_flatness_threshold`).
_FLATNESS_RATIO = 1.5
_FLATNESS_SIGMAS = 4.0
# Disturbance PSD after noise removal is clipped to this fraction of the noise level (of the
# POL PSD maximum if there is no noise), so that it stays strictly positive.
_PSD_FLOOR_FRACTION = 1e-6

# Noise-dominated bins: the POL PSD minus the noise is below this many standard deviations of
# the Welch scatter of the noise (sqrt(2 / nu) of the level): the disturbance is not detected
# there, and the bin's excess is replaced by the mean excess of such bins within
# _SMOOTH_OCTAVES around it before the clip (see _debias).
_DETECTION_SIGMAS = 3.0
_SMOOTH_OCTAVES = 1.0


def _welch_dof(n_frames: int, nperseg: int) -> float:
    """Equivalent degrees of freedom of a Welch estimate (Hann, 50 % overlap).

    Percival & Walden (1993), eq. (292b): ``nu = 2 K / (1 + 2 sum_m (1 - m/K) c_m^2)`` with
    ``K`` segments and ``c_m`` the normalised overlap of the window with itself shifted by
    ``m`` segment steps (only ``m = 1`` overlaps at 50 %).
    """
    step = nperseg - nperseg // 2
    k = 1 + (n_frames - nperseg) // step
    w = signal.get_window("hann", nperseg)
    c1 = float(np.dot(w[step:], w[:-step]) / np.dot(w, w)) if k > 1 else 0.0
    return 2 * k / (1 + 2 * (1 - 1 / k) * c1 * c1)


def _median_to_mean(dof: float) -> float:
    """Mean / median of a chi-square variable with ``dof`` degrees of freedom."""
    return float(dof / stats.chi2.median(dof))


def _debias(excess: np.ndarray, noise: np.ndarray, dof: float) -> np.ndarray:
    """Excess ``POL PSD - noise`` with the noise-dominated bins averaged (step 4).

    A bin is noise-dominated when its excess is below ``_DETECTION_SIGMAS`` standard
    deviations of the noise's Welch scatter, ``noise * sqrt(2 / dof)``. Its excess is replaced
    by the mean excess of the noise-dominated bins of the same mode within
    ``_SMOOTH_OCTAVES`` centred on it (bin ``k`` of the first positive frequency: bins
    ``k 2^-b/2 .. k 2^b/2``, by cumulative sums, vectorised over modes); the other bins are
    kept. The mean of an unbiased excess stays unbiased; its scatter, and so the bias of the
    clip that follows, shrinks as the square root of the number of bins averaged (``0.71 k``
    for one octave around bin ``k``: 180 bins at fs/4 with 1024-frame segments).

    Parameters
    ----------
    excess : ndarray, shape (n_modes, n_bins)
        Unbiased disturbance estimate on the positive frequencies (may be < 0) [units^2/Hz].
    noise : ndarray, shape (n_modes,)
        White noise level [units^2/Hz].
    dof : float
        Equivalent degrees of freedom of the Welch estimate.

    Returns
    -------
    ndarray, shape (n_modes, n_bins)
    """
    quiet = excess <= _DETECTION_SIGMAS * math.sqrt(2.0 / dof) * noise[:, None]
    sums = _octave_sums(np.where(quiet, excess, 0.0))
    mean = sums / np.maximum(_octave_sums(quiet.astype(float)), 1.0)
    return np.where(quiet, mean, excess)


def _octave_sums(x: np.ndarray) -> np.ndarray:
    """Sum of ``x[:, k']`` over the :data:`_SMOOTH_OCTAVES` centred on each bin ``k`` (bins
    counted from 1: ``k 2^-b/2 .. k 2^b/2``); cumulative sums, vectorised over modes."""
    n_bins = x.shape[1]
    k = np.arange(1, n_bins + 1)
    half = 2.0 ** (_SMOOTH_OCTAVES / 2)
    lo = np.clip(np.floor(k / half).astype(int) - 1, 0, n_bins)
    hi = np.clip(np.ceil(k * half).astype(int), 1, n_bins)
    sums = np.concatenate([np.zeros((x.shape[0], 1)), np.cumsum(x, axis=1)], axis=1)
    return sums[:, hi] - sums[:, lo]


def _floor(noise: np.ndarray, pxx: np.ndarray) -> np.ndarray:
    """Lowest disturbance PSD per mode: a fraction of the noise (of the POL PSD maximum)."""
    floor = _PSD_FLOOR_FRACTION * np.where(noise > 0, noise, pxx.max(axis=1))
    return np.where(floor > 0, floor, np.finfo(float).tiny)


def _flatness_threshold(dof: float, n_bins: int) -> float:
    """Ratio of the noise band's two half medians above which it is not flat (a warning).

    Each half's median is that of ``n_bins`` Welch bins, ``chi2(dof) / dof`` around the
    level; its relative standard deviation is ``1 / (2 f(m) m sqrt(n))`` (the sample
    median's asymptotic scatter, ``f`` the density at the median ``m``), with ``n`` half the
    bins (a Hann window correlates neighbours). The log of the ratio of two independent
    halves scatters ``sqrt(2)`` times that: the threshold is :data:`_FLATNESS_RATIO` or
    :data:`_FLATNESS_SIGMAS` standard deviations of it, whichever is larger.
    """
    m = stats.chi2.median(dof) / dof
    density = dof * stats.chi2.pdf(m * dof, dof)
    rel = 1.0 / (2.0 * density * m * math.sqrt(max(n_bins / 2.0, 1.0)))
    return max(_FLATNESS_RATIO, math.exp(_FLATNESS_SIGMAS * math.sqrt(2.0) * rel))


# The noise band is extended down (:func:`extended_noise_level`) over the bins where no
# disturbance is detected: an octave's mean POL PSD within this many standard deviations of
# the floor (its own and the octave mean's scatter), and never below this fraction of Nyquist.
_EXTEND_SIGMAS = 3.0
_EXTEND_MIN = 0.1


def extended_noise_level(
    pxx: np.ndarray, band: np.ndarray, dof: float, first: int
) -> tuple[np.ndarray, np.ndarray]:
    """White noise level per mode from the noise band extended down while it stays flat.

    The level measured on the band alone scatters with its few bins (several per cent per
    mode on the top 20 % of a short record), and the disturbance estimate turns that
    scatter into a bias: where the level comes out low the excess ``POL - level`` over the
    whole noise-dominated band is kept as disturbance (weighted by ``|S|^2 ~ 1-2`` in a
    prediction), where it comes out high the negative excess is clipped (docs/fidelity.md,
    "The predicted residual and its sampling error"). So, per mode, the band is extended
    down from its lower edge over the contiguous bins whose one-octave mean POL PSD stays
    within :data:`_EXTEND_SIGMAS` standard deviations of the band's level (that mean's
    scatter and the level's own), never below :data:`_EXTEND_MIN` of Nyquist nor past a
    bin where a disturbance is detected; the level is the median over the extended band,
    corrected to the mean. A disturbance below the detection threshold inside the extension
    raises the level by at most its mean there, a few % of the noise.

    Parameters
    ----------
    pxx : ndarray, shape (n_modes, n_freqs)
        Welch PSD of the pseudo-open loop, bin 0 at 0 Hz, the last at Nyquist.
    band : ndarray of bool, shape (n_freqs,)
        The noise band given (bins where the level is first measured).
    dof : float
        Equivalent degrees of freedom of the Welch estimate.
    first : int
        Lowest bin the extension may reach (``_EXTEND_MIN`` of Nyquist, at least 1).

    Returns
    -------
    noise : ndarray, shape (n_modes,)
        The level [units^2/Hz].
    lowest : ndarray of int, shape (n_modes,)
        Lowest bin of each mode's extended band.
    """
    idx = np.flatnonzero(band)
    lo_band = int(idx[0])
    m2m = _median_to_mean(dof)
    level0 = np.median(pxx[:, band], axis=1) * m2m
    rel_bin = math.sqrt(2.0 / dof)
    # The median of n bins scatters ~1.25 / sqrt(n) times a bin (Hann: n / 2 independent).
    rel_level = 1.25 * rel_bin / math.sqrt(max(idx.size / 2.0, 1.0))
    count = _octave_sums(np.ones((1, pxx.shape[1] - 1)))[0]
    mean = _octave_sums(pxx[:, 1:]) / count
    rel_mean = rel_bin / np.sqrt(np.maximum(count / 2.0, 1.0))
    limit = level0[:, None] * (1.0 + _EXTEND_SIGMAS * np.hypot(rel_mean, rel_level))
    flat = mean <= limit  # (n_modes, n_freqs - 1): bin k + 1
    below = np.arange(1, pxx.shape[1]) < lo_band
    detected = below & ~flat
    # Lowest bin of the contiguous flat run that ends at the band's lower edge.
    last = np.where(detected, np.arange(1, pxx.shape[1]), 0).max(axis=1)
    lowest = np.maximum(last + 1, max(first, 1))
    lowest = np.minimum(lowest, lo_band)
    cols = np.arange(pxx.shape[1])
    keep = (cols[None, :] >= lowest[:, None]) & (cols[None, :] <= idx[-1])
    noise = np.nanmedian(np.where(keep, pxx, np.nan), axis=1) * m2m
    return noise, lowest
