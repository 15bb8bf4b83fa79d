"""Temporal PSD models of modal disturbances: turbulence-like spectra and vibrations.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`. These are
*models* for design and tests (what a user without telemetry starts from); the simulator
produces its own disturbances.

Conventions
-----------
* PSDs are one-sided [nm^2/Hz] (or units^2/Hz): integrated over ``[0, inf)`` (continuous
  models) or over ``[0, fs/2]`` (sampled models, ``fs`` given) they give the variance, the
  convention of ``scipy.signal.welch(..., scaling="density")``.
* Modal coefficients are optical path [nm] of modes orthonormal over the pupil (unit
  coefficient = 1 nm RMS), KL-like ordering: radial order ``n = 1`` (tip, tilt) first, then
  ``n = 2`` (3 modes), ``n = 3`` (4 modes)... (``n + 1`` modes per radial order, as Zernike).
* Outputs are shaped ``(n_modes, n_freqs)``.

Turbulence model (formulas and sources)
---------------------------------------
Modal variance (von Karman, per mode of radial order ``n``), in rad^2 at 500 nm::

    s2_n = 8 pi c (n + 1) pi^(5/3) (D/r0)^(5/3) int_0^inf (x^2 + x0^2)^(-11/6) J_{n+1}(x)^2 / x dx

with ``c = Gamma(11/6)^2 / (2 pi^(11/3)) (24/5 Gamma(6/5))^(5/6) = 0.022896`` (the von
Karman phase spectrum ``c r0^(-5/3) (k^2 + 1/L0^2)^(-11/6)``, ``k`` in cycles/m),
``x = pi D k`` and ``x0 = pi D / L0``. The Zernike filter ``(n+1) [2 J_{n+1}(x)/x]^2`` is
averaged over azimuth (Noll 1976, JOSA 66, 207). For ``L0 = inf`` it reduces to Noll's
closed form ``s2_n = 8 pi c pi^(5/3) Gamma(14/3) / (2^(14/3) Gamma(17/6)^2) (n+1)
Gamma(n - 5/6) / Gamma(n + 23/6) (D/r0)^(5/3)`` (tilt: 0.449 (D/r0)^(5/3) rad^2 per axis).
Converted to nm^2 with ``(500 nm / 2 pi)^2``; ``r0`` is given at 500 nm.

Temporal shape (asymptotes of Conan, Rousset & Madec 1995, JOSA A 12, 1559, single frozen-flow
layer of speed ``V``): cut-off ``f_c = 0.3 (n + 1) V / D``; above it ``f^(-17/3)`` for every
mode; below it ``f^0`` for ``n >= 2`` and ``f^(-2/3)`` for tip/tilt. With a finite outer scale
the tip/tilt ``f^(-2/3)`` flattens below ``f_L = (5/3)^(3/2) V / L0 = 2.15 V / L0`` (where the
Kolmogorov ``f^(-2/3)`` asymptote meets the von Karman plateau of the frozen-flow integral for
``f << f_c``; the ratio of the two integrals is ``2 Gamma(11/6)/Gamma(5/6) = 5/3``). The
asymptotes are joined by smooth broken power laws (``x = f / f_c``)::

    n >= 2 :  h(x) = (1 + x^p)^(-17/(3p))
    n = 1  :  h(x) = (x^2 + x_L^2)^(-1/3) (1 + x^p)^(-5/p),   x_L = f_L / f_c

(sharpness ``p``, default 4; the asymptotes meet at ``x = 1``), each normalised so that its
integral over ``[0, inf)`` is the modal variance. This is a model, not the exact frozen-flow
spectrum: the Bessel ripples are smoothed and the parallel/perpendicular tilt anisotropy is
averaged out. ``wind_speed`` is one effective speed (e.g. the 5/3-weighted mean of a profile).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import integrate, special

from aocontrol._validation import (
    MAX_MODES,
    check_finite_array,
    check_frequency_grid,
    check_in_range,
    check_int,
    check_positive,
    check_psd,
)

__all__ = [
    "radial_orders",
    "modal_variances",
    "synthetic_turbulence_psd",
    "vibration_psd",
    "resonator_ar2",
    "psd_variance",
]

# von Karman / Kolmogorov phase-spectrum constant: c r0^(-5/3) k^(-11/3), k in cycles/m.
_VK_CONSTANT = (
    special.gamma(11 / 6) ** 2
    / (2 * np.pi ** (11 / 3))
    * (24 / 5 * special.gamma(6 / 5)) ** (5 / 6)
)
# Conan et al. (1995) cut-off: f_c = _CUTOFF_FACTOR (n + 1) V / D.
_CUTOFF_FACTOR = 0.3
# f_L = _TILT_OUTER_FACTOR V / L0, see the module docstring.
_TILT_OUTER_FACTOR = (5 / 3) ** 1.5
# Number of aliases folded on each side for a sampled (fs given) spectrum; the f^(-17/3) tail
# beyond 20 fs is below 1e-7 of the variance even for cut-offs at Nyquist.
_N_ALIASES = 20


def radial_orders(n_modes: int) -> np.ndarray:
    """Radial order of each mode in the KL-like ordering, shape ``(n_modes,)``.

    ``n + 1`` modes per radial order, starting at ``n = 1`` (tip, tilt; piston excluded).

    Parameters
    ----------
    n_modes : int
        Number of modes (>= 1).

    Returns
    -------
    numpy.ndarray of int, shape (n_modes,)

    Examples
    --------
    >>> radial_orders(10).tolist()
    [1, 1, 2, 2, 2, 3, 3, 3, 3, 4]
    """
    n_modes = check_int("n_modes", n_modes, minimum=1, maximum=MAX_MODES)
    # Modes before order n: sum_{m=1}^{n-1} (m+1) = (n-1)(n+2)/2; invert for index j.
    j = np.arange(n_modes)
    n = np.floor((-1 + np.sqrt(9 + 8 * j)) / 2).astype(int)
    # Guard rounding at exact triangular numbers.
    n = np.where((n - 1) * (n + 2) // 2 > j, n - 1, n)
    n = np.where(n * (n + 3) // 2 <= j, n + 1, n)
    return n


def _noll_kolmogorov(n: np.ndarray) -> np.ndarray:
    """Noll's Kolmogorov variance per mode of radial order ``n`` [rad^2 per (D/r0)^(5/3)]."""
    n = np.asarray(n, dtype=float)
    const = (
        8
        * np.pi
        * _VK_CONSTANT
        * np.pi ** (5 / 3)
        * special.gamma(14 / 3)
        / (2 ** (14 / 3) * special.gamma(17 / 6) ** 2)
    )
    return const * (n + 1) * np.exp(special.gammaln(n - 5 / 6) - special.gammaln(n + 23 / 6))


