"""Start candidates of the data-driven synthesis: the margin-constrained bound, reduced (private).

Private module of :mod:`aocontrol.synthesis._datadriven`. On resonant spectra the
convex-concave iterations stop in a local optimum far from the margin-constrained bound
(:func:`aocontrol.analysis.constrained_bound`) when started from an integrator
(``benchmarks/bench_synthesis.py`` part (f), ``docs/benchmarks.md``). The bound's own
controller, ``K_b = Q / (1 - G Q)`` with an FIR Youla parameter ``Q`` of a few hundred taps,
has a stable closed loop but, in general, unstable poles of its own, so it is not a start.
Its sensitivity ``S_b = 1 - G Q`` is a
target instead: a controller ``K = X / Y`` of the design's order (``Y = F Y'``, ``F`` the
fixed factor, ``Y'`` monic) whose sensitivity ``Y / (Y + G X)`` matches ``S_b`` is fitted by
Sanathanan-Koerner iterations (each a linear least-squares problem),

    min_{X, Y'}  sum_j  w_j |Y_j (1 - S_b,j) - S_b,j G_j X_j|^2 / |P_j^(k-1)|^2,

``w_j = tw_j (psd_j + noise_j)`` (the trapezoid weights of the input grid times what the
residual weighs: near the bound, the excess residual is about ``sum w |S - S_b|^2``) and
``P^(k-1)`` the previous iterate's ``Y + G X``. The free poles of the fit (roots of ``Y'``)
outside the radius are then reflected inside the unit circle (``p -> 1 / conj(p)``) and
pulled inside the radius, and ``X`` is fitted again with ``Y`` fixed (the same iterations,
``X`` only): the pole flip of vector fitting.

Nothing here certifies: the synthesis takes such a start only if it passes every
certificate of the design (exact modulus margin over the whole circle, closed-loop stability,
pole radius) and has a lower objective than the other starts (see
:func:`aocontrol.synthesis._dd_mode._design_mode`).
"""

from __future__ import annotations

import logging

import control
import numpy as np
from scipy.ndimage import median_filter
from scipy.signal import find_peaks

from aocontrol.plant import z_inverse_coefficients

logger = logging.getLogger(__name__)

#: FIR length of the Youla parameter of the bound used as the fit's target. Measured on the
#: 6 resonant modes of bench_synthesis part (f) (one thread, loaded machine): the reduced
#: starts at order 5 are 1.03-1.10 times the 256-tap bound from a 128-tap target (0.4 s CPU
#: per mode: the unconstrained FIR already meets the margin) and 1.03-1.06 from a 256-tap
#: target (about 5 s per mode: cutting-plane solves); 64 taps give 1.11-1.25.
BOUND_TAPS = 256
# Sanathanan-Koerner iterations of the fit (each one least-squares problem); measured: the
# residual of the fit stops changing after 5 to 10.
_SK_ITERATIONS = 12
# The reflected poles are pulled this fraction inside the radius (strictly inside, as the
# default start: the convexified radius constraint needs the scaled denominator nonzero on
# the circle).
_RADIUS_MARGIN = 1e-3
#: A line (``has_lines``): the PSD this many decades above its running median over
#: +-LINE_WINDOW_DECADES in log-frequency (the design grid's peak prominence, 0.5, too).
#: The window is 3.5x a damping-0.05 line's half-power width (0.043 decades) on each side.
LINE_DECADES = 0.5
LINE_WINDOW_DECADES = 0.15
_LINE_PER_DECADE = 100
# ... and this many times the row's scatter around its running median (an estimated PSD).
_LINE_SCATTER = 5.0
# has_lines(model=True): every local maximum of the PSD at least this far above the running
# median (a secondary line; an estimate's scatter leaves maxima at a few 0.01 decades).
_MODEL_PEAK_DECADES = 0.1


