"""Frequency grids and quadrature weights of the data-driven synthesis (private)."""

from __future__ import annotations

import numpy as np
from scipy.signal import find_peaks

# Verification grid: at least this many times denser than the design grid, and at least
# _MIN_DENSE points over [0, fs/2].
_DENSE_FACTOR = 10
_MIN_DENSE = 4096
# Relative prominence of a PSD peak (in decades) for its frequency to join the design grid.
_PEAK_PROMINENCE_DECADES = 0.5
_MAX_PEAKS = 12


def _trapezoid_weights(f: np.ndarray) -> np.ndarray:
    """Weights ``t`` with ``sum(t * y) == np.trapezoid(y, f)``."""
    t = np.zeros_like(f)
    df = np.diff(f)
    t[:-1] += df / 2
    t[1:] += df / 2
    return t


def _design_indices(freqs: np.ndarray, psd: np.ndarray, n_grid: int) -> np.ndarray:
    """Indices of the input grid used for design: log + linear spread and the PSD peaks.

    ``psd`` is what the objective weighs, disturbance plus noise: a peak of the disturbance
    below the noise floor is not one the design needs to resolve (and a noise-subtracted PSD
    clipped to a floor has a spurious "peak" at every bin that rises above the floor). The
    peaks of every row compete for one budget of ``n_grid // 5`` peaks (5 points each), the
    most prominent first, so that the grid has at most ``2 n_grid + 2`` points whatever the
    number of modes.
    """
    n = freqs.size
    if n <= n_grid:
        return np.arange(n)
    fpos = freqs[freqs > 0]
    n_log = int(round(0.6 * n_grid))
    targets = [
        np.geomspace(fpos[0], freqs[-1], n_log),
        np.linspace(freqs[0], freqs[-1], n_grid - n_log),
    ]
    idx = [np.clip(np.searchsorted(freqs, t), 0, n - 1) for t in targets]
    idx.append(np.array([0, n - 1]))
    # Resonances (vibrations): the local maxima that stand out of the smoothed log-PSD.
    logp = np.log10(np.maximum(psd, 1e-300 + psd.max(axis=-1, keepdims=True) * 1e-30))
    where, prominence = [], []
    for row in np.atleast_2d(logp):
        peaks, props = find_peaks(row, prominence=_PEAK_PROMINENCE_DECADES)
        if peaks.size:
            top = np.argsort(props["prominences"])[::-1][:_MAX_PEAKS]
            where.append(peaks[top])
            prominence.append(props["prominences"][top])
    if where:
        where, prominence = np.concatenate(where), np.concatenate(prominence)
        order = np.argsort(prominence, kind="stable")[::-1]
        _, first = np.unique(where[order], return_index=True)
        keep = where[order][np.sort(first)][: max(n_grid // 5, 1)]
        idx.append(np.clip((keep[:, None] + np.arange(-2, 3)).ravel(), 0, n - 1))
    return np.unique(np.concatenate(idx))


def _interp_matrix(f_design: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Hat-function matrix ``H`` (n_design, n): linear interpolation from design points."""
    H = np.zeros((f_design.size, f.size))
    j = np.clip(np.searchsorted(f_design, f, side="right") - 1, 0, f_design.size - 2)
    lo, hi = f_design[j], f_design[j + 1]
    t = np.clip((f - lo) / (hi - lo), 0.0, 1.0)
    cols = np.arange(f.size)
    H[j, cols] += 1.0 - t
    H[j + 1, cols] += t
    return H


def _dense_grid(f_design: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Verification grid over [lo, hi]: linear and log-spaced, >= 10x the design grid."""
    n = max(_DENSE_FACTOR * f_design.size, _MIN_DENSE)
    lin = np.linspace(lo, hi, n)
    # Log-spaced down to 1e-6 fs/2: a near pole-zero cancellation close to z = 1 can hide a
    # closed-loop pole pair crossing the circle at a tiny frequency.
    log = np.geomspace(max(lo, hi * 2e-6), hi, n // 2)
    return np.unique(np.concatenate([lin, log, f_design]))


# Fine check of the residual: linear and log points over the input range, and a log ladder of
# offsets around every |S| peak [fraction of fs/2] (a peak of width down to ~1e-7 fs/2).
_FINE_LINEAR, _FINE_LOG = 20001, 2001
_PEAK_OFFSETS = np.concatenate([[0.0], np.geomspace(1e-7, 1e-3, 9)])
_FINE_BLOCK = 64


def fine_residual(
    plant: object,
    banks: tuple,
    freqs: np.ndarray,
    psd: np.ndarray,
    noise: np.ndarray,
    fs: float,
    peaks: list,
) -> tuple:
    """Residual variance of each bank on a fine grid, the PSDs interpolated linearly.

    The reported residual is the trapezoid on the user's grid; this check integrates the exact
    ``|S|^2`` and ``|T|^2`` on 20,001 linear and 2,001 log-spaced points over the input range,
    the input points and a ladder of points around every ``|S|`` peak (``peaks``, Hz), with
    the PSDs linear between input points (the model the trapezoid rule assumes): a resonance
    of ``|S|`` between input points is seen.

    Returns
    -------
    tuple of numpy.ndarray, each of shape (n_modes,)
        One residual variance per mode for each bank [units^2].
    """
    from aocontrol.plant import frequency_response

    lo, hi = freqs[0], freqs[-1]
    pos = freqs[freqs > 0]
    parts = [freqs, np.linspace(lo, hi, _FINE_LINEAR)]
    if pos.size:
        parts.append(np.geomspace(pos[0], hi, _FINE_LOG))
    if peaks:
        p = np.concatenate([np.ravel(x) for x in peaks] + [np.empty(0)])
        p = np.unique(p[(p > lo) & (p < hi)])
        if p.size:
            d = _PEAK_OFFSETS * fs / 2
            parts.append((p[:, None] + np.concatenate([-d, d])[None, :]).ravel())
    f = np.unique(np.clip(np.concatenate(parts), lo, hi))
    j = np.clip(np.searchsorted(freqs, f, side="right") - 1, 0, freqs.size - 2)
    t = np.clip((f - freqs[j]) / (freqs[j + 1] - freqs[j]), 0.0, 1.0)
    # |S|^2 psd + |T|^2 noise = (|A|^2 psd + |G B|^2 noise) / |A + G B|^2 for K = B / A (what
    # aocontrol.analysis.residual_psd gives, A = 0 included: the noise PSD), evaluated from
    # the coefficients: the plant's response and the powers of z^-1 once for every bank.
    g = frequency_response(plant, f, fs)
    n_pow = max(max(bank.b.shape[1], bank.a.shape[1]) for bank in banks)
    zi = np.exp(-2j * np.pi * f / fs)
    powers = np.ones((n_pow, f.size), complex)
    for k in range(1, n_pow):
        powers[k] = powers[k - 1] * zi
    out = [np.empty(psd.shape[0]) for _ in banks]
    for s in range(0, psd.shape[0], _FINE_BLOCK):
        rows = slice(s, s + _FINE_BLOCK)
        pf = psd[rows, j] * (1 - t) + psd[rows, j + 1] * t
        nf = noise[rows, j] * (1 - t) + noise[rows, j + 1] * t
        for k, bank in enumerate(banks):
            A = bank.a[rows] @ powers[: bank.a.shape[1]]
            GB = (bank.b[rows] @ powers[: bank.b.shape[1]]) * g
            a2, gb2 = A.real**2 + A.imag**2, GB.real**2 + GB.imag**2
            P = A + GB
            r = (a2 * pf + gb2 * nf) / (P.real**2 + P.imag**2)
            out[k][rows] = np.trapezoid(r, f, axis=-1)
    return tuple(out)
