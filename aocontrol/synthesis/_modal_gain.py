"""Optimised modal gains of an integrator bank (Gendron & Lena 1994).

Per mode, the gain ``g`` of ``C(z) = g / (1 - (1 - leak) z^-1)`` minimises the residual
variance predicted from the pseudo-open-loop disturbance PSD and the noise PSD::

    J(g) = int_0^{fs/2} |S(g)|^2 psd + |T(g)|^2 noise_psd df,  S = 1/(1+gL1), T = gL1/(1+gL1)

with ``L1 = G / (1 - (1 - leak) z^-1)``, over gains below the stability limit (and, when a
modulus margin ``mu`` is requested, with ``min |1 + g L1| >= mu``). ``J`` is exactly what
:func:`aocontrol.analysis.residual_variance` computes (trapezoid on the same grid).

Reference: Gendron E. & Lena P., 1994, A&A 291, 337, "Astronomical adaptive optics. I.
Modal control optimization".
"""

from __future__ import annotations

import logging

import control
import numpy as np
from scipy import optimize

from aocontrol._validation import (
    PerModeError,
    check_frequency_grid,
    check_in_range,
    is_programming_error,
    mode_psds,
)
from aocontrol.analysis import is_stable
from aocontrol.controllers import Integrator
from aocontrol.plant import check_frd_coverage, frequency_response_unchecked, plant_fs

__all__ = ["optimal_modal_gain", "integrator_gain_limit", "ModalGainError"]

logger = logging.getLogger(__name__)

# Points of the dense half-circle grid used for the stability limit and the modulus margin.
_N_DENSE = 16384
# Gains are kept this fraction below the stability limit (the limit itself is marginal).
_STABILITY_BACKOFF = 1e-6
# Lowest gain searched without leak, as a fraction of the largest: a zero gain is a marginally
# stable pole at z = 1 (residual_variance reports it as unstable).
_MIN_GAIN_FRACTION = 1e-6
# Largest gain searched when the loop has no phase crossover (no finite stability limit).
_FALLBACK_MAX_GAIN = 10.0
# Coarse gain grid (bracketing the global minimum) and golden-section tolerance (fraction of
# the largest gain).
_N_COARSE = 129
_GOLDEN_XTOL = 1e-7
# Modes evaluated together in the golden-section search (memory ~ block * n_freqs * 16 B).
_BLOCK = 256


class ModalGainError(PerModeError):
    """The gain optimisation failed numerically for some modes; the others are kept.

    Parameters
    ----------
    failed : dict of int to str
        Mode index -> reason (exception type and message).
    result : Integrator
        Every mode: optimised gains, and for the failed modes the fallback gain ``g_min``
        (the smallest gain of the search: stabilising, barely correcting).

    Attributes
    ----------
    failed : dict of int to str
    result : Integrator
    """

    def __init__(self, failed: dict[int, str], result: Integrator) -> None:
        super().__init__(
            failed,
            result,
            n_modes=result.n_modes,
            operation="optimal modal gain",
            note="; error.result holds every mode (failed ones at the fallback gain)",
        )


def _dense_freqs(plant: object, fs: float) -> np.ndarray:
    f = np.linspace(0.0, fs / 2, _N_DENSE + 1)
    if isinstance(plant, control.FRD):
        f_grid = np.asarray(plant.omega, dtype=float) / (2 * np.pi)
        f = np.union1d(f[(f >= f_grid[0]) & (f <= f_grid[-1])], f_grid)
    return f


def _open_loop_unit(plant: object, freqs: np.ndarray, fs: float, leak: float) -> np.ndarray:
    """``L1 = G / (1 - (1 - leak) z^-1)`` at ``freqs``; ``inf`` where the integrator is."""
    zi = np.exp(-2j * np.pi * freqs / fs)
    den = 1.0 - (1.0 - leak) * zi
    G = frequency_response_unchecked(plant, np.atleast_1d(freqs), fs)  # validated by caller
    out = np.full(freqs.shape, np.inf + 0j)
    ok = np.abs(den) > 0
    out[ok] = G[ok] / den[ok]
    return out


