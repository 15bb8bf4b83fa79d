"""The telemetry estimator's steps below the main Welch grid and its pre-whitening
(:func:`aocontrol.synthesis.disturbance_from_telemetry`, steps 4, 6 and 7).

Step 4's Welch PSD of the differenced pseudo-open loop (its mean kept) and the expected
estimate of differenced white noise that whitens it; step 6's finer Welch levels below the
main grid's second bin; step 7's power law spread below the finest bin, carrying the
variance the Welch bins miss. Split from :mod:`aocontrol.synthesis._telemetry` (issue 34,
its size): the estimator's order and its checks stay there.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import signal

from aocontrol.analysis import welch_psd
from aocontrol.synthesis._welch_stats import _DETECTION_SIGMAS, _welch_dof

# Longest segment of the finer levels below the second Welch bin (step 6). Its first bin,
# fs / 4096 (0.73 Hz at 3 kHz, 0.24 Hz at 1 kHz), resolves the bright dCAO residual (1.4-s
# records); finer points of one-segment scatter made the PSD too jagged for the FFT grids
# that resample it (wiener_bound warned at 8192 frames); the rest is spread below (step 7).
_MAX_FINE_NPERSEG = 4096
# Below the finest bin (step 7): points per octave, steepest power law accepted (f^-4, a
# double pole), bisection steps of the slope and of the corner (2^-40 of their ranges).
_SPREAD_PER_OCTAVE, _MAX_SLOPE, _BISECTIONS = 4, 4.0, 40


def _welch_differenced(diff: np.ndarray, fs: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Welch PSD ``(n_modes, n_freqs)`` of the differenced pseudo-open loop.

    As :func:`aocontrol.analysis.welch_psd` but without removing the record mean: the
    differenced record has zero mean by construction, and its sample mean ``(pol[-1] -
    pol[0]) / (n - 1)`` is a ramp of ``pol`` that the Hann window puts into bin 1 (``L c /
    4`` for a segment of ``L`` frames). Removing it would bias the first bin of a one-segment
    estimate high, by several times on a long record of a spectrum flat at low frequency
    (``docs/benchmarks.md``); :func:`_whitening` is the expectation without mean removal.
    """
    nper = min(nperseg, diff.shape[0])
    f, pxx = signal.welch(
        diff, fs=fs, window="hann", nperseg=nper, noverlap=nper // 2, detrend=False, axis=0
    )
    pxx = np.moveaxis(pxx, 0, -1).copy()
    pxx[..., 0] *= 2
    if nper % 2 == 0:
        pxx[..., -1] *= 2
    return f, pxx


def _whitening(f: np.ndarray, fs: float, nperseg: int) -> np.ndarray:
    """Expected Welch estimate of differenced unit white noise, ``2 (1 - rho cos w)``.

    ``rho`` is the Hann window's lag-1 autocorrelation, not 1 as in ``|1 - z^-1|^2 = 2 (1 -
    cos w)``: the window leaks the f^2 rise of the differenced spectrum into the first bins
    (+33 % at bin 1, +8 % at bin 2 for Hann), which the division would amplify. Exact for a
    disturbance locally flat over the window's main lobe.
    """
    win = signal.get_window("hann", nperseg)
    rho = float(np.dot(win[1:], win[:-1]) / np.dot(win, win))
    return 2.0 * (1.0 - rho * np.cos(2 * np.pi * f / fs))


def _finer_segments(nperseg: int, n_frames: int) -> list[int]:
    """Segment lengths of the finer levels: ``2 nperseg, 4 nperseg, ...`` within the record
    and at most ``_MAX_FINE_NPERSEG``, then the whole record if it is at least 1.5 times the
    last and within that limit (coarse to fine)."""
    out, seg = [], nperseg
    while 2 * seg <= min(n_frames, _MAX_FINE_NPERSEG):
        seg *= 2
        out.append(seg)
    if 1.5 * seg <= n_frames <= _MAX_FINE_NPERSEG:
        out.append(n_frames)
    return out


