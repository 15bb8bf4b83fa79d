"""Frequency grids and quadrature weights of the data-driven synthesis (private)."""

from __future__ import annotations

import numpy as np
from scipy.signal import find_peaks

from aocontrol._jit import compile_once

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


# A grid does not resolve the PSD when one of its intervals holds more than this share of the
# PSD's trapezoid integral while the PSD changes across it by more than this factor (e.g. a
# turbulence knee below the first nonzero point: the trapezoid there is a triangle whose area
# the design, seeing two points, cannot weigh: a 4.7-Hz first point above a 0.42-Hz knee
# makes the design a near-zero-gain integrator).
UNRESOLVED_SHARE, UNRESOLVED_RATIO = 0.25, 100.0


def unresolved_intervals(freqs: np.ndarray, psd: np.ndarray) -> dict[int, tuple]:
    """Modes whose PSD the grid does not resolve: ``{mode: (f_lo, f_hi, ratio, share)}``.

    For each mode, the worst interval ``[f_lo, f_hi]`` of ``freqs`` [Hz] across which the PSD
    (``psd`` of shape ``(n_modes, n_freqs)``, one-sided) changes by more than
    ``UNRESOLVED_RATIO`` (``ratio``) and which holds more than ``UNRESOLVED_SHARE`` of the
    row's trapezoid integral (``share``).
    """
    out: dict[int, tuple] = {}
    area = 0.5 * (psd[:, 1:] + psd[:, :-1]) * np.diff(freqs)
    total = area.sum(axis=1)
    lo, hi = psd[:, :-1], psd[:, 1:]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.maximum(lo, hi) / np.minimum(lo, hi)
        share = area / total[:, None]
    bad = (ratio > UNRESOLVED_RATIO) & (share > UNRESOLVED_SHARE)
    for i in np.flatnonzero(bad.any(axis=1)):
        k = int(np.argmax(np.where(bad[i], share[i], -1.0)))
        out[int(i)] = (float(freqs[k]), float(freqs[k + 1]), float(ratio[i, k]), float(share[i, k]))
    return out


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
    threads: int = 1,
) -> tuple:
    """Residual variance of each bank on a fine grid, the PSDs interpolated linearly.

    The reported residual is the trapezoid on the user's grid; this check integrates the exact
    ``|S|^2`` and ``|T|^2`` on 20,001 linear and 2,001 log-spaced points over the input range,
    the input points and, for each mode, a ladder of points around every one of its ``|S|``
    peaks (``peaks[i]``, Hz, mode ``i``), with the PSDs linear between input points (the
    model the trapezoid rule assumes): a resonance of ``|S|`` between input points is seen.

    The common points are evaluated for every mode at once; each mode's ladder refines the
    trapezoid on the intervals it falls in (``_refine``), which is the trapezoid on the
    common points and that ladder. (It was the union of every mode's ladders for every mode:
    ~32,000 more points for every mode of a 540-mode turbulence bank, 2.4 times the work.)

    ``threads``: blocks of :data:`_FINE_BLOCK` modes on this many threads (the figures do
    not depend on it). The common points' integrals are one compiled loop per block
    (:func:`_trapezoids`, numba; the numpy path without it, equal to rounding).

    Returns
    -------
    tuple of numpy.ndarray, each of shape (n_modes,)
        One residual variance per mode for each bank [units^2].
    """
    lo, hi = freqs[0], freqs[-1]
    pos = freqs[freqs > 0]
    parts = [freqs, np.linspace(lo, hi, _FINE_LINEAR)]
    if pos.size:
        parts.append(np.geomspace(pos[0], hi, _FINE_LOG))
    f = np.unique(np.clip(np.concatenate(parts), lo, hi))
    n_pow = max(max(bank.b.shape[1], bank.a.shape[1]) for bank in banks)
    ev = _Integrand(plant, banks, freqs, psd, noise, fs, n_pow)
    common = ev.basis(f)  # the plant and the powers of z^-1 on f, once for every block
    out = [np.empty(psd.shape[0]) for _ in banks]
    blocks = [
        np.arange(s, min(s + _FINE_BLOCK, psd.shape[0]))
        for s in range(0, psd.shape[0], _FINE_BLOCK)
    ]

    def block(rows: np.ndarray) -> list:
        return ev.trapezoids(f, rows, common)

    if threads > 1 and len(blocks) > 1:
        # numpy's element-wise passes release the GIL: the blocks run side by side, each
        # mode's arithmetic unchanged (the same bits as one thread)
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(min(threads, len(blocks))) as pool:
            values = list(pool.map(block, blocks))
    else:
        values = [block(rows) for rows in blocks]
    for rows, vals in zip(blocks, values, strict=True):
        for k, v in enumerate(vals):
            out[k][rows] = v
    if peaks is not None:
        for k, delta in enumerate(_refine(ev, f, peaks, fs)):
            out[k] += delta
    return tuple(out)