def _line_excess(freqs: np.ndarray, psd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``log10(psd)`` minus its running median in log-frequency, on ``freqs > 0``.

    The running median is over ``+-LINE_WINDOW_DECADES``, on a uniform log-frequency grid of
    ``_LINE_PER_DECADE`` points per decade (linear interpolation both ways, all modes at
    once; ``scipy.ndimage.median_filter``). It follows turbulence (a monotone stretch is its
    own running median) and ignores a line narrower than the window. Returns the excess
    [decades], shape ``(n_modes, n_pos)``, and ``log10(psd)`` there.
    """
    pos = freqs > 0
    # The design grid's floor (_design_indices): 30 decades below each row's maximum.
    logp = np.log10(np.maximum(psd, 1e-300 + psd.max(axis=-1, keepdims=True) * 1e-30))[:, pos]
    lf = np.log10(freqs[pos])
    u = np.linspace(lf[0], lf[-1], max(int(np.ceil((lf[-1] - lf[0]) * _LINE_PER_DECADE)) + 1, 3))
    half = int(round(LINE_WINDOW_DECADES * _LINE_PER_DECADE))
    j = np.clip(np.searchsorted(lf, u, side="right") - 1, 0, lf.size - 2)
    t = np.clip((u - lf[j]) / (lf[j + 1] - lf[j]), 0.0, 1.0)
    level = median_filter(
        logp[:, j] * (1 - t) + logp[:, j + 1] * t, size=(1, 2 * half + 1), mode="nearest"
    )
    k = np.clip(np.searchsorted(u, lf, side="right") - 1, 0, u.size - 2)
    s = np.clip((lf - u[k]) / (u[k + 1] - u[k]), 0.0, 1.0)
    return logp - (level[:, k] * (1 - s) + level[:, k + 1] * s), logp


def has_lines(freqs: np.ndarray, psd: np.ndarray, *, model: bool = False) -> np.ndarray:
    """Modes whose PSD has a line: a narrow peak ``LINE_DECADES`` above its running median.

    Parameters
    ----------
    freqs : ndarray, shape (n_freqs,)
        Input grid [Hz] (increasing; a point at 0 Hz is ignored).
    psd : ndarray, shape (n_modes, n_freqs)
        One-sided PSD [units^2/Hz].
    model : bool, default False
        Only rows that look like a model (turbulence plus lines): every local maximum of the
        PSD at least ``_MODEL_PEAK_DECADES`` above the running median, and so are the two
        bins beside the highest one (a line's skirt). An estimated PSD (Welch scatter; noise
        subtracted, detected bins kept among averaged ones by
        :func:`aocontrol.synthesis.disturbance_from_telemetry`) has tens of local maxima
        and isolated bins decades above their neighbours. A line narrower than the grid's
        spacing fails the skirt test (the disturbance-plus-noise test still sees it above
        the noise).

    Returns
    -------
    ndarray of bool, shape (n_modes,)
        The highest excess over the running median (``_line_excess``) is at least
        ``LINE_DECADES`` and ``_LINE_SCATTER`` times the row's scatter around that median
        (1.4826 times the median absolute deviation: a Welch estimate's).

    Notes
    -----
    Which modes it selects on the benchmark's resonant and turbulence banks and on modes
    estimated from telemetry: ``docs/benchmarks.md``.
    """
    psd = np.atleast_2d(psd)
    out = np.zeros(psd.shape[0], dtype=bool)
    # A line is a local maximum: rows without one (a turbulence model) are not filtered.
    d = np.diff(psd[:, freqs > 0], axis=-1)
    rows = np.flatnonzero(np.any((d[:, :-1] > 0) & (d[:, 1:] <= 0), axis=-1))
    if np.count_nonzero(freqs > 0) < 3 or not rows.size:
        return out
    excess, logp = _line_excess(freqs, psd[rows])
    scatter = 1.4826 * np.median(np.abs(excess), axis=-1)
    found = excess.max(axis=-1) >= np.maximum(LINE_DECADES, _LINE_SCATTER * scatter)
    if model:
        for i in np.flatnonzero(found):
            peaks = find_peaks(logp[i])[0]
            top = int(np.argmax(excess[i]))
            skirt = excess[i, max(top - 1, 0) : top + 2]
            found[i] = bool(
                np.all(excess[i, peaks] >= _MODEL_PEAK_DECADES)
                and np.all(skirt >= _MODEL_PEAK_DECADES)
            )
    out[rows] = found
    return out


def bound_sensitivities(
    plant: object,
    freqs: np.ndarray,
    psd: np.ndarray,
    noise: np.ndarray,
    mu: float,
    n_taps: int | None = None,
) -> list:
    """``S_b = 1 - G Q`` of the margin-constrained bound on ``freqs``, per mode (str: failed).

    Parameters
    ----------
    plant : control.TransferFunction
        Stable discrete plant.
    freqs : ndarray, shape (n_freqs,)
        Input grid [Hz].
    psd, noise : ndarray, shape (n_modes, n_freqs)
        Disturbance and noise PSDs, one-sided [units^2/Hz].
    mu : float
        Modulus margin of the bound.
    n_taps : int, optional
        FIR length of ``Q`` (default ``BOUND_TAPS``).

    Returns
    -------
    list of (ndarray of complex, shape (n_freqs,)) or str
        Per mode, ``S_b``, or the bound's failure message (a ``str``) for a mode it failed.
    """
    from aocontrol.analysis import constrained_bound
    from aocontrol.plant import frequency_response

    n_taps = BOUND_TAPS if n_taps is None else n_taps
    res = constrained_bound(plant, freqs, psd, noise, mu, n_taps=n_taps, raise_on_failure=False)
    fs = res.fs
    g = frequency_response(plant, freqs, fs)
    w = np.exp(-2j * np.pi * freqs / fs)
    out = []
    for i in range(psd.shape[0]):
        if not res.ok[i]:
            logger.debug("bound start: the bound failed for a mode (%s)", res.messages[i])
            out.append(res.messages[i] or "failed")
            continue
        out.append(1.0 - g * np.polyval(res.q[i][::-1], w))
    return out


def _lstsq(A: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Real least squares of the complex system ``A x ~ rhs``."""
    return np.linalg.lstsq(
        np.vstack([A.real, A.imag]), np.concatenate([rhs.real, rhs.imag]), rcond=None
    )[0]


def reduced_start(
    s_target: np.ndarray,
    w: np.ndarray,
    g: np.ndarray,
    weight: np.ndarray,
    nq: int,
    fixed: np.ndarray,
    radius: float | None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """A controller of the design's structure whose sensitivity fits ``s_target``.

    Parameters
    ----------
    s_target : ndarray of complex, shape (n,)
        Target sensitivity on the grid.
    w : ndarray of complex, shape (n,)
        ``z^-1`` on the grid (``exp(-2j pi f / fs)``).
    g : ndarray of complex, shape (n,)
        Plant response on the grid.
    weight : ndarray, shape (n,)
        Nonnegative fit weights (trapezoid weight times disturbance plus noise PSD).
    nq : int
        Free coefficients: ``X`` has ``nq + 1``, ``Y'`` has ``nq`` (monic).
    fixed : ndarray, shape (m,)
        Fixed factor ``F`` of the denominator (powers of ``z^-1``, ``F[0] = 1``).
    radius : float or None
        The free poles end inside ``radius * (1 - _RADIUS_MARGIN)`` (None: inside the unit
        circle's reflection only).

    Returns
    -------
    (b, a) or None
        Numerator and denominator in powers of ``z^-1`` (``a = F Y'``), or None if the fit
        is not finite.
    """
    pp = np.polynomial.polynomial
    sw = np.sqrt(np.maximum(weight, 0.0))
    powers = w[:, None] ** np.arange(nq + 1)
    F = pp.polyval(w, fixed)
    Ax_base = -(s_target * g)[:, None] * powers
    p_prev = np.ones_like(w)
    with np.errstate(all="ignore"):
        # (1) X and Y' together.
        for _ in range(_SK_ITERATIONS):
            scale = sw / np.maximum(np.abs(p_prev), 1e-300)
            Ay = (F * (1.0 - s_target))[:, None] * powers[:, 1:]
            A = np.hstack([Ax_base, Ay]) * scale[:, None]
            sol = _lstsq(A, -(F * (1.0 - s_target)) * scale)
            x, y = sol[: nq + 1], sol[nq + 1 :]
            Y = F * pp.polyval(w, np.concatenate([[1.0], y]))
            p_prev = Y + g * pp.polyval(w, x)
        if not np.all(np.isfinite(sol)):
            return None
        # (2) The free poles inside the unit circle (reflected) and inside the radius.
        if nq:
            poles = np.roots(np.concatenate([[1.0], y]))
            poles = np.where(np.abs(poles) > 1.0, 1.0 / np.conj(poles), poles)
            limit = (1.0 if radius is None else radius) * (1.0 - _RADIUS_MARGIN)
            mag = np.abs(poles)
            poles = np.where(mag > limit, poles / np.maximum(mag, 1e-300) * limit, poles)
            y = np.real(np.poly(poles))[1:]
        a = pp.polymul(fixed, np.concatenate([[1.0], y]))
        Y = pp.polyval(w, a)
        # (3) X again with Y fixed.
        p_prev = np.ones_like(w)
        for _ in range(_SK_ITERATIONS):
            scale = sw / np.maximum(np.abs(p_prev), 1e-300)
            x = _lstsq(Ax_base * scale[:, None], -(Y * (1.0 - s_target)) * scale)
            p_prev = Y + g * pp.polyval(w, x)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(a))):
        return None
    return x, a


def bound_candidate(ctx, g: np.ndarray, psd, noise, target) -> tuple | None:
    """The reduced bound start at the order and fixed factor of ``ctx`` (None: no target).

    ``ctx`` is the :class:`~aocontrol.synthesis._dd_context.DesignContext` (its input grid
    and weights, free order, fixed factor and pole radius), ``g`` the plant on the input grid and
    ``target`` the bound's sensitivity there (:func:`bound_sensitivities`).
    """
    if target is None:
        return None
    w = np.exp(-2j * np.pi * ctx.input_freqs / ctx.fs)
    weight = ctx.input_weights * (psd + noise)
    return reduced_start(
        target, w, g, weight, ctx.free_order, ctx.fixed_factor, ctx.max_pole_radius
    )


def bound_start_modes(
    bound_start: object, plant: object, freqs: np.ndarray, psd: np.ndarray, noise: np.ndarray
) -> np.ndarray:
    """Modes that get the reduced-bound start candidate (``datadriven``'s ``bound_start``).

    ``psd`` and ``noise`` are the disturbance and noise PSDs on ``freqs``, shape
    ``(n_modes, n_freqs)``. With ``bound_start=None``: the modes with a line
    (:func:`has_lines`) in the disturbance PSD, or in disturbance plus noise (an estimated
    disturbance, noise subtracted and clipped to a floor, scatters too much below the noise
    for the first test; a line above the noise still shows in the second).
    """
    if bound_start is not None and not isinstance(bound_start, (bool, np.bool_)):
        raise TypeError(f"bound_start must be True, False or None, got {bound_start!r}")
    n_modes = psd.shape[0]
    if bound_start is False:
        return np.zeros(n_modes, dtype=bool)
    is_tf = isinstance(plant, control.TransferFunction)
    usable = is_tf
    if is_tf:
        _, ag = z_inverse_coefficients(plant, "plant")
        ag = np.trim_zeros(ag, "b")
        usable = ag.size == 1 or bool(np.max(np.abs(np.roots(ag))) < 1.0)
    if bound_start:
        if not usable:
            what = "a plant with a pole on or outside the unit circle" if is_tf else "a control.FRD"
            raise ValueError(
                "bound_start=True needs a stable transfer-function plant (the bound's Youla "
                f"parametrisation K = Q / (1 - G Q)), got {what}"
            )
        return np.ones(n_modes, dtype=bool)
    if not usable:
        return np.zeros(n_modes, dtype=bool)
    return has_lines(freqs, psd, model=True) | has_lines(freqs, psd + noise)


def bound_targets(ctx, items: list, mu_d: float) -> tuple[list, list]:
    """The bound's sensitivity on the input grid for the items asking for it (else None), and
    why it is missing for an item that asked (else "").

    One :func:`aocontrol.analysis.constrained_bound` call for the chunk's modes (its problem
    compiled once), with the design grid's margin ``mu_d`` (a little above the margin), so the
    reduced start keeps some room for the design grid's margin. A failure of the bound leaves
    the modes with their other starts; the reason goes to the mode's report
    (:attr:`ModeReport.bound_start_error`).
    """
    asked = [k for k, item in enumerate(items) if item.bound_start]
    out: list = [None] * len(items)
    why: list = [""] * len(items)
    if not asked:
        return out, why
    psd = np.array([items[k].psd for k in asked])
    noise = np.array([items[k].noise for k in asked])
    try:
        found = bound_sensitivities(ctx.plant, ctx.input_freqs, psd, noise, mu_d)
    except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
        logger.warning("bound start: constrained_bound failed (%s); not used", exc)
        for k in asked:
            why[k] = f"constrained_bound failed: {exc}"
        return out, why
    for k, s_b in zip(asked, found, strict=True):
        if isinstance(s_b, str):
            why[k] = f"constrained_bound failed: {s_b}"
        else:
            out[k] = s_b
    return out, why


def start_certified(ctx, cert, dense, v: np.ndarray) -> bool:
    """A start candidate ``v`` passes every certificate (margin, stability, pole radius, peaks).

    ``cert`` is the mode's certifier (``_ModeCertifier``), ``dense`` its dense grid's data.

    Besides the certificates of the iterations (``cert.check``), the margin is also checked on
    the dense grid: a second, independent test for a start that did not come from the
    iterations (the stationary-point certificate can miss a dip when controller poles crowd
    near ``z = 1``; this test refuses such a start where the dip is below the margin on the
    grid).
    """
    if not cert.check(v).ok:
        return False
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = np.abs(dense.A @ v + dense.F) >= ctx.modulus_margin * np.abs(dense.AY @ v + dense.F)
    return bool(np.all(ok))