def _below_second_bin(
    diff: np.ndarray,
    pol: np.ndarray,
    fs: float,
    nperseg: int,
    second: np.ndarray,
    noise: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pre-whitened excess below the main grid's second bin, from longer segments (step 6).

    The first bin of a pre-whitened Welch estimate is biased by the local slope of the
    spectrum (:func:`_whitening` adds the window's second moment, 33 % of ``|1 - z^-1|^2`` at
    bin 1, exact only for a spectrum flat over the main lobe: a ``f^-2`` spectrum comes out
    25 % low there, 8 % at bin 2). So every level, segments ``2^j nperseg`` frames long (up
    to ``_MAX_FINE_NPERSEG`` or the whole record, :func:`_finer_segments`), gives its bins 2
    and up that lie below the lowest frequency already covered (``2 fs / nperseg`` for the
    main grid): bins 2 and 3 of each level, the levels tiling ``(fs / L, 2 fs / nperseg)``
    (``L`` the finest segment) without double counting (a dyadic, multi-resolution grid).
    The finest level also gives its bin 1, ``fs / L``. A bin whose excess is below
    ``_DETECTION_SIGMAS`` standard deviations of the noise's scatter at that level's degrees
    of freedom (the disturbance not detected) takes the value of the next higher bin instead
    (the clip of a chi-square scatter would bias it up, as in :func:`_debias`).

    Parameters
    ----------
    diff, pol : ndarray, shape (n_frames - 1, n_modes) and (n_frames, n_modes)
        Differenced and plain pseudo-open loop [units].
    fs : float
        Loop rate [Hz].
    nperseg : int
        Segment of the main Welch grid [frames].
    second : ndarray, shape (n_modes,)
        Excess at the main grid's second bin ``2 fs / nperseg`` (after :func:`_debias`)
        [units^2/Hz].
    noise : ndarray, shape (n_modes,)
        White noise level [units^2/Hz].

    Returns
    -------
    freqs : ndarray, shape (n_low,)
        Ascending [Hz], all below ``2 fs / nperseg``; empty if the record holds no segment
        twice as long as ``nperseg`` (then the main grid's first bin is kept).
    excess : ndarray, shape (n_modes, n_low)
        Disturbance excess at ``freqs`` (not clipped) [units^2/Hz].
    pol_psd : ndarray, shape (n_modes, n_low)
        Plain Welch PSD of ``pol`` at ``freqs`` with the same segments [units^2/Hz].
    """
    freqs, cols, plain = [], [], []
    above, covered = second, 2.0 * fs / nperseg
    segments = _finer_segments(nperseg, diff.shape[0])
    for level, seg in enumerate(segments):
        f, pxx = _welch_differenced(diff, fs, seg)
        first = 1 if level == len(segments) - 1 else 2
        bins = [k for k in range(first, f.size) if f[k] < covered * (1 - 1e-9)][::-1]
        if not bins:
            continue
        value = pxx[:, bins] / _whitening(f[bins], fs, seg) - noise[:, None]
        sigma = math.sqrt(2.0 / _welch_dof(diff.shape[0], seg)) * noise
        p_pol = welch_psd(pol, fs, seg)[1]
        for i, k in enumerate(bins):  # high to low frequency: a few bins per level
            above = np.where(value[:, i] > _DETECTION_SIGMAS * sigma, value[:, i], above)
            freqs.append(f[k])
            cols.append(above)
            plain.append(p_pol[:, k])
        covered = f[bins[-1]]
    n_modes = diff.shape[1]
    if not freqs:
        return np.empty(0), np.empty((n_modes, 0)), np.empty((n_modes, 0))
    return np.array(freqs[::-1]), np.column_stack(cols[::-1]), np.column_stack(plain[::-1])


def _below_finest_bin(
    freqs: np.ndarray, psd: np.ndarray, target: np.ndarray, f_record: float
) -> tuple[np.ndarray, np.ndarray]:
    """The disturbance PSD from 0 Hz to the finest bin ``f1 = freqs[1]`` (step 7).

    The variance that the bins from ``f1`` up do not hold, ``V = target - int_f1 psd``,
    lies below ``f1``. It is spread with the spectrum's own low-frequency slope: ``P(f) =
    P(f1) (max(f, f_c) / f1)^-alpha``, a power law continuing the estimate below ``f1``,
    flat below a corner ``f_c`` (the shape of a von Karman spectrum below its outer-scale
    corner). ``alpha`` is the least-squares log-log slope of the estimate over ``[f1, 4 f1]``,
    clipped to ``[0, _MAX_SLOPE]``; ``f_c`` is chosen so that the trapezoid over the new points
    integrates to ``V`` exactly (variance conserved). The corner is not put below the
    record's resolution ``f_record = fs / (2 n_frames)`` (a record's sample variance holds
    a frequency ``f`` with the weight ``1 - sinc^2(f n_frames / fs)``, 0.59 at ``f_record``):
    where the slope cannot hold ``V`` above it, ``alpha`` is raised instead (up to
    ``_MAX_SLOPE``; beyond it the points below ``f1`` are scaled up). When ``V <= P(f1)
    f1`` the PSD stays flat at ``P(f1)`` below ``f1`` (the trapezoid between the dyadic
    points already overestimates a steep spectrum's integral; nothing is removed).

    Parameters
    ----------
    freqs : ndarray, shape (n_freqs,)
        The estimate's grid [Hz], ``freqs[0] = 0``.
    psd : ndarray, shape (n_modes, n_freqs)
        The estimate (clipped > 0) [units^2/Hz]; its 0-Hz column is ignored.
    target : ndarray, shape (n_modes,)
        Variance the PSD must integrate to: the pseudo-open loop's minus the noise's
        [units^2].
    f_record : float
        Lowest corner [Hz].

    Returns
    -------
    freqs, psd : ndarray, shapes (n_low,) and (n_modes, n_low)
        0, then ``_SPREAD_PER_OCTAVE`` log-spaced points per octave from ``min(f_record,
        f1 / 2)`` to below ``f1`` [Hz]; the PSD there [units^2/Hz].
    """
    f1 = freqs[1]
    c_min = min(f_record / f1, 0.5)
    n_pts = max(_SPREAD_PER_OCTAVE, math.ceil(_SPREAD_PER_OCTAVE * math.log2(1 / c_min)))
    x = np.concatenate([[0.0], np.geomspace(c_min, 1.0, n_pts + 1)])  # f / f1, ends at 1
    p1 = psd[:, 1]
    fit = (freqs > 0) & (freqs <= 4 * f1 * (1 + 1e-12))
    if fit.sum() >= 2:
        logf = np.log(freqs[fit] / f1)
        logp = np.log(psd[:, fit])
        slope = ((logp - logp.mean(axis=1, keepdims=True)) @ (logf - logf.mean())) / np.sum(
            (logf - logf.mean()) ** 2
        )
        alpha = np.clip(-slope, 0.0, _MAX_SLOPE)
    else:
        alpha = np.zeros_like(p1)
    above = np.trapezoid(psd[:, 1:], freqs[1:], axis=1)
    need = (target - above) / (p1 * f1)  # V in units of P(f1) f1

    def integral(log_c: np.ndarray, a: np.ndarray) -> np.ndarray:
        shape = np.maximum(x[None, :], np.exp(log_c)[:, None]) ** -a[:, None]
        return np.trapezoid(shape, x, axis=1)

    spread = need > 1.0
    lo_c = np.full(p1.shape, math.log(c_min))
    # Slope too shallow to hold V above the lowest corner: raise it (bisection, vectorised).
    short = spread & (integral(lo_c, alpha) < need)
    a_lo, a_hi = alpha.copy(), np.full(p1.shape, _MAX_SLOPE)
    for _ in range(_BISECTIONS):
        mid = 0.5 * (a_lo + a_hi)
        big = integral(lo_c, mid) >= need
        a_hi, a_lo = np.where(big, mid, a_hi), np.where(big, a_lo, mid)
    alpha = np.where(short, a_hi, alpha)
    # The corner holding V exactly (the integral falls as the corner rises).
    c_lo, c_hi = lo_c.copy(), np.zeros(p1.shape)
    for _ in range(_BISECTIONS):
        mid = 0.5 * (c_lo + c_hi)
        big = integral(mid, alpha) >= need
        c_lo, c_hi = np.where(big, mid, c_lo), np.where(big, c_hi, mid)
    corner = np.where(short, lo_c, c_lo)
    shape = np.maximum(x[None, :], np.exp(corner)[:, None]) ** -alpha[:, None]
    # Exact trapezoid: scale the points below f1 (a rounding factor, or the excess beyond
    # the steepest slope).
    below = np.trapezoid(shape, x, axis=1) - 0.5 * (x[-1] - x[-2])
    scale = np.maximum(need - 0.5 * (x[-1] - x[-2]), 0.0) / np.maximum(below, 1e-300)
    shape[:, :-1] *= scale[:, None]
    shape = np.where(spread[:, None], shape, 1.0)
    return x[:-1] * f1, p1[:, None] * shape[:, :-1]
