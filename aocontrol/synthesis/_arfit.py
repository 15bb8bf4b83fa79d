"""Fitting the per-mode disturbance models of :mod:`aocontrol.synthesis._armodel` to PSDs.

AR(2) turbulence by Yule-Walker on the PSD's autocovariance, refined by a weighted log-PSD
least-squares fit, then up to ``n_vibrations`` resonances picked from the peaks that stand out
of the turbulence model and fitted jointly (frequency, damping, variance). PSDs are one-sided
[units^2/Hz] (``scipy.signal.welch(..., scaling="density")``).
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from aocontrol._validation import (
    check_frequency_grid,
    check_int,
    check_positive,
    mode_psds,
)
from aocontrol.synthesis._armodel import (
    DisturbanceModel,
    _ar2_denominator,
    _ar2_psd,
    _finite_rows,
    _resonator,
    ar2_variance,
)

__all__ = ["fit_disturbance_model"]

logger = logging.getLogger(__name__)

# Bounds of the turbulence's reflection coefficients in the fit, atanh scale: tanh(15) =
# 1 - 1.9e-13, so a fitted pole cannot reach the unit circle by the optimiser's rounding.
_ATANH_BOUND = 15.0
# Bounds of the fitted log-variances, as natural-log offsets from the log of the mode's PSD
# variance: a driving variance is at most the process variance and, with the reflection
# coefficients within tanh(15), at least ~1e-26 of it (e^-60); a resonance carries at most
# the whole variance and below e^-40 of it is nothing. The optimisers keep them (exp() stays
# finite on every iterate), except the driving variance of the joint refinement (L-BFGS-B):
# a bound there, however loose, changes its path (its subspace steps treat bounded variables
# apart) and lost the strongest resonance of a two-peak spectrum to a misfit; that one is
# capped in the map (``_LOG_S2_CAP``) instead.
_LOG_VAR_BOUNDS = {"driving": (-70.0, 5.0), "resonance": (-40.0, 5.0)}
# Largest natural-log driving variance the parameter map evaluates: e^300 ~ 1e130 keeps the
# PSD (<= 2 s2 / fs / 1e-30) and its gradient (one more 1 / |A|^2) below the float range.
_LOG_S2_CAP = 300.0
# The Whittle objective's model spectrum is floored at this fraction of the largest target
# value (the rounding level of a spectrum): target / S and target / S^2 stay finite.
_SPECTRUM_FLOOR = 1e-15
# Fitted damping ratios are kept within these bounds (a resonance narrower than 1e-5 is not
# resolved by any telemetry record; one wider than 0.9 is not a resonance).
_XI_BOUNDS = (1e-5, 0.9)
# A PSD whose lag-1 correlation is within this of 1 has its variance at 0 Hz (no AR model).
_DC_TOL = 1e-12
# Fitted turbulence poles are kept at least this far inside the unit circle.
_R_MAX_GAP = 1e-8
# Modes per parallel work item of the fit.
_FIT_CHUNK = 16
# Iterations of the peak-masking loop that separates the smooth turbulence from the peaks.
_MASK_ITER = 6


def _autocov(freqs: np.ndarray, psd: np.ndarray, fs: float, lags: int) -> np.ndarray:
    """Autocovariance ``r[tau] = int_0^{fs/2} P(f) cos(2 pi f tau / fs) df`` (trapezoid)."""
    tau = np.arange(lags + 1)
    return np.trapezoid(
        psd[None, :] * np.cos(2 * np.pi * freqs[None, :] * tau[:, None] / fs), freqs
    )


def _yule_walker_ar2(r: np.ndarray) -> tuple[float, float, float]:
    """AR(2) ``(a1, a2, s_w^2)`` from the autocovariances ``r[0..2]`` (Levinson), with the
    reflection coefficients clipped into the open unit interval (a stable model)."""
    k_lim = np.tanh(_ATANH_BOUND)
    k1 = float(np.clip(r[1] / r[0], -k_lim, k_lim))
    e1 = r[0] * (1 - k1 * k1)
    k2 = float(np.clip((r[2] - k1 * r[1]) / e1, -k_lim, k_lim))
    a1 = k1 * (1 - k2)
    a2 = k2
    return a1, a2, max(float(e1 * (1 - k2 * k2)), 1e-300)


def _turb_from_params(p: np.ndarray) -> tuple[float, float, float]:
    """(a1, a2, s_w^2) from (atanh k1, atanh k2, log s_w^2): always a stable AR(2).

    ``log s_w^2`` is capped at ``_LOG_S2_CAP`` (an unbounded optimiser's trial step cannot
    overflow; the fits' solutions lie far below it, within ``_LOG_VAR_BOUNDS``).
    """
    k1, k2 = np.tanh(p[0]), np.tanh(p[1])
    return float(k1 * (1 - k2)), float(k2), float(np.exp(min(p[2], _LOG_S2_CAP)))


def _turb_params(a1: float, a2: float, s2: float) -> np.ndarray:
    k2 = a2
    k1 = a1 / (1 - a2)
    lim = np.tanh(_ATANH_BOUND)
    return np.array(
        [np.arctanh(np.clip(k1, -lim, lim)), np.arctanh(np.clip(k2, -lim, lim)), np.log(s2)]
    )


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs ``[start, stop)`` of True in a 1-D mask."""
    edges = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def _ar2_psd_grad(
    c1: float, c2: float, s2: float, zi: np.ndarray, fs: float
) -> tuple[np.ndarray, np.ndarray]:
    """PSD ``M`` of one AR(2) component and ``dM / d(c1, c2, log s2)``, shape ``(3, n)``.

    ``M = 2 s2 / fs / |A|^2``, ``A = 1 - c1 z^-1 - c2 z^-2``:
    ``dM/dc = 2 M Re(z^-i conj(A)) / |A|^2`` (i = 1, 2), ``dM/dlog s2 = M``; ``|A|^2``
    floored at the rounding level (:func:`aocontrol.synthesis._armodel._ar2_denominator`).
    """
    a, a2 = _ar2_denominator(np.asarray(c1), np.asarray(c2), zi)
    m = 2 * s2 / fs / a2
    ca = np.conj(a)
    d = np.empty((3, zi.size))
    d[0] = 2 * m * (zi * ca).real / a2
    d[1] = 2 * m * (zi * zi * ca).real / a2
    d[2] = m
    return m, d


def _turb_jacobian(p: np.ndarray) -> np.ndarray:
    """``d(a1, a2, log s2) / d(atanh k1, atanh k2, log s2)``, shape ``(3, 3)``."""
    k1, k2 = np.tanh(p[0]), np.tanh(p[1])
    return np.array(
        [
            [(1 - k1 * k1) * (1 - k2), -k1 * (1 - k2 * k2), 0.0],
            [0.0, 1 - k2 * k2, 0.0],
            [0.0, 0.0, 1.0],
        ]
    )


def _vib_coefficients(q: np.ndarray, fs: float) -> np.ndarray:
    """``(b1, b2, log s_w^2)`` of a resonance from ``(f0, log xi, log variance)``."""
    b1, b2 = _resonator(np.asarray(q[0]), np.exp(q[1]), fs)
    return np.array([b1, b2, q[2] - np.log(ar2_variance(b1, b2, 1.0))])


def _vib_jacobian(q: np.ndarray, fs: float) -> np.ndarray:
    """Central-difference Jacobian of :func:`_vib_coefficients`, shape ``(3, 3)``."""
    jac = np.empty((3, 3))
    for i in range(3):
        h = 1e-6 * max(abs(q[i]), 1.0)
        dq = np.zeros(3)
        dq[i] = h
        jac[:, i] = (_vib_coefficients(q + dq, fs) - _vib_coefficients(q - dq, fs)) / (2 * h)
    return jac


def _log_var_bounds(kind: str, variance: float) -> tuple[float, float]:
    """Bounds of a fitted natural-log variance around ``log(variance)`` (``_LOG_VAR_BOUNDS``)."""
    lo, hi = _LOG_VAR_BOUNDS[kind]
    centre = float(np.log(variance))
    return centre + lo, centre + hi


def _log_weights(freqs: np.ndarray) -> np.ndarray:
    """Quadrature weights of the log-frequency measure ``df / f`` (0 Hz as half the first bin)."""
    pos = freqs[freqs > 0]
    lf = np.log(np.maximum(freqs, pos[0] / 2 if pos.size else 1.0))
    w = np.gradient(lf)
    return w / w.sum()


def _fit_turbulence(
    freqs: np.ndarray,
    p: np.ndarray,
    noise: float,
    zi: np.ndarray,
    fs: float,
    start: tuple[float, float, float],
    ratio: float,
    variance: float,
) -> tuple[float, float, float]:
    """AR(2) ``(a1, a2, s_w^2)`` fitting the smooth part of ``p`` in log scale.

    Least squares on ``log(model + noise) - log(p + noise)`` with the log-frequency measure
    and a robust (soft L1) loss; points flagged as peaks (``p + noise > ratio (model +
    noise)``) are dropped and the fit repeated until the flags settle.
    """
    w = np.sqrt(_log_weights(freqs))
    floor = 1e-12 * max(float(np.max(p + noise)), 1e-300)
    logp = np.log(np.maximum(p + noise, floor))
    keep = np.ones(freqs.size, dtype=bool)
    x = _turb_params(*start)
    lim = (-_ATANH_BOUND, _ATANH_BOUND)
    lv = _log_var_bounds("driving", variance)
    bounds = ([lim[0], lim[0], lv[0]], [lim[1], lim[1], lv[1]])
    x = np.clip(x, np.array(bounds[0]) + 1e-9, np.array(bounds[1]) - 1e-9)
    for _ in range(_MASK_ITER):

        def resid(x: np.ndarray, keep: np.ndarray = keep) -> np.ndarray:
            a1, a2, s2 = _turb_from_params(x)
            m = _ar2_psd(np.asarray(a1), np.asarray(a2), np.asarray(s2), zi[keep], fs)
            return w[keep] * (np.log(np.maximum(m + noise, floor)) - logp[keep])

        def jac(x: np.ndarray, keep: np.ndarray = keep) -> np.ndarray:
            m, dm = _ar2_psd_grad(*_turb_from_params(x), zi[keep], fs)
            return ((w[keep] / np.maximum(m + noise, floor)) * dm).T @ _turb_jacobian(x)

        x = optimize.least_squares(
            resid, x, jac=jac, bounds=bounds, loss="soft_l1", f_scale=0.1 * float(w.mean())
        ).x
        a1, a2, s2 = _turb_from_params(x)
        model = _ar2_psd(np.asarray(a1), np.asarray(a2), np.asarray(s2), zi, fs)
        new_keep = ~((p + noise) > ratio * (model + noise))
        if np.array_equal(new_keep, keep) or new_keep.sum() < 8:
            break
        keep = new_keep
    return _turb_from_params(x)


@dataclass(frozen=True)
class _FitSettings:
    fs: float
    n_vibrations: int
    peak_ratio: float
    min_vibration_fraction: float


def _fit_mode(
    mode: int, freqs: np.ndarray, p: np.ndarray, noise: float, s: _FitSettings
) -> tuple[tuple[float, float, float], list[tuple[float, float, float]], bool]:
    """Fit one mode: turbulence ``(a1, a2, variance)``, resonances ``[(f0, xi, var)]`` and
    whether a turbulence pole was shrunk to the grid's resolution."""
    fs = s.fs
    zi = np.exp(-2j * np.pi * freqs / fs)
    w = np.gradient(freqs) if freqs.size > 1 else np.ones(1)
    w = w / w.sum()
    total_var = float(np.trapezoid(p, freqs)) if freqs.size > 1 else float(p[0] * fs / 2)
    if not total_var > 0:
        raise ValueError(f"psd of mode {mode} has no variance: no AR model can be fitted")
    # 1. Smooth turbulence: robust log-spectral fit of an AR(2) (peaks are positive
    # outliers), started from Yule-Walker, then refitted without the flagged peaks.
    r = _autocov(freqs, p, fs, 2)
    if not r[0] > 0:
        raise ValueError(f"psd of mode {mode} has no variance: no AR model can be fitted")
    if abs(r[1]) >= (1 - _DC_TOL) * r[0]:
        raise ValueError(
            f"psd of mode {mode}: no stable AR model can be fitted, its variance sits at 0 Hz "
            f"(lag-1 correlation {r[1] / r[0]:.15g}: a constant or a random walk, not a "
            "stationary disturbance)"
        )
    turb = _fit_turbulence(freqs, p, noise, zi, fs, _yule_walker_ar2(r), s.peak_ratio, r[0])
    mask = (p + noise) > s.peak_ratio * (_ar2_psd(*(np.asarray(v) for v in turb), zi, fs) + noise)
    model = _ar2_psd(*(np.asarray(v) for v in turb), zi, fs)
    excess = np.maximum(p - model, 0.0)
    # 2. Resonance candidates: the flagged runs, strongest excess variance first.
    first_pos = int(np.flatnonzero(freqs > 0)[0])
    cands = []
    for i0, i1 in _runs(mask):
        seg = slice(max(i0 - 1, 0), min(i1 + 1, freqs.size))
        var = float(np.trapezoid(excess[seg], freqs[seg])) if i1 - i0 >= 1 else 0.0
        ipk = i0 + int(np.argmax(excess[i0:i1]))
        f0 = freqs[ipk]
        if ipk <= first_pos or p[ipk - 1] >= p[ipk]:
            # Not a peak: the spectrum does not fall on its low-frequency side (an excess at
            # the grid's lowest bins is turbulence the grid does not resolve, e.g. the
            # variance a Welch estimate puts at 0 Hz, not a resonance).
            continue
        above = freqs >= f0 / 2
        ref = float(np.trapezoid(model[above] + noise, freqs[above])) if above.sum() > 1 else 0.0
        if not (0 < f0 < fs / 2) or var <= s.min_vibration_fraction * ref:
            continue
        half = excess[i0:i1] >= excess[ipk] / 2
        width = max(float(np.sum(w[i0:i1][half]) * (freqs[-1] - freqs[0])), 1e-12)
        xi = float(np.clip(width / (2 * f0), 2 * _XI_BOUNDS[0], 0.5))
        lo = freqs[max(i0 - 1, 0)] if i0 > 0 else f0 * 0.5
        hi = freqs[min(i1, freqs.size - 1)] if i1 < freqs.size else f0
        cands.append((var, f0, xi, max(lo, 1e-9), min(hi, fs / 2 * (1 - 1e-9))))
    cands.sort(reverse=True)
    cands = cands[: s.n_vibrations]
    # 3. Joint refinement: Whittle likelihood of the total spectrum (model + white noise),
    # sum_i w_i [log S_i + P_i / S_i], minimised at S = P for a model that fits exactly.
    x0 = [_turb_params(*turb)]
    bounds = [(-_ATANH_BOUND, _ATANH_BOUND)] * 2 + [(None, None)]
    for var, f0, xi, lo, hi in cands:
        x0.append([f0, np.log(xi), np.log(var)])
        bounds += [(lo, hi), tuple(np.log(_XI_BOUNDS)), _log_var_bounds("resonance", r[0])]
    x0 = np.concatenate(x0)
    lo_b, hi_b = ([np.inf * (2 * j - 1) if b[j] is None else b[j] for b in bounds] for j in (0, 1))
    x0 = np.clip(x0, lo_b, hi_b)
    target = p + noise
    scale = float(np.sum(w * target))
    s_floor = _SPECTRUM_FLOOR * float(np.max(target))

    def unpack(x: np.ndarray):
        a1, a2, s2 = _turb_from_params(x[:3])
        v = x[3:].reshape(-1, 3)
        return a1, a2, s2, v[:, 0], np.exp(v[:, 1]), np.exp(v[:, 2])

    def objective(x: np.ndarray) -> tuple[float, np.ndarray]:
        # Whittle objective and its exact gradient (chain rule through each component).
        m, dm = _ar2_psd_grad(*_turb_from_params(x[:3]), zi, fs)
        parts = [(dm, _turb_jacobian(x[:3]))]
        total = m + noise
        for q in x[3:].reshape(-1, 3):
            mv, dmv = _ar2_psd_grad(*_vib_coefficients(q, fs)[:2], 1.0, zi, fs)
            c = _vib_coefficients(q, fs)
            mv, dmv = mv * np.exp(c[2]), dmv * np.exp(c[2])
            total = total + mv
            parts.append((dmv, _vib_jacobian(q, fs)))
        sp = np.maximum(total, s_floor)
        value = float(np.sum(w * (np.log(sp / scale) + target / sp)))
        dj = w * (1 - target / sp) / sp
        grad = np.concatenate([(dmx @ dj) @ jx for dmx, jx in parts])
        return value, grad

    res = optimize.minimize(
        objective,
        x0,
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"maxiter": 2000, "ftol": 1e-15, "gtol": 1e-12},
    )
    x = res.x if np.isfinite(res.fun) and res.fun <= objective(x0)[0] else x0
    a1, a2, s2, f0, xi, var = unpack(x)
    tv = float(ar2_variance(a1, a2, s2))
    # Poles closer to the unit circle than the grid resolves (time constants beyond
    # fs / (pi f_lo) frames) are not supported by the data: shrink them to that radius.
    pos = freqs[freqs > 0]
    r_max = min(1.0 - np.pi * pos[0] / fs, 1.0 - _R_MAX_GAP)
    poles = np.roots([1.0, -a1, -a2])
    clipped = bool(np.max(np.abs(poles)) > r_max)
    if clipped:
        poles = np.where(np.abs(poles) > r_max, poles / np.abs(poles) * r_max, poles)
        a1, a2 = float(np.real(poles.sum())), float(-np.real(np.prod(poles)))
        # The model's shape below the grid is not the data's: only its variance is known
        # (the PSD's integral, a Welch estimate's 0-Hz bin included). Match it (the
        # variance of the unshrunk fit is unrelated, orders of magnitude off either way).
        tv = max(total_var - float(np.sum(var)), 1e-6 * total_var)
    if not (np.isfinite(tv) and tv >= 0 and np.all(np.isfinite([a1, a2]))):
        raise ValueError(f"psd of mode {mode}: no stable AR model can be fitted (fit diverged)")
    vibs = [(float(a), float(b), float(c)) for a, b, c in zip(f0, xi, var, strict=True)]
    return (a1, a2, tv), vibs, clipped