def _von_karman_correction(orders: np.ndarray, x0: float) -> np.ndarray:
    """Von Karman minus Kolmogorov variance [rad^2 per (D/r0)^(5/3)] for radial ``orders``.

    ``8 pi c (n+1) pi^(5/3) int [(x^2+x0^2)^(-11/6) - x^(-11/3)] J_{n+1}(x)^2 / x dx``: the
    difference decays as ``x^(-20/3)``, so a finite grid suffices; near 0 the Kolmogorov part
    is integrated analytically on ``[0, eps]``.
    """
    if x0 == 0.0:
        return np.zeros(orders.size)
    return np.array([_vk_correction_one(int(n), float(x0)) for n in orders])


@functools.lru_cache(maxsize=4096)
def _vk_correction_one(n: int, x0: float) -> float:
    eps = 1e-10
    # J_{n+1}(x)^2 peaks near x ~ n; beyond (50 + 3 n) max(1, x0) the difference kernel is
    # below 1e-10 of its value at the peak.
    x_hi = (50.0 + 3.0 * n) * max(1.0, x0)
    # Log grid through the steep part of the kernel (x <~ 8 max(1, x0)), then linear steps of
    # 0.05 (60 per period of J^2): relative error ~1e-5 against adaptive quadrature.
    x_mid = 8.0 * max(1.0, x0)
    x = np.concatenate(
        [
            np.geomspace(eps, x_mid, 3000, endpoint=False),
            np.linspace(x_mid, x_hi, int((x_hi - x_mid) / 0.05) + 1),
        ]
    )
    diff_kernel = (x * x + x0 * x0) ** (-11 / 6) - x ** (-11 / 3)
    val = np.trapezoid(diff_kernel * special.jv(n + 1, x) ** 2 / x, x)
    # Kolmogorov part on [0, eps]: J_{n+1}(x) ~ (x/2)^(n+1)/(n+1)!
    p = 2 * n + 1 - 11 / 3
    small = eps ** (p + 1) / ((p + 1) * 4.0 ** (n + 1) * special.gamma(n + 2) ** 2)
    return float(8 * np.pi * _VK_CONSTANT * np.pi ** (5 / 3) * (n + 1) * (val - small))


