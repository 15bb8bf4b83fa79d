"""Per-mode state-space disturbance models: AR(2) turbulence plus AR(2) vibration resonances.

Each mode's disturbance is the sum of independent components driven by white noise,

    d[k] = t[k] + sum_j v_j[k],
    t[k]   = a1 t[k-1] + a2 t[k-2] + w_t[k]           (turbulence, AR(2))
    v_j[k] = b1j v_j[k-1] + b2j v_j[k-2] + w_j[k]     (resonance j: f0, damping, variance)

the resonances being the sampled damped oscillators of
:func:`aocontrol.disturbance.resonator_ar2`. As a state space (per mode, ``nx = 2 (1 + n_vib)``)::

    x[k] = (t[k], t[k-1], v_1[k], v_1[k-1], ...),  x[k+1] = A x[k] + w[k],  d[k] = C x[k]

``A`` block diagonal with companion blocks ``[[a1, a2], [1, 0]]``, ``C = (1, 0, 1, 0, ...)``
and ``Q = E[w w^T]`` diagonal with the driving variances on the even entries. Modes with fewer
resonances than the bank's widest are padded with absent resonances (variance 0: zero block).

PSDs are one-sided [units^2/Hz] (``scipy.signal.welch(..., scaling="density")``): an AR(2)
component of driving variance ``s_w^2`` per frame has ``P(f) = (2 s_w^2 / fs) /
|1 - a1 e^{-jw} - a2 e^{-2jw}|^2``, ``w = 2 pi f / fs``.
"""

from __future__ import annotations

import logging
import os
import warnings
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import optimize

from aocontrol._validation import (
    check_frequency_grid,
    check_int,
    check_positive,
    mode_psds,
)

__all__ = ["DisturbanceModel", "ar2_variance", "fit_disturbance_model"]

logger = logging.getLogger(__name__)

# An AR(2) is declared unstable (no usable model) when a pole modulus reaches 1 - this.
_POLE_MARGIN = 1e-9
# Bounds of the turbulence's reflection coefficients in the fit, atanh scale: tanh(15) =
# 1 - 1.9e-13, so a fitted pole cannot reach the unit circle by the optimiser's rounding.
_ATANH_BOUND = 15.0
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


def ar2_variance(a1: object, a2: object, driving_variance: object) -> np.ndarray:
    """Variance of a stationary AR(2) process ``x[k] = a1 x[k-1] + a2 x[k-2] + w[k]``.

    ``var(x) = s_w^2 (1 - a2) / ((1 + a2) ((1 - a2)^2 - a1^2))`` (Box & Jenkins).

    Parameters
    ----------
    a1, a2 : array_like
        AR coefficients (broadcast together), stable: ``|a2| < 1``, ``|a1| < 1 - a2``.
    driving_variance : array_like
        Variance ``s_w^2`` of the white driving noise per frame [units^2].

    Returns
    -------
    ndarray
        Process variance [units^2].
    """
    a1, a2, s2 = (np.asarray(x, dtype=float) for x in (a1, a2, driving_variance))
    return s2 * (1 - a2) / ((1 + a2) * ((1 - a2) ** 2 - a1 * a1))


_TINY = np.finfo(float).tiny