class _Integrand:
    """``|S|^2 psd + |T|^2 noise`` of each bank's modes at given frequencies."""

    def __init__(self, plant, banks, freqs, psd, noise, fs, n_pow) -> None:
        self.plant, self.banks, self.freqs = plant, banks, freqs
        self.psd, self.noise, self.fs, self.n_pow = psd, noise, fs, n_pow

    def basis(self, f: np.ndarray) -> tuple:
        """What the values at ``f`` share across modes and banks: the PSD grid's interval and
        position of each point, the plant's response and the powers of ``z^-1``."""
        from aocontrol.plant import frequency_response

        freqs = self.freqs
        j = np.clip(np.searchsorted(freqs, f, side="right") - 1, 0, freqs.size - 2)
        t = np.clip((f - freqs[j]) / (freqs[j + 1] - freqs[j]), 0.0, 1.0)
        g = frequency_response(self.plant, f.ravel(), self.fs).reshape(f.shape)
        zi = np.exp(-2j * np.pi * f / self.fs)
        powers = np.ones((self.n_pow,) + f.shape, complex)
        for k in range(1, self.n_pow):
            powers[k] = powers[k - 1] * zi
        return j, t, g, powers

    def __call__(self, f: np.ndarray, rows: np.ndarray, basis: tuple | None = None) -> list:
        """Values at ``f`` (shape (m,), the same for every row, or (rows.size, m), one row of
        points per mode) for the modes ``rows``: one (rows.size, m) array per bank.
        ``basis``: :meth:`basis` of ``f`` if already computed."""
        # |S|^2 psd + |T|^2 noise = (|A|^2 psd + |G B|^2 noise) / |A + G B|^2 for K = B / A
        # (what aocontrol.analysis.residual_psd gives, A = 0 included: the noise PSD),
        # evaluated from the coefficients: the plant's response and the powers of z^-1 once
        # for every bank.
        j, t, g, powers = self.basis(f) if basis is None else basis
        psd, noise = self.psd[rows], self.noise[rows]
        if f.ndim == 2:
            r = np.arange(rows.size)[:, None]
            pf = psd[r, j] * (1 - t) + psd[r, j + 1] * t
            nf = noise[r, j] * (1 - t) + noise[r, j + 1] * t
        else:
            pf = psd[:, j] * (1 - t) + psd[:, j + 1] * t
            nf = noise[:, j] * (1 - t) + noise[:, j + 1] * t
        out = []
        for bank in self.banks:
            if f.ndim == 2:
                A = np.einsum("nk,knm->nm", bank.a[rows], powers[: bank.a.shape[1]])
                GB = np.einsum("nk,knm->nm", bank.b[rows], powers[: bank.b.shape[1]]) * g
            else:
                A = bank.a[rows] @ powers[: bank.a.shape[1]]
                GB = (bank.b[rows] @ powers[: bank.b.shape[1]]) * g
            a2, gb2 = A.real**2 + A.imag**2, GB.real**2 + GB.imag**2
            P = A + GB
            out.append((a2 * pf + gb2 * nf) / (P.real**2 + P.imag**2))
        return out

    def trapezoids(self, f: np.ndarray, rows: np.ndarray, basis: tuple) -> list:
        """The trapezoid over ``f`` (shape (m,)) of :meth:`__call__`'s values, one array
        (rows.size,) per bank: the compiled :func:`_trapezoids` (a pass over the points per
        mode, no (rows, m) arrays), or numpy's ``np.trapezoid`` of them without numba.

        The two agree to rounding: the compiled loop sums the products and the trapezoid's
        terms in order (numpy: its matrix product, pairwise sums), which moves a mode's
        integral by a few units in the last place where the evaluation is well conditioned
        and by up to about 1e-10 relative where ``|1 + G K|`` is computed from near-cancelling
        terms (measured on a 540-mode telemetry bank; both paths 6e-11 to 2e-10 from an
        extended-precision evaluation there). The integrals decide only whether a design is
        worse than its start by more than 1e-6 relative and the grid-disagreement warning.
        """
        compiled = compile_once(_KERNEL, (_trapezoids,), "the fine check runs in numpy")
        if compiled is None:
            return [np.trapezoid(r, f, axis=-1) for r in self(f, rows, basis)]
        j, t, g, powers = basis
        psd = np.ascontiguousarray(self.psd[rows], dtype=float)
        noise = np.ascontiguousarray(self.noise[rows], dtype=float)
        out = []
        for bank in self.banks:
            a = np.ascontiguousarray(bank.a[rows], dtype=float)
            b = np.ascontiguousarray(bank.b[rows], dtype=float)
            res = np.empty(rows.size)
            compiled[0](a, b, j, t, g, powers, f, psd, noise, res)
            out.append(res)
        return out


