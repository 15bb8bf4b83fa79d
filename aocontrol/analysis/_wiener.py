"""Wiener bound: the smallest residual variance of any causal linear controller.

Also the shared PSD-pair validation :func:`mode_psds` used by the synthesis routines.
PSDs are one-sided [units^2/Hz]: integrated over [0, fs/2] they give the variance.
"""

from __future__ import annotations

import warnings

import control
import numpy as np
import scipy.fft

from aocontrol._validation import check_frequency_grid, check_int, mode_psds
from aocontrol.plant import (
    check_frd_coverage,
    frequency_response,
    plant_fs,
    z_inverse_coefficients,
)

__all__ = ["mode_psds", "wiener_bound"]


# Default size of the full-circle FFT grid (frequency step fs / n_fft).
_N_FFT = 2**15
#: Largest accepted ``n_fft``: the bound is computed on n_fft and 2 n_fft points, with
#: (modes x points) complex arrays; 2**22 resolves a resonance damping of 1e-6 fs already.
MAX_N_FFT = 2**22
# PSDs are floored at this fraction of their maximum before taking logarithms (the cepstral
# factorisation needs a PSD > 0 everywhere).
_PSD_FLOOR = 1e-14
# Plant zeros with |z| > 1 + _ZERO_TOL are non-minimum phase (moved to the inner factor).
_ZERO_TOL = 1e-9
# Largest number of (mode x grid point) values processed at once: memory, and speed (8 modes
# of the 2**16-point grid keep each temporary within a few MB, in cache: 2**22 was 20 %
# slower on 540 modes). A mode's bound does not depend on it.
_CHUNK = 2**19
# Relative change of the bound between n_fft and 2 n_fft above which the PSD grid is
# declared too coarse (a resolved PSD changes by < 1e-6; an unresolved tip PSD by 100x).
_RESOLUTION_TOL = 0.02
# Largest FFT size the unresolved modes are refined to by default (fs / 2**20 = 3 mHz at
# 3 kHz: resolves sub-hertz tip/tilt of a few seconds of telemetry; about 1 s per mode).
_MAX_REFINED_N_FFT = 2**20


def _minimum_phase_log(log_mag2: np.ndarray, n: int) -> np.ndarray:
    """Log of the minimum-phase factor ``M`` with ``|M|^2 = exp(log_mag2)``, on the half circle.

    ``log_mag2`` is real and even, sampled at ``theta_k = 2 pi k / n`` for ``k = 0 .. n/2``
    (last axis, ``n`` even); so is the result's modulus, and ``log M`` is Hermitian, so the
    half circle holds all of it. Cepstral method: with ``c = ifft(log |M|^2)`` over the full
    circle (coefficients of ``e^{-j m theta}``, real and even: a DCT-I of the half), ``log M``
    keeps ``c_0 / 2``, ``c_m`` for ``0 < m < n/2`` and ``c_{n/2} / 2``; its values on the half
    circle are the first ``n/2 + 1`` of that sequence's real FFT.
    """
    h = n // 2
    c = scipy.fft.dct(log_mag2, type=1, axis=-1) / n
    c[..., 0] /= 2
    c[..., h] /= 2
    return scipy.fft.rfft(c, n=n, axis=-1)