def _resonator(f0: np.ndarray, xi: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised :func:`aocontrol.disturbance.resonator_ar2` (same impulse-invariant map)."""
    w0 = 2 * np.pi * f0 / fs
    r = np.exp(-xi * w0)
    theta = w0 * np.sqrt(1 - xi * xi)
    return 2 * r * np.cos(theta), -r * r


def _ar2_psd(a1: np.ndarray, a2: np.ndarray, s2: np.ndarray, zi: np.ndarray, fs: float):
    """One-sided PSD of AR(2) components; coefficient arrays (...,), ``zi`` (n_freqs,)."""
    den = np.abs(1 - a1[..., None] * zi - a2[..., None] * zi * zi) ** 2
    # A trial pole on the unit circle (the fit's iterates may touch z = 1 at f = 0): a huge,
    # finite PSD instead of a division by zero.
    return 2 * s2[..., None] / fs / np.maximum(den, _TINY)


def _ar2_stable(a1: np.ndarray, a2: np.ndarray) -> np.ndarray:
    """Largest pole modulus of ``1 - a1 z^-1 - a2 z^-2`` (elementwise)."""
    disc = np.asarray(a1, dtype=complex) ** 2 + 4 * np.asarray(a2, dtype=complex)
    root = np.sqrt(disc)
    return np.maximum(np.abs((a1 + root) / 2), np.abs((a1 - root) / 2))


@dataclass(frozen=True)
class DisturbanceModel:
    """Per-mode AR(2) turbulence plus AR(2) resonances, as one state space per mode.

    See the module docstring for the state layout. Arrays are per mode; resonance arrays are
    padded to the bank's widest mode with absent resonances (``vibration_variance == 0``,
    their frequency and damping are then ignored and may be NaN). Build it directly from the
    components or with :func:`fit_disturbance_model`.

    Parameters
    ----------
    turbulence_ar : array_like, shape (n_modes, 2)
        Turbulence AR(2) coefficients ``(a1, a2)`` per mode, stable (poles inside the unit
        circle; ``(0, 0)`` is white).
    turbulence_variance : array_like, shape (n_modes,)
        Turbulence process variance [units^2], >= 0.
    vibration_frequency : array_like, shape (n_modes, n_vib)
        Resonance natural frequency ``f0`` [Hz], in ``(0, fs/2)`` where present.
    vibration_damping : array_like, shape (n_modes, n_vib)
        Damping ratio ``xi`` in ``(0, 1)`` where present.
    vibration_variance : array_like, shape (n_modes, n_vib)
        Resonance process variance [units^2], >= 0 (0: absent).
    fs : float
        Loop rate [Hz].

    Attributes
    ----------
    A : ndarray, shape (n_modes, nx, nx)
        State transition, ``nx = 2 (1 + n_vib)``.
    C : ndarray, shape (n_modes, nx)
        Output ``d[k] = C x[k]``.
    Q : ndarray, shape (n_modes, nx, nx)
        Process-noise covariance per frame [units^2].

    Raises
    ------
    ValueError
        Shapes that disagree, non-finite values, an unstable turbulence AR(2), a negative
        variance, a resonance frequency outside ``(0, fs/2)`` or a damping outside ``(0, 1)``
        (naming the mode).

    Examples
    --------
    >>> m = DisturbanceModel([[1.8, -0.81]], [1.0], [[50.0]], [[0.05]], [[0.5]], fs=1000.0)
    >>> m.A.shape, m.n_vibrations
    ((1, 4, 4), 1)
    >>> f = np.linspace(0.0, 500.0, 200001)
    >>> round(float(np.trapezoid(m.psd(f)[0], f)), 3)   # total variance 1.0 + 0.5
    1.5
    """

    turbulence_ar: np.ndarray
    turbulence_variance: np.ndarray
    vibration_frequency: np.ndarray
    vibration_damping: np.ndarray
    vibration_variance: np.ndarray
    fs: float

    def __post_init__(self) -> None:
        fs = check_positive("fs", self.fs)
        ar = _finite_rows("turbulence_ar", self.turbulence_ar, 2)
        n = ar.shape[0]
        if ar.shape[1] != 2 or n < 1:
            raise ValueError(f"turbulence_ar must have shape (n_modes, 2), got {ar.shape}")
        tv = _finite_rows("turbulence_variance", self.turbulence_variance, 1)
        if tv.shape != (n,):
            raise ValueError(f"turbulence_variance must have shape ({n},), got {tv.shape}")
        vv = _finite_rows("vibration_variance", self.vibration_variance, 2)
        if vv.shape[0] != n:
            raise ValueError(f"vibration_variance must have shape ({n}, n_vib), got {vv.shape}")
        vf = np.asarray(self.vibration_frequency, dtype=float)
        vd = np.asarray(self.vibration_damping, dtype=float)
        for name, arr in (("vibration_frequency", vf), ("vibration_damping", vd)):
            if arr.shape != vv.shape:
                raise ValueError(f"{name} must have shape {vv.shape}, got {arr.shape}")
        if np.any(tv < 0):
            raise ValueError(
                f"turbulence_variance must be >= 0, mode {_first(tv < 0)} is {tv.min()}"
            )
        if np.any(vv < 0):
            raise ValueError(
                f"vibration_variance must be >= 0, mode {_first(vv < 0)} is {vv.min()}"
            )
        pole = _ar2_stable(ar[:, 0], ar[:, 1])
        if np.any(pole >= 1 - _POLE_MARGIN):
            m = _first(pole >= 1 - _POLE_MARGIN)
            raise ValueError(
                f"turbulence_ar must be a stable AR(2) (poles inside the unit circle), mode {m} "
                f"has (a1, a2) = {tuple(ar[m])} with a pole of modulus {pole[m]:.12g}"
            )
        present = vv > 0
        bad_f = present & ~((vf > 0) & (vf < fs / 2))
        if np.any(bad_f):
            m, j = np.argwhere(bad_f)[0]
            raise ValueError(
                f"vibration_frequency must be in (0, fs/2) = (0, {fs / 2}) Hz (Nyquist), mode {m} "
                f"resonance {j} has {vf[m, j]!r} Hz"
            )
        bad_d = present & ~((vd > 0) & (vd < 1))
        if np.any(bad_d):
            m, j = np.argwhere(bad_d)[0]
            raise ValueError(
                f"vibration_damping must be in (0, 1), mode {m} resonance {j} has {vd[m, j]!r}"
            )
        vf = np.where(present, vf, np.nan)
        vd = np.where(present, vd, np.nan)
        for name, arr in (
            ("turbulence_ar", ar),
            ("turbulence_variance", tv),
            ("vibration_frequency", vf),
            ("vibration_damping", vd),
            ("vibration_variance", vv),
        ):
            arr = np.array(arr, dtype=float)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "fs", fs)

    # -- sizes ----------------------------------------------------------------------------
    @property
    def n_modes(self) -> int:
        """Number of modes."""
        return self.turbulence_ar.shape[0]

    @property
    def n_vibrations(self) -> int:
        """Resonance slots per mode (the widest mode's count)."""
        return self.vibration_variance.shape[1]

    @property
    def nx(self) -> int:
        """State dimension per mode, ``2 (1 + n_vibrations)``."""
        return 2 * (1 + self.n_vibrations)

    # -- components -----------------------------------------------------------------------
    @cached_property
    def vibration_ar(self) -> np.ndarray:
        """Resonance AR(2) coefficients ``(b1, b2)``, shape ``(n_modes, n_vib, 2)``; 0 if absent."""
        present = self.vibration_variance > 0
        f0 = np.where(present, self.vibration_frequency, 1.0)
        xi = np.where(present, self.vibration_damping, 0.5)
        b1, b2 = _resonator(f0, xi, self.fs)
        out = np.stack([np.where(present, b1, 0.0), np.where(present, b2, 0.0)], axis=-1)
        out.setflags(write=False)
        return out

    @cached_property
    def component_ar(self) -> np.ndarray:
        """AR(2) coefficients of every component, shape ``(n_modes, 1 + n_vib, 2)``,
        turbulence first."""
        out = np.concatenate([self.turbulence_ar[:, None, :], self.vibration_ar], axis=1)
        out.setflags(write=False)
        return out

    @cached_property
    def driving_variance(self) -> np.ndarray:
        """Driving-noise variance per frame of every component [units^2],
        shape ``(n_modes, 1 + n_vib)``, turbulence first."""
        ar = self.component_ar
        var = np.concatenate([self.turbulence_variance[:, None], self.vibration_variance], axis=1)
        unit = ar2_variance(ar[..., 0], ar[..., 1], 1.0)
        out = var / unit
        out.setflags(write=False)
        return out

    @property
    def variance(self) -> np.ndarray:
        """Total disturbance variance per mode [units^2], shape ``(n_modes,)``."""
        return self.turbulence_variance + self.vibration_variance.sum(axis=1)

    # -- state space ----------------------------------------------------------------------
    @cached_property
    def A(self) -> np.ndarray:  # noqa: N802 - state-space notation
        """State transition, shape ``(n_modes, nx, nx)`` (block-diagonal companion blocks)."""
        n, nc = self.n_modes, 1 + self.n_vibrations
        out = np.zeros((n, 2 * nc, 2 * nc))
        ar = self.component_ar
        for c in range(nc):
            out[:, 2 * c, 2 * c] = ar[:, c, 0]
            out[:, 2 * c, 2 * c + 1] = ar[:, c, 1]
            out[:, 2 * c + 1, 2 * c] = 1.0
        out.setflags(write=False)
        return out

    @cached_property
    def C(self) -> np.ndarray:  # noqa: N802
        """Output matrix, shape ``(n_modes, nx)``: ``d = C x`` sums the components."""
        out = np.zeros((self.n_modes, self.nx))
        out[:, 0::2] = 1.0
        out.setflags(write=False)
        return out

    @cached_property
    def Q(self) -> np.ndarray:  # noqa: N802
        """Process-noise covariance per frame [units^2], shape ``(n_modes, nx, nx)``."""
        out = np.zeros((self.n_modes, self.nx, self.nx))
        idx = np.arange(0, self.nx, 2)
        out[:, idx, idx] = self.driving_variance
        out.setflags(write=False)
        return out

    # -- spectra and samples --------------------------------------------------------------
    def psd(self, freqs: object) -> np.ndarray:
        """One-sided PSD of the model [units^2/Hz], shape ``(n_modes, n_freqs)``.

        Parameters
        ----------
        freqs : array_like, shape (n_freqs,)
            Strictly increasing frequencies in ``[0, fs/2]`` [Hz].
        """
        freqs = check_frequency_grid("freqs", freqs, self.fs)
        return self.component_psd(freqs).sum(axis=1)

    def component_psd(self, freqs: object) -> np.ndarray:
        """One-sided PSD of each component [units^2/Hz], shape ``(n_modes, 1 + n_vib, n_freqs)``,
        turbulence first.

        Parameters
        ----------
        freqs : array_like, shape (n_freqs,)
            Strictly increasing frequencies in ``[0, fs/2]`` [Hz].
        """
        freqs = check_frequency_grid("freqs", freqs, self.fs)
        zi = np.exp(-2j * np.pi * freqs / self.fs)
        ar = self.component_ar
        return _ar2_psd(ar[..., 0], ar[..., 1], self.driving_variance, zi, self.fs)

    def simulate(
        self, n_frames: int, rng: np.random.Generator, *, burn_in: int | None = None
    ) -> np.ndarray:
        """A stationary realisation of the disturbance, shape ``(n_frames, n_modes)`` [units].

        The recursion runs ``burn_in`` frames before the record (default: ten times the
        slowest component's decay time, at most 100000 frames) so that the record starts in
        the stationary regime. Vectorised over modes and components.

        Parameters
        ----------
        n_frames : int
            Number of frames, >= 1.
        rng : numpy.random.Generator
            Source of the driving noise.
        burn_in : int, optional
            Frames discarded before the record.
        """
        n_frames = check_int("n_frames", n_frames, minimum=1)
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        ar = self.component_ar
        if burn_in is None:
            pole = float(np.max(_ar2_stable(ar[..., 0], ar[..., 1])))
            decay = 1.0 / max(1.0 - pole, 1e-5)
            burn_in = int(min(10 * decay, 100_000))
        burn_in = check_int("burn_in", burn_in, minimum=0)
        a1, a2 = ar[..., 0], ar[..., 1]
        sd = np.sqrt(self.driving_variance)
        total = burn_in + n_frames
        w = rng.standard_normal((total,) + sd.shape) * sd
        x1 = np.zeros(sd.shape)
        x2 = np.zeros(sd.shape)
        out = np.empty((n_frames, self.n_modes))
        for k in range(total):
            x = a1 * x1 + a2 * x2 + w[k]
            x2, x1 = x1, x
            if k >= burn_in:
                out[k - burn_in] = x.sum(axis=1)
        return out


def _finite_rows(name: str, value: object, ndim: int | tuple[int, ...]) -> np.ndarray:
    """``value`` as a float array; NaN/inf raise naming the first mode concerned.

    The mode is the row of a 2-D array and the index of a 1-D per-mode array; a 1-D PSD
    (``name == "psd"``) is the single mode 0.
    """
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise TypeError(
            f"{name} must be array-like of numbers, got {type(value).__name__}"
        ) from exc
    allowed = (ndim,) if isinstance(ndim, int) else ndim
    if arr.ndim not in allowed:
        dims = " or ".join(map(str, allowed))
        raise ValueError(f"{name} must have {dims} dimension(s), got shape {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        rows = (
            bad.reshape(1, -1)
            if (arr.ndim == 1 and name == "psd")
            else bad.reshape(arr.shape[0], -1)
        )
        mode = int(np.flatnonzero(rows.any(axis=1))[0])
        raise ValueError(
            f"{name} must contain only finite values, mode {mode} has "
            f"{int(rows[mode].sum())} NaN/inf"
        )
    return arr


def _first(mask: np.ndarray) -> int:
    """Index of the first mode (row) where ``mask`` holds."""
    return int(np.argwhere(mask)[0][0])


# ---------------------------------------------------------------------------------------------
# Fitting
# ---------------------------------------------------------------------------------------------
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
    """(a1, a2, s_w^2) from (atanh k1, atanh k2, log s_w^2): always a stable AR(2)."""
    k1, k2 = np.tanh(p[0]), np.tanh(p[1])
    return float(k1 * (1 - k2)), float(k2), float(np.exp(p[2]))


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
    ``dM/dc = 2 M Re(z^-i conj(A)) / |A|^2`` (i = 1, 2), ``dM/dlog s2 = M``.
    """
    a = 1 - c1 * zi - c2 * zi * zi
    a2 = (a * np.conj(a)).real
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
    bounds = ([lim[0], lim[0], -np.inf], [lim[1], lim[1], np.inf])
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
    turb = _fit_turbulence(freqs, p, noise, zi, fs, _yule_walker_ar2(r), s.peak_ratio)
    mask = (p + noise) > s.peak_ratio * (_ar2_psd(*(np.asarray(v) for v in turb), zi, fs) + noise)
    model = _ar2_psd(*(np.asarray(v) for v in turb), zi, fs)
    excess = np.maximum(p - model, 0.0)
    # 2. Resonance candidates: the flagged runs, strongest excess variance first.
    cands = []
    for i0, i1 in _runs(mask):
        seg = slice(max(i0 - 1, 0), min(i1 + 1, freqs.size))
        var = float(np.trapezoid(excess[seg], freqs[seg])) if i1 - i0 >= 1 else 0.0
        ipk = i0 + int(np.argmax(excess[i0:i1]))
        f0 = freqs[ipk]
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
        bounds += [(lo, hi), tuple(np.log(_XI_BOUNDS)), (None, None)]
    x0 = np.concatenate(x0)
    target = p + noise
    scale = float(np.sum(w * target))

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
        sp = np.maximum(total, 1e-300)
        value = float(np.sum(w * (np.log(sp / scale) + target / sp)))
        dj = w * (1 / sp - target / (sp * sp))
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
    if not (np.isfinite(tv) and tv >= 0 and np.all(np.isfinite([a1, a2]))):
        raise ValueError(f"psd of mode {mode}: no stable AR model can be fitted (fit diverged)")
    vibs = [(float(a), float(b), float(c)) for a, b, c in zip(f0, xi, var, strict=True)]
    return (a1, a2, tv), vibs, clipped


def _fit_chunk(freqs: np.ndarray, chunk: list, settings: _FitSettings) -> list:
    return [_fit_mode(m, freqs, p, noise, settings) for m, p, noise in chunk]


def _run_fits(freqs: np.ndarray, items: list, settings: _FitSettings, n_jobs: int | None) -> list:
    """Per-mode fits in this process or over joblib workers (chunks of modes, in order)."""
    if n_jobs is not None:
        n_jobs = check_int("n_jobs", n_jobs)
        if n_jobs == 0:
            raise ValueError("n_jobs must be a nonzero integer (negative: joblib convention)")
    cores = os.cpu_count() or 1
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
       radius, with a ``UserWarning`` naming the modes.

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