_KERNEL: list = []  # [(the compiled _trapezoids,) or None], filled on first use


def _trapezoids(a, b, j, t, g, powers, f, psd, noise, out):  # pragma: no cover - compiled
    """``out[r]``: trapezoid over ``f`` of ``(|A|^2 psd + |G B|^2 noise) / |A + G B|^2`` for
    row ``r`` (``A``, ``B`` the rows of ``a``, ``b`` on ``powers`` of ``z^-1``, ``G`` =
    ``g``; the PSDs linear between the input points: interval ``j``, position ``t``). Plain
    Python, compiled by :func:`aocontrol._jit.compile_once`; :meth:`_Integrand.__call__`
    and ``np.trapezoid`` are its numpy twin."""
    m = f.size
    ka, kb = a.shape[1], b.shape[1]
    for r in range(a.shape[0]):
        total = 0.0
        prev = 0.0
        for k in range(m):
            ar = a[r, 0] * powers[0, k].real
            ai = a[r, 0] * powers[0, k].imag
            for c in range(1, ka):
                ar += a[r, c] * powers[c, k].real
                ai += a[r, c] * powers[c, k].imag
            br = b[r, 0] * powers[0, k].real
            bi = b[r, 0] * powers[0, k].imag
            for c in range(1, kb):
                br += b[r, c] * powers[c, k].real
                bi += b[r, c] * powers[c, k].imag
            gr, gi = g[k].real, g[k].imag
            gbr, gbi = br * gr - bi * gi, br * gi + bi * gr
            pr, pi = ar + gbr, ai + gbi
            jk, tk = j[k], t[k]
            pf = psd[r, jk] * (1 - tk) + psd[r, jk + 1] * tk
            nf = noise[r, jk] * (1 - tk) + noise[r, jk + 1] * tk
            v = ((ar * ar + ai * ai) * pf + (gbr * gbr + gbi * gbi) * nf) / (pr * pr + pi * pi)
            if k:
                total += (f[k] - f[k - 1]) * (v + prev)
            prev = v
        out[r] = total / 2


def _refine(ev: _Integrand, f: np.ndarray, peaks: list, fs: float) -> list:
    """Change of each mode's trapezoid on the sorted grid ``f`` when its ladder of points
    around its peaks (``peaks[i]``, Hz) joins the grid, one array (n_modes,) per bank.

    The intervals of ``f`` holding a new point are integrated on their end points and the new
    points instead; every mode's points are evaluated at once (rows padded with their last
    point: zero-width segments).
    """
    lo, hi = f[0], f[-1]
    d = np.concatenate([-_PEAK_OFFSETS[::-1], _PEAK_OFFSETS[1:]]) * fs / 2
    n_modes = len(peaks)
    modes, pts_rows, kept = [], [], []
    for i, p in enumerate(peaks):
        p = np.ravel(p)
        p = p[(p > lo) & (p < hi)]
        if not p.size:
            continue
        new = np.unique(np.clip((p[:, None] + d[None, :]).ravel(), lo, hi))
        at = np.searchsorted(f, new)
        new = new[f[np.minimum(at, f.size - 1)] != new]  # not already on the grid
        if not new.size:
            continue
        k = np.unique(np.clip(np.searchsorted(f, new) - 1, 0, f.size - 2))  # refined intervals
        pts = np.unique(np.concatenate([f[k], f[k + 1], new]))
        mid = np.clip(np.searchsorted(f, (pts[:-1] + pts[1:]) / 2) - 1, 0, f.size - 2)
        inside = k[np.minimum(np.searchsorted(k, mid), k.size - 1)] == mid
        # Where the refined intervals' end points are among pts: their old trapezoid.
        ends = np.searchsorted(pts, np.stack([f[k], f[k + 1]]))
        modes.append(i)
        pts_rows.append(pts)
        kept.append((inside, ends, f[k + 1] - f[k]))
    out = [np.zeros(n_modes) for _ in ev.banks]
    if not modes:
        return out
    m = max(x.size for x in pts_rows)
    grid = np.array([np.pad(x, (0, m - x.size), mode="edge") for x in pts_rows])
    for b, vals in enumerate(ev(grid, np.array(modes))):
        for row, (i, (inside, ends, width)) in enumerate(zip(modes, kept, strict=True)):
            v = vals[row]
            x = grid[row, : inside.size + 1]
            seg = (v[:-1][: inside.size] + v[1 : inside.size + 1]) / 2 * np.diff(x)
            before = (v[ends[0]] + v[ends[1]]) / 2 * width
            out[b][i] = float(np.sum(seg[inside]) - np.sum(before))
    return out