def modal_variances(
    n_modes: int,
    *,
    diameter: float = 8.0,
    r0: float = 0.15,
    L0: float = 25.0,
    wavelength_nm: float = 500.0,
) -> np.ndarray:
    """Turbulent variance of each mode [nm^2], KL-like ordering, shape ``(n_modes,)``.

    Zernike variances per radial order (Noll 1976), von Karman corrected for the outer scale
    by numerical integration (formula in the module docstring). Modes of one radial order
    share one variance.

    Parameters
    ----------
    n_modes : int
        Number of modes (tip/tilt first, piston excluded).
    diameter : float, default 8.0
        Telescope diameter [m].
    r0 : float, default 0.15
        Fried parameter [m] at ``wavelength_nm``.
    L0 : float, default 25.0
        Outer scale [m]; ``numpy.inf`` for Kolmogorov.
    wavelength_nm : float, default 500.0
        Wavelength at which ``r0`` is given [nm] (sets the rad -> nm conversion).

    Returns
    -------
    ndarray, shape (n_modes,)
        Variances [nm^2 of optical path], non-increasing.

    Examples
    --------
    >>> v = modal_variances(2, diameter=8.0, r0=0.15, L0=np.inf)
    >>> # Noll: tilt variance 0.449 (D/r0)^(5/3) rad^2 at 500 nm -> nm^2
    >>> round(float(v[0] / (0.4489 * (8 / 0.15) ** (5 / 3) * (500 / (2 * np.pi)) ** 2)), 3)
    1.0
    """
    n_modes = check_int("n_modes", n_modes, minimum=1, maximum=MAX_MODES)
    diameter = check_positive("diameter", diameter)
    r0 = check_positive("r0", r0)
    L0 = _check_outer_scale(L0)
    wavelength_nm = check_positive("wavelength_nm", wavelength_nm)
    orders = radial_orders(n_modes)
    unique = np.unique(orders)
    x0 = 0.0 if np.isinf(L0) else np.pi * diameter / L0
    per_order = _noll_kolmogorov(unique) + _von_karman_correction(unique, x0)
    rad2 = per_order * (diameter / r0) ** (5 / 3)
    nm2 = rad2 * (wavelength_nm / (2 * np.pi)) ** 2
    return nm2[np.searchsorted(unique, orders)]


def _check_outer_scale(L0: object) -> float:
    if (
        isinstance(L0, (int, float, np.floating))
        and not isinstance(L0, bool)
        and float(L0) == np.inf
    ):
        return np.inf
    return check_positive("L0", L0)


def _shape(x: np.ndarray, tilt: bool, x_l: float, p: float) -> np.ndarray:
    """Unnormalised broken power law ``h(x)``, ``x = f / f_c`` (see module docstring)."""
    if tilt:
        with np.errstate(divide="ignore"):
            return (x * x + x_l * x_l) ** (-1 / 3) * (1 + x**p) ** (-5 / p)
    return (1 + x**p) ** (-17 / (3 * p))


def _shape_integral(tilt: bool, x_l: float, p: float) -> float:
    """``int_0^inf h(x) dx``: closed form for n >= 2, quadrature for tip/tilt."""
    if not tilt:
        # int (1 + x^p)^(-q) dx = B(1/p, q - 1/p) / p with q = 17/(3p).
        q = 17 / (3 * p)
        return float(special.beta(1 / p, q - 1 / p) / p)
    pieces = [0.0, min(x_l, 1.0), 1.0, 10.0, np.inf] if x_l > 0 else [0.0, 1.0, 10.0, np.inf]
    total = 0.0
    for lo, hi in zip(pieces[:-1], pieces[1:], strict=True):
        if hi > lo:
            val, _ = integrate.quad(
                lambda t: float(_shape(np.array(t), True, x_l, p)),
                lo,
                hi,
                limit=200,
                epsabs=0.0,
                epsrel=1e-11,
            )
            total += val
    return total