def _inner_factor(plant: object, n: int, fs: float) -> np.ndarray:
    """Inner (all-pass) factor ``G_i`` of a stable plant on ``theta_k = 2 pi k / n``,
    ``k = 0 .. n/2`` (the half circle: ``G_i`` is Hermitian, its coefficients real).

    Transfer function: exact. ``G = z^-D B(z) / A(z)``; every zero ``zeta`` of ``B`` outside
    the unit circle contributes the Blaschke factor
    ``(1 - zeta z^-1) / (|zeta| (1 - z^-1 / conj(zeta)))``: ``G_i = z^-D prod(...)``.
    FRD: ``G / G_o`` with ``G_o`` the cepstral minimum-phase factor of ``|G|``.
    """
    theta = 2 * np.pi * np.arange(n // 2 + 1) / n
    zi = np.exp(-1j * theta)
    if isinstance(plant, control.TransferFunction):
        b, a = z_inverse_coefficients(plant, "plant")
        poles = np.roots(np.trim_zeros(a, "b")) if np.trim_zeros(a, "b").size > 1 else []
        if np.size(poles) and np.max(np.abs(poles)) >= 1.0:
            raise ValueError(
                "plant must be stable (the Wiener bound uses the Youla parametrisation of a "
                f"stable plant), got a pole of modulus {np.max(np.abs(poles))!r}"
            )
        scale = np.max(np.abs(b))
        if scale == 0:
            raise ValueError("plant must not be identically zero")
        nz = np.flatnonzero(np.abs(b) > 1e-14 * scale)
        delay, b = int(nz[0]), np.trim_zeros(b[nz[0] :], "b")
        out = zi**delay
        for zeta in np.roots(b) if b.size > 1 else []:
            if abs(zeta) > 1.0 + _ZERO_TOL:
                out = out * (1 - zeta * zi) / (abs(zeta) * (1 - zi / np.conj(zeta)))
        return out
    half = theta * fs / (2 * np.pi)
    try:
        g = frequency_response(plant, np.clip(half, 0.0, fs / 2), fs)
    except ValueError as exc:
        raise ValueError(
            f"a measured (FRD) plant must cover [0, fs/2] for the Wiener bound: {exc}"
        ) from exc
    mag = np.abs(g)
    log_m2 = 2 * np.log(np.maximum(mag, _PSD_FLOOR * mag.max()))
    return g / np.exp(_minimum_phase_log(log_m2, n))


def wiener_bound(
    plant: object,
    freqs: object,
    psd: object,
    noise_psd: object = 0.0,
    *,
    fs: float | None = None,
    n_fft: int = _N_FFT,
    max_n_fft: int | None = None,
) -> float | np.ndarray:
    """Smallest residual variance any causal linear controller can reach [units^2].

    For a stable plant ``G``, every stabilising controller is ``K = Q / (1 - G Q)`` with
    ``Q`` stable and causal (Youla), and the residual is ``e = (1 - G Q) d - G Q n`` up to a
    unit-modulus delay on the noise path. This returns, per mode,

        min_Q E[e^2] = int Sd Sn / (Sd + Sn) + || [conj(G_i) Sd / conj(M)]_- ||^2

    (Wiener-Hopf; ``|M|^2 = Sd + Sn`` with ``M`` minimum phase, ``G = G_i G_o`` the
    inner-outer factorisation, ``[.]_-`` the strictly anticausal part). With no noise and an
    integer delay ``d`` this is the ``d``-step prediction error of the disturbance
    (``s_w^2 (1 - a^(2d)) / (1 - a^2)`` for an AR(1)); for white disturbance it is its variance.

    The delay is handled exactly: ``loop_plant`` has ``G = z^-(k+1) ((1-f) + f z^-1)``; for
    ``f < 0.5`` the interpolation factor is minimum phase (no cost beyond the ``k + 1``
    frames), for ``f > 0.5`` its zero ``-f/(1-f)`` lies outside the unit circle and the
    all-pass ``((1-f) + f z^-1) / (f + (1-f) z^-1)`` joins the inner factor (it costs extra).
    For any stable TF plant, every zero outside the unit circle is treated that way; for an
    FRD plant the inner factor is ``G / G_o`` with ``G_o`` the cepstral minimum-phase factor
    of ``|G|`` (the FRD must cover ``[0, fs/2]``).

    Numerics and assumptions:

    * ``d`` and ``n`` are independent, zero-mean, stationary; PSDs are one-sided
      [units^2/Hz] on ``freqs``, interpolated onto ``n_fft/2 + 1`` uniform points of
      ``[0, fs/2]`` (geometrically where the PSD is positive, else linearly; held constant
      beyond the given range) (the circle's even half: see ``_bound``).
    * Resolution check: the bound is computed with ``n_fft`` and ``2 n_fft`` points and the
      finer value returned. The modes where they differ by more than 2 % are computed again
      with the FFT size doubled (those modes only) until two successive sizes agree, up to
      ``max_n_fft``; a mode still unresolved there raises a ``UserWarning`` naming it.
      Low-order turbulent modes put most of their variance below ~1 Hz, a few points of a
      ``2**15`` grid at kHz rates, and a tip PSD may need ``2**18`` to ``2**19`` points to
      settle (``docs/benchmarks.md``). A grid log-spaced at low frequency is still the
      better input (fewer interpolation artefacts).
    * Spectral factorisation by the cepstrum (FFT of size ``n_fft``): the total PSD must be
      > 0; it is floored at ``1e-14`` of its maximum (Paley-Wiener), and ``n_fft`` must
      resolve its sharpest feature (a resonance of damping ``z`` at ``f0`` needs
      ``fs / n_fft << z f0``).
    * ``G`` is stable and causal; zeros on the unit circle (``f = 0.5``: a zero at Nyquist)
      count as outer, so the bound is an infimum that no stable ``Q`` attains.

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Stable discrete SISO plant (e.g. :func:`aocontrol.loop_plant`).
    freqs : array_like, shape (n_freqs,)
        Strictly increasing grid in [0, fs/2] [Hz].
    psd : array_like, shape (n_freqs,) or (n_modes, n_freqs)
        Disturbance PSD, one-sided [units^2/Hz].
    noise_psd : float or array_like, default 0.0
        Measurement-noise PSD, one-sided [units^2/Hz]: scalar (white), like ``psd``, or one
        white level per mode ``(n_modes,)``.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    n_fft : int, default 32768
        Size of the full-circle FFT grid (even, in [64, 2**22]).
    max_n_fft : int, optional
        Largest FFT size of the refinement of unresolved modes, in ``[2 n_fft, 2**22]``
        (default ``max(2**20, 2 n_fft)``; ``2 n_fft``: no refinement, the check only).

    Returns
    -------
    float, or ndarray of shape (n_modes,) for 2-D inputs
        Minimum residual variance [units^2].

    Raises
    ------
    ValueError
        Bad grid or PSDs (NaN, negative, wrong shape), bad ``n_fft`` or ``max_n_fft``,
        unstable plant, FRD not covering ``[0, fs/2]``.

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> fs, a = 1000.0, 0.9
    >>> f = np.linspace(0.0, fs / 2, 20001)
    >>> ar1 = 2 / fs / np.abs(1 - a * np.exp(-2j * np.pi * f / fs)) ** 2  # s_w^2 = 1
    >>> # two-frame delay: prediction error 1 + a^2 = 1.81
    >>> round(float(wiener_bound(loop_plant(fs, 1.0), f, ar1)), 4)
    1.81
    """
    fs_ = plant_fs(plant, fs)
    if isinstance(plant, control.FRD):
        check_frd_coverage("plant", plant, fs_)
    freqs = check_frequency_grid("freqs", freqs, fs_)
    psd2, noise2, squeeze = mode_psds(psd, noise_psd, freqs.size)
    n_fft = check_int("n_fft", n_fft, minimum=64)
    if n_fft % 2 or n_fft > MAX_N_FFT:
        raise ValueError(f"n_fft must be an even integer in [64, {MAX_N_FFT}], got {n_fft}")
    if max_n_fft is None:
        max_n_fft = max(_MAX_REFINED_N_FFT, 2 * n_fft)
    max_n_fft = check_int("max_n_fft", max_n_fft, minimum=2 * n_fft)
    if max_n_fft > MAX_N_FFT:
        raise ValueError(f"max_n_fft must be in [2 n_fft, {MAX_N_FFT}], got {max_n_fft}")
    coarse = _bound(plant, fs_, freqs, psd2, noise2, n_fft)
    fine = _bound(plant, fs_, freqs, psd2, noise2, 2 * n_fft)
    size = 2 * n_fft
    bad = _unresolved(coarse, fine)
    # Modes whose bound still moves: the FFT size doubled for them alone, up to max_n_fft.
    while bad.size and 2 * size <= max_n_fft:
        size *= 2
        coarse = fine.copy()
        fine[bad] = _bound(plant, fs_, freqs, psd2[bad], noise2[bad], size)
        bad = bad[np.isin(bad, _unresolved(coarse, fine))]
    if bad.size:
        rel = np.abs(coarse[bad] / fine[bad] - 1.0)
        warnings.warn(
            f"wiener_bound: the PSD grid does not resolve the spectrum of modes "
            f"{bad[:10].tolist()}{' ...' if bad.size > 10 else ''} (the bound changes by up to "
            f"{100 * rel.max():.0f}% between FFT sizes {size // 2} and {size}); sample "
            "the PSD on a grid log-spaced at low frequency (e.g. numpy.geomspace)",
            UserWarning,
            stacklevel=2,
        )
    return float(fine[0]) if squeeze else fine


def _unresolved(coarse: np.ndarray, fine: np.ndarray) -> np.ndarray:
    """Modes whose bound changed by more than ``_RESOLUTION_TOL`` between two FFT sizes."""
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(coarse / fine - 1.0)
    return np.flatnonzero((rel > _RESOLUTION_TOL) & (fine > 0))


def _bound(
    plant: object, fs_: float, freqs: np.ndarray, psd2: np.ndarray, noise2: np.ndarray, n_fft: int
) -> np.ndarray:
    """The bound per mode on an ``n_fft``-point circle (see :func:`wiener_bound`).

    Every spectrum of the formula is even (the PSDs) or Hermitian (``G_i``, ``M``, the
    product ``F``), so it is computed on the ``n_fft/2 + 1`` points of the half circle with
    real transforms: a DCT-I and a real FFT for the factorisation, an inverse real FFT for
    ``F``'s coefficients (real); a mean over the full circle is the half's with the inner
    points counted twice.
    """
    gi_conj = np.conj(_inner_factor(plant, n_fft, fs_))
    h = n_fft // 2
    f_half = np.arange(h + 1) * fs_ / n_fft
    # Full-circle mean from the half circle: end points once, inner points twice.
    twice = np.full(h + 1, 2.0 / n_fft)
    twice[[0, h]] = 1.0 / n_fft
    n_modes = psd2.shape[0]
    out = np.empty(n_modes)
    block = max(1, _CHUNK // n_fft)
    for start in range(0, n_modes, block):
        sl = slice(start, min(start + block, n_modes))
        # Two-sided per-sample spectra: S(theta) = one-sided PSD * fs / 2, so that
        # mean over the circle = variance.
        sd = _to_half(psd2[sl], freqs, f_half) * (fs_ / 2)
        sn = _to_half(noise2[sl], freqs, f_half) * (fs_ / 2)
        total = sd + sn
        peak = total.max(axis=1, keepdims=True)
        zero = peak[:, 0] == 0
        total = np.maximum(total, _PSD_FLOOR * np.where(zero[:, None], 1.0, peak))
        log_m = _minimum_phase_log(np.log(total), n_fft)
        # F = conj(G_i) Sd / conj(M), M = exp(log_m)
        F = gi_conj * sd * np.exp(-np.conj(log_m))
        coef = scipy.fft.irfft(F, n=n_fft, axis=1)
        anticausal = np.sum(coef[:, h + 1 :] ** 2, axis=1) + 0.5 * coef[:, h] ** 2
        # a row sum, not a BLAS product: the same bits for a mode whatever the chunk's rows
        unpredictable = np.sum(sd * sn / total * twice, axis=1)
        out[sl] = np.where(zero, 0.0, unpredictable + anticausal)
    return out


def _to_half(psd: np.ndarray, freqs: np.ndarray, f_half: np.ndarray) -> np.ndarray:
    """Interpolate one-sided PSD rows onto ``f_half`` (the half circle).

    Rows that are positive everywhere are interpolated geometrically (log-PSD linear in
    frequency): turbulence spectra fall by decades between the points of a coarse linear grid,
    and linear interpolation there would invent high-frequency power, hence unpredictability
    (a "bound" far too high). Rows with zeros are interpolated linearly.
    """
    half = np.empty((psd.shape[0], f_half.size))
    for i, row in enumerate(psd):
        if np.all(row > 0):
            half[i] = np.exp(np.interp(f_half, freqs, np.log(row)))
        else:
            half[i] = np.interp(f_half, freqs, row)
    return half
