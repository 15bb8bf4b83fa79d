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
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from aocontrol._validation import (
    check_frequency_grid,
    check_int,
    check_positive,
)

__all__ = ["DisturbanceModel", "ar2_variance"]

logger = logging.getLogger(__name__)

# An AR(2) is declared unstable (no usable model) when a pole modulus reaches 1 - this.
_POLE_MARGIN = 1e-9


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


#: Floor of ``|A(z)|^2`` on the unit circle, ``A = 1 - a1 z^-1 - a2 z^-2``: the square of the
#: rounding error of computing ``A`` (a few ulps of its terms, each at most 4 in modulus for
#: a stable AR(2)). Below it the value is rounding noise; a trial pole on the unit circle (a
#: fit's iterate may touch ``z = 1`` at 0 Hz) gives a large, finite PSD, never a division by
#: zero or an overflow.
_AR2_DENOMINATOR_FLOOR = (16 * np.finfo(float).eps) ** 2


def _resonator(f0: np.ndarray, xi: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised :func:`aocontrol.disturbance.resonator_ar2` (same impulse-invariant map)."""
    w0 = 2 * np.pi * f0 / fs
    r = np.exp(-xi * w0)
    theta = w0 * np.sqrt(1 - xi * xi)
    return 2 * r * np.cos(theta), -r * r


def _ar2_denominator(
    a1: np.ndarray, a2: np.ndarray, zi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``A = 1 - a1 z^-1 - a2 z^-2`` on ``zi`` and ``|A|^2`` floored at the rounding level.

    The one evaluation of an AR(2) denominator for PSDs and their gradients
    (:data:`_AR2_DENOMINATOR_FLOOR`).

    Parameters
    ----------
    a1, a2 : numpy.ndarray, shape (...,)
        AR coefficients.
    zi : numpy.ndarray of complex, shape (n_freqs,)
        ``exp(-2j pi f / fs)``.

    Returns
    -------
    a : numpy.ndarray of complex, shape (..., n_freqs)
    abs2 : numpy.ndarray, shape (..., n_freqs)
        ``max(|A|^2, _AR2_DENOMINATOR_FLOOR)``.
    """
    a = 1 - a1[..., None] * zi - a2[..., None] * zi * zi
    return a, np.maximum(a.real * a.real + a.imag * a.imag, _AR2_DENOMINATOR_FLOOR)


def _ar2_psd(a1: np.ndarray, a2: np.ndarray, s2: np.ndarray, zi: np.ndarray, fs: float):
    """One-sided PSD of AR(2) components; coefficient arrays (...,), ``zi`` (n_freqs,)."""
    return 2 * s2[..., None] / fs / _ar2_denominator(a1, a2, zi)[1]


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
    components or with :func:`aocontrol.synthesis.fit_disturbance_model`.

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