def _stability_limit(plant: object, fs: float, leak: float) -> float:
    """Smallest gain at which ``1 + g L1`` touches 0 on the unit circle (first crossing)."""
    f = _dense_freqs(plant, fs)
    L1 = _open_loop_unit(plant, f, fs, leak)
    finite = np.isfinite(L1)
    exact = isinstance(plant, control.TransferFunction)

    def im_l1(fq: float) -> float:
        return float(_open_loop_unit(plant, np.array([fq]), fs, leak)[0].imag)

    cands = []
    im = np.where(finite, L1.imag, np.nan)
    idx = np.flatnonzero(finite[:-1] & finite[1:] & (im[:-1] * im[1:] < 0))
    for i in idx:
        if exact:
            fq = optimize.brentq(im_l1, f[i], f[i + 1], xtol=1e-12 * fs)
            v = _open_loop_unit(plant, np.array([fq]), fs, leak)[0]
        else:
            w = im[i] / (im[i] - im[i + 1])
            v = L1[i] + w * (L1[i + 1] - L1[i])
        cands.append(v.real)
    cands.extend(L1[finite & (im == 0.0)].real.tolist())
    # Both ends of the half circle lie on the real axis for real-coefficient systems (the
    # crossing of an integrator with a one-frame delay is exactly at Nyquist).
    for end, f_end in ((0, 0.0), (-1, fs / 2)):
        if finite[end] and abs(f[end] - f_end) <= 1e-12 * fs:
            cands.append(float(L1[end].real))
    neg = [c for c in cands if c < 0]
    return float(-1.0 / min(neg)) if neg else np.inf


def _min_return_difference(
    plant: object, f: np.ndarray, L1: np.ndarray, fs: float, leak: float, g: float
) -> float:
    """``min_f |1 + g L1|`` on the dense grid, refined around the minimum (TF plants)."""
    finite = np.isfinite(L1)
    d = np.where(finite, np.abs(1.0 + g * np.where(finite, L1, 0.0)), np.inf)
    i = int(np.argmin(d))
    best = float(d[i])
    if isinstance(plant, control.TransferFunction):
        lo, hi = f[max(i - 1, 0)], f[min(i + 1, f.size - 1)]
        res = optimize.minimize_scalar(
            lambda fq: float(np.abs(1.0 + g * _open_loop_unit(plant, np.array([fq]), fs, leak)[0])),
            bounds=(lo, hi),
            method="bounded",
            options={"xatol": 1e-10 * fs},
        )
        best = min(best, float(res.fun))
    return best