def _fit_chunk(freqs: np.ndarray, chunk: list, settings: _FitSettings) -> list:
    # One BLAS thread: L-BFGS-B calls the BLAS on vectors of a few elements at every
    # iteration, where a multi-threaded OpenBLAS wakes its threads each time (measured on
    # 2 cores at load ~1: 0.7-4.7 ms per objective evaluation against 35-43 us with one
    # thread; the LQG fit of 20 full-scale modes 4.0 s against 0.88 s, identical). The products
    # are small: a second thread has nothing to do.
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return [_fit_mode(m, freqs, p, noise, settings) for m, p, noise in chunk]


def _run_fits(freqs: np.ndarray, items: list, settings: _FitSettings, n_jobs: int | None) -> list:
    """Per-mode fits in this process or over joblib workers (chunks of modes, in order)."""
    if n_jobs is not None:
        n_jobs = check_int("n_jobs", n_jobs)
        if n_jobs == 0:
            raise ValueError("n_jobs must be a nonzero integer (negative: joblib convention)")
    from joblib import cpu_count

    cores = cpu_count()  # affinity, cgroups and LOKY_MAX_CPU_COUNT (a sweep worker's share)
    workers = cores if n_jobs is None else (n_jobs if n_jobs > 0 else max(1, cores + 1 + n_jobs))
    chunks = [items[i : i + _FIT_CHUNK] for i in range(0, len(items), _FIT_CHUNK)]
    workers = min(workers, len(chunks))
    if workers <= 1:
        return [r for chunk in chunks for r in _fit_chunk(freqs, chunk, settings)]
    from joblib import Parallel, delayed

    parts = Parallel(n_jobs=workers)(delayed(_fit_chunk)(freqs, c, settings) for c in chunks)
    return [r for part in parts for r in part]