def synthetic_turbulence_psd(
    freqs: object,
    n_modes: int,
    *,
    diameter: float = 8.0,
    wind_speed: float = 10.0,
    r0: float = 0.15,
    L0: float = 25.0,
    wavelength_nm: float = 500.0,
    sharpness: float = 4.0,
    fs: float | None = None,
) -> np.ndarray:
    """Turbulence-like modal temporal PSDs [nm^2/Hz], one-sided, shape ``(n_modes, n_freqs)``.

    Mode ``j`` of radial order ``n`` (KL-like ordering, :func:`radial_orders`) has the
    variance of :func:`modal_variances` spread over a broken power law with cut-off
    ``f_c = 0.3 (n + 1) V / D`` (Conan et al. 1995): flat (``n >= 2``) or ``f^(-2/3)``
    (tip/tilt, flattening below ``2.15 V / L0``) below ``f_c``, ``f^(-17/3)`` above. Formulas
    and sources in the module docstring.

    Parameters
    ----------
    freqs : array_like, shape (n_freqs,)
        Strictly increasing frequencies [Hz], >= 0 (> 0 if ``L0 = inf``: the Kolmogorov tilt
        spectrum diverges at 0). With ``fs``, within ``[0, fs/2]``.
    n_modes : int
        Number of modes.
    diameter : float, default 8.0
        Telescope diameter ``D`` [m].
    wind_speed : float, default 10.0
        Effective wind speed ``V`` [m/s].
    r0 : float, default 0.15
        Fried parameter [m] at ``wavelength_nm``.
    L0 : float, default 25.0
        Outer scale [m]; ``numpy.inf`` for Kolmogorov.
    wavelength_nm : float, default 500.0
        Wavelength of ``r0`` [nm].
    sharpness : float, default 4.0
        Exponent ``p`` of the broken power laws (larger: sharper knee at ``f_c``), >= 1.
    fs : float, optional
        Sampling rate [Hz]. If given, the spectrum is that of the disturbance sampled at
        ``fs`` (aliases folded onto ``[0, fs/2]``, 20 on each side), so that its integral
        over ``[0, fs/2]`` is the modal variance. If omitted, the continuous-time one-sided
        PSD (integral over ``[0, inf)`` is the variance).

    Returns
    -------
    ndarray, shape (n_modes, n_freqs)
        One-sided PSD [nm^2/Hz].

    Raises
    ------
    ValueError
        Non-increasing or negative ``freqs``, ``freqs`` beyond ``fs/2``, a zero frequency
        with ``L0 = inf``, or non-positive physical parameters.

    Examples
    --------
    >>> f = np.linspace(0.0, 500.0, 50001)
    >>> psd = synthetic_turbulence_psd(f, 5, fs=1000.0)
    >>> var = np.trapezoid(psd, f, axis=-1)
    >>> bool(np.allclose(var, modal_variances(5), rtol=1e-3))
    True
    """
    n_modes = check_int("n_modes", n_modes, minimum=1, maximum=MAX_MODES)
    diameter = check_positive("diameter", diameter)
    wind_speed = check_positive("wind_speed", wind_speed)
    r0 = check_positive("r0", r0)
    L0 = _check_outer_scale(L0)
    sharpness = check_in_range("sharpness", sharpness, 1.0, 64.0, high_inclusive=True)
    if fs is None:
        freqs = check_frequency_grid("freqs", freqs, np.inf)
    else:
        fs = check_positive("fs", fs)
        freqs = check_frequency_grid("freqs", freqs, fs)
    if np.isinf(L0) and freqs[0] == 0.0:
        raise ValueError(
            "freqs must be > 0 Hz when L0 = inf (the Kolmogorov tip/tilt PSD "
            f"diverges at 0), got freqs[0]={freqs[0]!r}"
        )
    variances = modal_variances(
        n_modes, diameter=diameter, r0=r0, L0=L0, wavelength_nm=wavelength_nm
    )
    orders = radial_orders(n_modes)
    unique = np.unique(orders)
    f_l = 0.0 if np.isinf(L0) else _TILT_OUTER_FACTOR * wind_speed / L0
    if fs is None:
        fgrid = freqs[None, :]
    else:
        k = np.arange(-_N_ALIASES, _N_ALIASES + 1)[:, None]
        fgrid = np.abs(freqs[None, :] + k * fs)
    per_order = np.empty((unique.size, freqs.size))
    for i, n in enumerate(unique):
        f_c = _CUTOFF_FACTOR * (n + 1) * wind_speed / diameter
        tilt = n == 1
        x_l = f_l / f_c
        norm = f_c * _shape_integral(tilt, x_l, sharpness)
        # One-sided: the continuous PSD on [0, inf) integrates to 1 after normalisation.
        per_order[i] = _shape(fgrid / f_c, tilt, x_l, sharpness).sum(axis=0) / norm
    return variances[:, None] * per_order[np.searchsorted(unique, orders)]