def integrator_gain_limit(
    plant: control.TransferFunction | control.FRD,
    *,
    leak: float = 0.0,
    modulus_margin: float | None = None,
    fs: float | None = None,
) -> float:
    """Largest admissible gain of ``g / (1 - (1 - leak) z^-1)`` on ``plant``.

    The stability limit (first crossing of -1 by ``g L1`` on the unit circle, refined exactly
    for transfer functions), backed off by a relative 1e-6; with ``modulus_margin = mu`` also
    the largest ``g`` such that ``min |1 + g' L1| >= mu`` for every ``g' <= g`` (bisection on
    a 16385-point half-circle grid refined around the minimum). Assumes a plant with positive
    static gain for which small gains are stable (AO plants: delays).

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant.
    leak : float, default 0.0
        Integrator leak in [0, 1).
    modulus_margin : float, optional
        Required ``min |1 + L|`` in (0, 1).
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.

    Returns
    -------
    float
        Largest gain (dimensionless); 10 if the loop never crosses -1 (no phase crossover).

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> # G = z^-1: stability limit g < 2 (pole 1 - g inside the unit circle)
    >>> round(integrator_gain_limit(loop_plant(1000.0, 0.0)), 5)
    2.0
    """
    fs_ = plant_fs(plant, fs)
    if isinstance(plant, control.FRD):
        # The limit is the first crossing of -1 on the whole circle: a band never measured
        # could hold it.
        check_frd_coverage("plant", plant, fs_)
    leak = check_in_range("leak", leak, 0.0, 1.0)
    g_stab = _stability_limit(plant, fs_, leak)
    g_max = g_stab * (1.0 - _STABILITY_BACKOFF) if np.isfinite(g_stab) else _FALLBACK_MAX_GAIN
    if modulus_margin is None:
        return float(g_max)
    mu = check_in_range("modulus_margin", modulus_margin, 0.0, 1.0, low_inclusive=False)
    f = _dense_freqs(plant, fs_)
    L1 = _open_loop_unit(plant, f, fs_, leak)
    finite = np.isfinite(L1)
    gains = np.linspace(0.0, g_max, 257)
    Lf = np.where(finite, L1, 0.0)
    d = np.abs(1.0 + gains[:, None] * Lf[None, :])
    d[:, ~finite] = np.inf
    ok = d.min(axis=1) >= mu
    if ok.all() and _min_return_difference(plant, f, L1, fs_, leak, g_max) >= mu:
        return float(g_max)
    k = int(np.argmin(ok)) if not ok.all() else gains.size - 1

    def excess(g: float) -> float:
        return _min_return_difference(plant, f, L1, fs_, leak, g) - mu

    # The refined minimum can be below the grid minimum: move the bracket down until its
    # lower end is feasible (g = 0 always is: |1 + 0| = 1 > mu).
    while k > 1 and excess(gains[k - 1]) < 0:
        k -= 1
    lo, hi = gains[k - 1], gains[k]
    for _ in range(60):  # bisection to ~1e-18 of the bracket; lo stays feasible
        mid = 0.5 * (lo + hi)
        if excess(mid) >= 0:
            lo = mid
        else:
            hi = mid
    return float(min(lo, g_max))


def _residual_matrix(
    L1: np.ndarray, w: np.ndarray, gains: np.ndarray, psd: np.ndarray, noise: np.ndarray
) -> np.ndarray:
    """Residual variance for every (mode, gain) of a gain grid shared by all modes."""
    finite = np.isfinite(L1)
    Lf = np.where(finite, L1, 0.0)
    s2 = 1.0 / np.abs(1.0 + gains[:, None] * Lf[None, :]) ** 2
    t2 = (gains[:, None] ** 2) * np.abs(Lf[None, :]) ** 2 * s2
    s2[:, ~finite] = 0.0
    t2[:, ~finite] = 1.0
    return psd @ (s2 * w).T + noise @ (t2 * w).T


def _residual_per_mode(
    L1: np.ndarray, w: np.ndarray, g: np.ndarray, psd: np.ndarray, noise: np.ndarray
) -> np.ndarray:
    """Residual variance of each mode at its own gain ``g`` (shape (n_modes,))."""
    finite = np.isfinite(L1)
    Lf = np.where(finite, L1, 0.0)
    s2 = 1.0 / np.abs(1.0 + g[:, None] * Lf[None, :]) ** 2
    t2 = (g[:, None] ** 2) * np.abs(Lf[None, :]) ** 2 * s2
    s2[:, ~finite] = 0.0
    t2[:, ~finite] = 1.0
    return np.einsum("mf,f->m", s2 * psd + t2 * noise, w)