def fit_disturbance_model(
    freqs: object,
    psd: object,
    fs: float,
    *,
    n_vibrations: int = 2,
    noise_psd: object = 0.0,
    peak_ratio: float = 4.0,
    min_vibration_fraction: float = 1e-2,
    n_jobs: int | None = 1,
) -> DisturbanceModel:
    """Fit AR(2) turbulence plus up to ``n_vibrations`` AR(2) resonances per mode to a PSD.

    Per mode:

    1. Smooth turbulence: an AR(2) fitted to ``log(psd + noise)`` by robust (soft L1) least
       squares over log frequency, started from Yule-Walker (autocovariances at lags 0-2
       integrated from the PSD), refitted without the peaks until they settle; a peak is
       where ``psd + noise > peak_ratio * (fit + noise)``.
    2. Resonance candidates: each contiguous peak region, its excess variance over the fit
       (kept if above ``min_vibration_fraction`` of the fit-plus-noise variance above half
       its frequency: a resonance counts against what the loop leaves at that frequency, not
       against the low-order turbulence), its frequency at the largest excess and its
       damping from the half-power width; the strongest ``n_vibrations`` are kept.
    3. Joint refinement of every parameter by the Whittle likelihood of the total spectrum
       ``S = model + noise``, ``sum_i df_i (log S_i + (psd_i + noise) / S_i)`` (the
       maximum-likelihood fit of a periodogram; minimal at ``S = psd + noise``, so a PSD of
       the model's form is recovered exactly). Parametrisations keep the turbulence stable
       (reflection coefficients ``tanh``), ``f0`` within its peak region and the damping in
       ``(1e-5, 0.9)``.
    4. Resolution: a turbulence pole closer to the unit circle than the grid resolves
       (modulus above ``1 - pi f_lo / fs``, ``f_lo`` the lowest positive grid frequency: a
       spectrum still rising at ``f_lo``, e.g. tip/tilt on a Welch grid) is shrunk to that
       radius, with a ``UserWarning`` naming the modes; the turbulence variance is then the
       PSD's integral minus the resonances' (moment matching: the data give the variance
       below ``f_lo``, not its shape).

    Parameters
    ----------
    freqs : array_like, shape (n_freqs,)
        Strictly increasing grid in ``[0, fs/2]`` [Hz] (a Welch grid, or log-spaced).
    psd : array_like, shape (n_freqs,) or (n_modes, n_freqs)
        Disturbance PSD, one-sided [units^2/Hz] (noise removed, e.g.
        :func:`aocontrol.synthesis.disturbance_from_telemetry`'s ``psd``).
    fs : float
        Loop rate [Hz].
    n_vibrations : int, default 2
        Largest number of resonances per mode (0: turbulence only).
    noise_psd : float or array_like, default 0.0
        White measurement-noise PSD, one-sided [units^2/Hz]: scalar or one level per mode
        ``(n_modes,)``. It weights the fit (frequencies where noise dominates carry little).
    peak_ratio : float, default 4.0
        Threshold of ``(psd + noise) / (turbulence fit + noise)`` marking a peak, > 1.
    min_vibration_fraction : float, default 1e-2
        Smallest resonance variance kept, as a fraction of the variance of the turbulence fit
        plus noise above half the resonance frequency.
    n_jobs : int or None, default 1
        Worker processes (joblib) over chunks of modes; ``None`` uses every core. Each mode's
        fit is independent: the result does not depend on ``n_jobs``.

    Returns
    -------
    DisturbanceModel

    Raises
    ------
    ValueError
        Non-finite or negative PSD, a mode with no variance or whose variance sits at 0 Hz
        (no stable AR model; naming the mode), bad grid or options.

    Warns
    -----
    UserWarning
        Modes whose spectrum is not resolved at low frequency (step 4).

    Examples
    --------
    >>> f = np.linspace(0.0, 500.0, 4001)
    >>> true = DisturbanceModel([[1.9, -0.9025]], [1.0], [[80.0]], [[0.02]], [[0.3]], fs=1000.0)
    >>> fit = fit_disturbance_model(f, true.psd(f), 1000.0, n_vibrations=1)
    >>> round(float(fit.vibration_frequency[0, 0]), 3), round(float(fit.vibration_damping[0, 0]), 4)
    (80.0, 0.02)
    """
    fs = check_positive("fs", fs)
    freqs = check_frequency_grid("freqs", freqs, fs)
    n_vib = check_int("n_vibrations", n_vibrations, minimum=0)
    ratio = check_positive("peak_ratio", peak_ratio)
    if ratio <= 1:
        raise ValueError(f"peak_ratio must be > 1, got {ratio!r}")
    frac = check_positive("min_vibration_fraction", min_vibration_fraction)
    if freqs.size < 8:
        raise ValueError(f"freqs must have at least 8 points to fit a model, got {freqs.size}")
    _finite_rows("psd", psd, (1, 2))
    psd2, noise2, _ = mode_psds(psd, noise_psd, freqs.size)
    noise_level = noise2.mean(axis=1)
    if not np.allclose(noise2, noise_level[:, None], rtol=1e-9, atol=0):
        raise ValueError("noise_psd must be white (one level per mode) for the AR model fit")
    settings = _FitSettings(fs, n_vib, ratio, frac)
    n = psd2.shape[0]
    turb = np.empty((n, 3))
    vf = np.full((n, n_vib), np.nan)
    vd = np.full((n, n_vib), np.nan)
    vv = np.zeros((n, n_vib))
    clipped = []
    items = [(m, psd2[m], float(noise_level[m])) for m in range(n)]
    for mode, ((a1, a2, tv), vibs, clip) in zip(
        range(n), _run_fits(freqs, items, settings, n_jobs), strict=True
    ):
        turb[mode] = a1, a2, tv
        for j, (f0, xi, var) in enumerate(vibs):
            vf[mode, j], vd[mode, j], vv[mode, j] = f0, xi, var
        if clip:
            clipped.append(mode)
    if clipped:
        pos = freqs[freqs > 0]
        warnings.warn(
            f"fit_disturbance_model: the PSD of modes {clipped[:10]}"
            f"{' ...' if len(clipped) > 10 else ''} keeps rising down to the lowest grid "
            f"frequency {pos[0]:.3g} Hz: its AR(2) pole was shrunk to the radius that grid "
            "resolves; the model (and an LQG from it) may be suboptimal there. Use a PSD "
            "resolved at lower frequency (longer Welch segments or a log-spaced grid)",
            UserWarning,
            stacklevel=2,
        )
    return DisturbanceModel(turb[:, :2], turb[:, 2], vf, vd, vv, fs)