def resonator_ar2(frequency: float, damping: float, fs: float) -> tuple[float, float]:
    """AR(2) coefficients ``(a1, a2)`` of a sampled damped resonator.

    ``x[k] = a1 x[k-1] + a2 x[k-2] + w[k]`` with poles ``r exp(+-j theta)``,
    ``r = exp(-damping 2 pi f0 / fs)``, ``theta = 2 pi f0 sqrt(1 - damping^2) / fs``
    (impulse-invariant map of the continuous poles): ``a1 = 2 r cos(theta)``, ``a2 = -r^2``.

    Parameters
    ----------
    frequency : float
        Natural frequency ``f0`` [Hz], in ``(0, fs/2)``.
    damping : float
        Damping ratio in ``(0, 1)``.
    fs : float
        Sampling rate [Hz].
    """
    fs = check_positive("fs", fs)
    f0 = check_in_range("frequency", frequency, 0.0, fs / 2, low_inclusive=False)
    zeta = check_in_range("damping", damping, 0.0, 1.0, low_inclusive=False)
    w0 = 2 * np.pi * f0 / fs
    r = np.exp(-zeta * w0)
    theta = w0 * np.sqrt(1 - zeta * zeta)
    return float(2 * r * np.cos(theta)), float(-r * r)


def vibration_psd(
    freqs: object, frequency: float, variance: float, damping: float, *, fs: float | None = None
) -> np.ndarray:
    """One-sided PSD [units^2/Hz] of a vibration: a white-noise-driven damped resonator.

    Continuous (``fs`` omitted): the second-order resonator ``1/(s^2 + 2 zeta w0 s + w0^2)``,
    normalised to ``variance``::

        P(f) = variance * 4 zeta f0^3 / (pi ((f0^2 - f^2)^2 + (2 zeta f0 f)^2))

    since ``int_0^inf df / ((f0^2 - f^2)^2 + (2 zeta f0 f)^2) = pi / (4 zeta f0^3)``.
    Its peak at ``f0`` has a half-power width ``~ 2 zeta f0``.

    Sampled (``fs`` given): the AR(2) process of :func:`resonator_ar2`,
    ``P(f) = (2 s_w^2 / fs) / |1 - a1 e^{-jw} - a2 e^{-2jw}|^2`` with ``w = 2 pi f / fs`` and
    the driving variance ``s_w^2`` set so that the process variance
    ``s_w^2 (1 - a2) / ((1 + a2) ((1 - a2)^2 - a1^2))`` is ``variance``: the integral over
    ``[0, fs/2]`` is exactly ``variance``.

    Parameters
    ----------
    freqs : array_like, shape (n_freqs,)
        Strictly increasing frequencies [Hz], >= 0 (within ``[0, fs/2]`` with ``fs``).
    frequency : float
        Resonance frequency ``f0`` [Hz], > 0 (``< fs/2`` with ``fs``).
    variance : float
        Vibration variance [units^2], >= 0.
    damping : float
        Damping ratio ``zeta`` in ``(0, 1)`` (typical telescope vibrations: 0.001 - 0.05).
    fs : float, optional
        Sampling rate [Hz] for the AR(2) form.

    Returns
    -------
    ndarray, shape (n_freqs,)

    Examples
    --------
    >>> f = np.linspace(0.0, 500.0, 200001)
    >>> p = vibration_psd(f, 50.0, 4.0, 0.01, fs=1000.0)
    >>> round(float(np.trapezoid(p, f)), 4)
    4.0
    """
    variance = float(check_finite_array("variance", variance, ndim=0))
    if variance < 0:
        raise ValueError(f"variance must be >= 0, got {variance!r}")
    zeta = check_in_range("damping", damping, 0.0, 1.0, low_inclusive=False)
    if fs is None:
        f0 = check_positive("frequency", frequency)
        freqs = check_frequency_grid("freqs", freqs, np.inf)
        den = (f0 * f0 - freqs * freqs) ** 2 + (2 * zeta * f0 * freqs) ** 2
        return variance * 4 * zeta * f0**3 / (np.pi * den)
    fs = check_positive("fs", fs)
    freqs = check_frequency_grid("freqs", freqs, fs)
    a1, a2 = resonator_ar2(frequency, zeta, fs)
    s_w2 = variance * (1 + a2) * ((1 - a2) ** 2 - a1 * a1) / (1 - a2)
    zi = np.exp(-2j * np.pi * freqs / fs)
    return 2 * s_w2 / fs / np.abs(1 - a1 * zi - a2 * zi * zi) ** 2


def psd_variance(freqs: object, psd: object) -> np.ndarray:
    """Variance [units^2] of one-sided PSDs: trapezoid over the last axis of ``psd``.

    Parameters
    ----------
    freqs : array_like, shape (n_freqs,)
        Increasing frequencies [Hz].
    psd : array_like, shape (..., n_freqs)
        One-sided PSD [units^2/Hz], >= 0.

    Raises
    ------
    ValueError
        A negative or non-finite PSD, or a last axis that is not ``n_freqs`` long.
    """
    freqs = check_frequency_grid("freqs", freqs, np.inf)
    psd = check_psd("psd", psd, freqs.size, ndim=None)
    return np.trapezoid(psd, freqs, axis=-1)