def _golden(fun, a: np.ndarray, b: np.ndarray, xtol: float) -> np.ndarray:
    """Vectorised golden-section minimisation of ``fun(x) -> (n,)`` on ``[a, b]`` per entry."""
    invphi = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = a.copy(), b.copy()
    width = float(np.max(b - a)) if a.size else 0.0
    n_iter = int(np.ceil(np.log(max(xtol, 1e-300) / max(width, xtol)) / np.log(invphi))) + 1
    c = b - invphi * (b - a)
    d = a + invphi * (b - a)
    fc, fd = fun(c), fun(d)
    for _ in range(max(n_iter, 0)):
        left = fc <= fd  # minimum in [a, d]
        b = np.where(left, d, b)
        a = np.where(left, a, c)
        new_c = b - invphi * (b - a)
        new_d = a + invphi * (b - a)
        # Reuse the surviving interior point, evaluate one new point per entry.
        x_new = np.where(left, new_c, new_d)
        f_new = fun(x_new)
        fc, fd, c, d = (
            np.where(left, f_new, fd),
            np.where(left, fc, f_new),
            np.where(left, x_new, d),
            np.where(left, c, x_new),
        )
    return np.where(fc <= fd, c, d)


def _block_gains(
    L1: np.ndarray,
    w: np.ndarray,
    coarse: np.ndarray,
    psd: np.ndarray,
    noise: np.ndarray,
    g_max: float,
) -> np.ndarray:
    """Optimal gains of a block of modes (coarse grid, then golden section)."""
    p, n = np.ascontiguousarray(psd), np.ascontiguousarray(noise)
    with np.errstate(invalid="ignore", over="ignore"):
        J = _residual_matrix(L1, w, coarse, p, n)
    # A NaN would win argmin silently: treat it as +inf, and fail a mode with no finite value.
    J = np.where(np.isnan(J), np.inf, J)
    if not np.all(np.isfinite(J).any(axis=1)):
        bad = np.flatnonzero(~np.isfinite(J).any(axis=1))
        raise FloatingPointError(
            f"residual variance not finite at any gain for block rows {bad[:10].tolist()}"
        )
    k = np.argmin(J, axis=1)
    a = coarse[np.maximum(k - 1, 0)]
    b = coarse[np.minimum(k + 1, coarse.size - 1)]
    best = _golden(lambda g: _residual_per_mode(L1, w, g, p, n), a, b, _GOLDEN_XTOL * g_max)
    # Keep the coarse minimum if the refinement did not improve on it (flat objective).
    j_best = _residual_per_mode(L1, w, best, p, n)
    return np.where(j_best <= J[np.arange(k.size), k], best, coarse[k])


def optimal_modal_gain(
    plant: control.TransferFunction | control.FRD,
    freqs: object,
    psd: object,
    noise_psd: object = 0.0,
    *,
    modulus_margin: float | None = None,
    leak: float = 0.0,
    fs: float | None = None,
) -> Integrator:
    """Integrator bank with the residual-minimising gain per mode (Gendron & Lena 1994).

    For each mode, minimises ``J(g) = int (|S|^2 psd + |T|^2 noise_psd) df`` (trapezoid on
    ``freqs``, exactly :func:`aocontrol.analysis.residual_variance`) over
    ``g in [g_min, g_max]``: ``g_max`` from :func:`integrator_gain_limit` (stability limit,
    and the modulus margin if requested), ``g_min = 0`` with a leak, else ``1e-6 g_max`` (a
    pure integrator with zero gain is only marginally stable). The search is vectorised over
    modes: ``J`` on 129 gains shared by all modes (two matrix products), then a golden-section
    search in each mode's bracket around its coarse minimum (global minimum to the coarse
    resolution, then to ``1e-7 g_max``).

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant (e.g. :func:`aocontrol.loop_plant`), the same for every mode.
    freqs : array_like, shape (n_freqs,)
        Strictly increasing grid in [0, fs/2] [Hz]; it must resolve the PSDs and ``S``.
    psd : array_like, shape (n_freqs,) or (n_modes, n_freqs)
        Pseudo-open-loop disturbance PSD, one-sided [units^2/Hz].
    noise_psd : float or array_like, default 0.0
        Measurement-noise PSD, one-sided [units^2/Hz]: scalar (white), like ``psd``, or one
        white level per mode ``(n_modes,)`` (white noise of per-frame variance ``s2`` has
        level ``2 s2 / fs``).
    modulus_margin : float, optional
        If given, ``mu`` in (0, 1): every gain satisfies ``min |1 + L| >= mu`` (``||S||_inf
        <= 1/mu``), so the result is a feasible start for the data-driven design.
    leak : float, default 0.0
        Leak of the integrators in [0, 1).
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.

    Returns
    -------
    Integrator
        ``n_modes`` gains (``n_modes = 1`` for 1-D inputs), the given ``leak``.

    Raises
    ------
    ValueError
        Bad grid (not increasing, beyond Nyquist), PSDs with NaN/inf or negative values or of
        mismatched shapes, ``modulus_margin`` outside (0, 1), ``leak`` outside [0, 1), an FRD
        plant that does not cover [0, fs/2].
    ModalGainError
        A numerical failure (overflow, linear algebra, ...) for some modes; ``error.result``
        holds every mode, the failed ones at the fallback gain.

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> fs = 1000.0
    >>> f = np.linspace(1e-3, fs / 2, 4001)
    >>> # random walk (innovation variance 1) in white noise (variance 1), G = z^-1:
    >>> # optimal gain (-r + sqrt(r^2 + 4 r))/2 = 0.618 for r = 1 (steady-state Kalman gain)
    >>> zi = np.exp(-2j * np.pi * f / fs)
    >>> K = optimal_modal_gain(loop_plant(fs, 0.0), f, 2 / fs / np.abs(1 - zi) ** 2, 2 / fs)
    >>> round(float(K.gain[0]), 3)
    0.618
    """
    fs_ = plant_fs(plant, fs)
    freqs = check_frequency_grid("freqs", freqs, fs_)
    if freqs.size < 2:
        raise ValueError(f"freqs must have at least 2 points, got {freqs.size}")
    psd2, noise2, _ = mode_psds(psd, noise_psd, freqs.size)
    leak = check_in_range("leak", leak, 0.0, 1.0)
    g_max = integrator_gain_limit(plant, leak=leak, modulus_margin=modulus_margin, fs=fs_)
    g_min = 0.0 if leak > 0 else _MIN_GAIN_FRACTION * g_max

    L1 = _open_loop_unit(plant, freqs, fs_, leak)
    # Trapezoid weights: sum(w * y) == np.trapezoid(y, freqs).
    df = np.diff(freqs)
    w = np.zeros(freqs.size)
    w[:-1] += df / 2
    w[1:] += df / 2

    coarse = np.linspace(g_min, g_max, _N_COARSE)
    n_modes = psd2.shape[0]
    gains = np.empty(n_modes)
    failed: dict[int, str] = {}
    for start in range(0, n_modes, _BLOCK):
        sl = slice(start, min(start + _BLOCK, n_modes))
        try:
            gains[sl] = _block_gains(L1, w, coarse, psd2[sl], noise2[sl], g_max)
        except Exception as exc:
            if is_programming_error(exc):
                raise
            # Isolate the failing modes: each mode of the block on its own.
            for i in range(sl.start, sl.stop):
                try:
                    gains[i] = _block_gains(
                        L1, w, coarse, psd2[i : i + 1], noise2[i : i + 1], g_max
                    )[0]
                except Exception as exc_i:
                    if is_programming_error(exc_i):
                        raise
                    failed[i] = f"{type(exc_i).__name__}: {exc_i}"
                    gains[i] = g_min
    gains = np.clip(gains, g_min, g_max)
    K = Integrator(gains, fs=fs_, leak=leak)
    if failed:
        raise ModalGainError(failed, K)
    if isinstance(plant, control.TransferFunction) and not is_stable(
        plant, K, fs=fs_, mode=int(np.argmax(gains))
    ):
        raise RuntimeError(
            "internal error: the optimised integrator is not stabilising; "
            f"largest gain {gains.max()!r}, limit {g_max!r}"
        )
    return K
