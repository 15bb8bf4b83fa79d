"""Loop models of an AO control loop, as python-control objects.

Conventions (control layer)
---------------------------
* Discrete time: the loop runs at ``fs`` [Hz], ``dt = 1/fs`` [s]. Public frequencies in Hz.
* The plant ``G`` maps a modal command to the modal measurement: WFS integration of one frame
  (``z^-1``), an RTC latency of ``latency_frames`` frames and a DM with unit gain::

      G(z) = z^-1 * ((1 - f) z^-k + f z^-(k+1)),  k = floor(latency_frames), f = frac part

  The fractional part linearly interpolates the command, as COMPASS does.
* A measured plant is a :class:`control.FRD` with ``dt = 1/fs``. python-control 0.10.2 resets
  ``dt`` to 0 on FRD arithmetic, so every function here takes ``fs`` explicitly when the FRD has
  lost it, and evaluates FRDs itself instead of relying on FRD arithmetic.
"""

from __future__ import annotations

import math

import control
import numpy as np

from aocontrol._validation import (
    check_finite_array,
    check_frequency_grid,
    check_nonnegative,
    check_positive,
)

__all__ = [
    "loop_plant",
    "measured_plant",
    "plant_fs",
    "frequency_response",
    "tf_from_z_inverse",
    "z_inverse_coefficients",
    "check_plant",
    "plant_delay_frames",
    "split_latency",
    "MAX_LATENCY_FRAMES",
]

# Relative tolerance to decide that a fractional delay is an integer (numerical noise of
# e.g. 0.83 * 3 computed in floating point).
_INTEGER_DELAY_RTOL = 1e-9
#: Largest accepted latency [frames]: an AO loop's RTC latency is a few frames; beyond this a
#: request is taken for a unit error (seconds or microseconds passed as frames) rather than
#: allocating a delay line of that length.
MAX_LATENCY_FRAMES = 1000.0


def split_latency(latency_frames: float) -> tuple[int, float]:
    """Split a latency into whole and fractional frames, ``(k, f)`` with ``0 <= f < 1``.

    The one owner of this split: :func:`loop_plant` and the simulator's delay line both use
    it, so that the simulated timing is the plant's. A fractional part within a relative
    ``1e-9`` of an integer (floating-point noise of e.g. ``0.83 * 3``) is taken as zero.

    Parameters
    ----------
    latency_frames : float
        RTC latency beyond the one-frame WFS integration [frames], in
        ``[0, MAX_LATENCY_FRAMES]``.

    Returns
    -------
    k : int
        Whole frames, ``floor(latency_frames)`` (rounded when ``f`` is numerical noise).
    f : float
        Fractional part in ``[0, 1)``.

    Raises
    ------
    ValueError
        If ``latency_frames`` is negative, not finite or above ``MAX_LATENCY_FRAMES``.

    Examples
    --------
    >>> split_latency(0.83)
    (0, 0.83)
    >>> split_latency(3 * (1 / 3))
    (1, 0.0)
    """
    latency = check_nonnegative("latency_frames", latency_frames)
    if latency > MAX_LATENCY_FRAMES:
        raise ValueError(
            f"latency_frames must be <= {MAX_LATENCY_FRAMES:g} frames (an RTC latency of a few "
            f"frames; a unit error?), got {latency!r}"
        )
    k = math.floor(latency)
    f = latency - k
    if abs(f - round(f)) < _INTEGER_DELAY_RTOL * max(1.0, latency):
        k, f = int(round(latency)), 0.0
    return int(k), float(f)


def tf_from_z_inverse(b: object, a: object, dt: float) -> control.TransferFunction:
    """Build a discrete SISO transfer function from coefficients in powers of ``z^-1``.

    ``H(z) = (b[0] + b[1] z^-1 + ...) / (a[0] + a[1] z^-1 + ...)``, as in
    :func:`scipy.signal.lfilter`. python-control stores polynomials in positive powers of z;
    both are padded to the same length so that the two forms are the same rational function.

    Examples
    --------
    >>> H = tf_from_z_inverse([0.5], [1.0, -1.0], dt=1e-3)   # 0.5 / (1 - z^-1)
    >>> float(H(1j).real), float(H(1j).imag)                  # z = j
    (0.25, -0.25)
    """
    b = np.atleast_1d(np.asarray(b, dtype=float))
    a = np.atleast_1d(np.asarray(a, dtype=float))
    n = max(b.size, a.size)
    num = np.concatenate([b, np.zeros(n - b.size)])
    den = np.concatenate([a, np.zeros(n - a.size)])
    return control.tf(num, den, dt)


def z_inverse_coefficients(sys: control.TransferFunction) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(b, a)`` in powers of ``z^-1`` of a discrete SISO transfer function.

    Inverse of :func:`tf_from_z_inverse` (up to trailing zeros); ``a[0]`` is normalised to 1.
    """
    if not isinstance(sys, control.TransferFunction):
        raise TypeError(f"sys must be a control.TransferFunction, got {type(sys).__name__}")
    if not sys.issiso():
        raise ValueError(f"sys must be SISO, got {sys.noutputs}x{sys.ninputs}")
    num = np.atleast_1d(np.asarray(sys.num[0][0], dtype=float))
    den = np.atleast_1d(np.asarray(sys.den[0][0], dtype=float))
    n = max(num.size, den.size)
    # Positive powers of z, highest first; dividing by z^(n-1) gives powers of z^-1.
    b = np.concatenate([np.zeros(n - num.size), num])
    a = np.concatenate([np.zeros(n - den.size), den])
    lead = np.flatnonzero(a)[0]
    b, a = b[lead:], a[lead:]
    scale = a[0]
    return b / scale, a / scale


def loop_plant(fs: float, latency_frames: float) -> control.TransferFunction:
    """Discrete AO loop plant ``G(z) = z^-1 ((1-f) z^-k + f z^-(k+1))``.

    Parameters
    ----------
    fs : float
        Loop rate [Hz], > 0.
    latency_frames : float
        RTC latency beyond the one-frame WFS integration [frames], >= 0 (0.83 for SAXO+ at
        3 kHz). ``k = floor(latency_frames)``, ``f = latency_frames - k``.

    Returns
    -------
    control.TransferFunction
        SISO, ``dt = 1/fs``. Total delay ``1 + latency_frames`` frames at low frequency.

    Raises
    ------
    ValueError
        If ``fs <= 0`` or ``latency_frames < 0`` (or not finite).

    Examples
    --------
    >>> G = loop_plant(fs=1000.0, latency_frames=1.0)      # G = z^-2
    >>> bool(abs(complex(G(np.exp(1j * 0.3))) - np.exp(-2j * 0.3)) < 1e-12)
    True
    """
    fs = check_positive("fs", fs)
    k, f = split_latency(latency_frames)
    b = np.zeros(k + 3)
    b[k + 1] = 1.0 - f
    b[k + 2] = f
    if f == 0.0:
        b = b[:-1]
    return tf_from_z_inverse(b, [1.0], 1.0 / fs)


def plant_delay_frames(
    plant: control.TransferFunction | control.FRD,
    fs: float | None = None,
) -> float:
    """Low-frequency group delay of a plant [frames] (``1 + latency_frames`` for loop_plant)."""
    fs_ = plant_fs(plant, fs)
    f0 = fs_ * 1e-4
    resp = frequency_response(plant, np.array([f0, 2 * f0]), fs_)
    dphi = np.angle(resp[1] / resp[0])
    return float(-dphi / (2 * np.pi * f0 / fs_))


def measured_plant(freqs: object, response: object, fs: float) -> control.FRD:
    """A measured plant as :class:`control.FRD` with ``dt = 1/fs``.

    Parameters
    ----------
    freqs : array_like, shape (n_freqs,)
        Strictly increasing frequencies in [0, fs/2] [Hz].
    response : array_like of complex, shape (n_freqs,)
        Plant frequency response (command to measurement) at ``freqs``.
    fs : float
        Loop rate [Hz].
    """
    fs = check_positive("fs", fs)
    freqs = check_frequency_grid("freqs", freqs, fs)
    resp = check_finite_array("response", response, ndim=1, dtype=complex)
    if resp.shape != freqs.shape:
        raise ValueError(f"response must have the shape of freqs {freqs.shape}, got {resp.shape}")
    return control.FRD(resp, 2 * np.pi * freqs, dt=1.0 / fs)


def plant_fs(plant: object, fs: float | None = None) -> float:
    """Loop rate [Hz] of a discrete plant, or ``fs`` when given (must then agree).

    Raises
    ------
    TypeError
        If ``plant`` is not a SISO ``control.TransferFunction`` / ``control.FRD``.
    ValueError
        If the plant is continuous-time (``dt == 0``) and no ``fs`` is given, or ``fs`` and
        the plant's ``dt`` disagree.
    """
    check_plant(plant)
    dt = plant.dt
    has_dt = dt not in (None, 0, True, False) and np.isfinite(float(dt)) and float(dt) > 0
    if fs is None:
        if not has_dt:
            kind = (
                "FRD (python-control drops dt on FRD arithmetic)"
                if isinstance(plant, control.FRD)
                else "system"
            )
            raise ValueError(
                f"plant must be discrete-time with dt = 1/fs > 0, got dt={dt!r} for a {kind}; "
                "pass fs explicitly"
            )
        return 1.0 / float(dt)
    fs = check_positive("fs", fs)
    if has_dt and not math.isclose(1.0 / float(dt), fs, rel_tol=1e-9):
        raise ValueError(f"fs={fs!r} Hz disagrees with the plant's dt={dt!r} s (1/dt Hz)")
    if not has_dt and isinstance(plant, control.TransferFunction):
        raise ValueError(
            f"plant must be a discrete-time transfer function, got dt={dt!r} (continuous)"
        )
    return fs


def check_plant(plant: object) -> None:
    """Raise ``TypeError``/``ValueError`` unless ``plant`` is a SISO TF or FRD."""
    if not isinstance(plant, (control.TransferFunction, control.FRD)):
        raise TypeError(
            f"plant must be a control.TransferFunction or control.FRD, got {type(plant).__name__}"
        )
    if plant.ninputs != 1 or plant.noutputs != 1:
        raise ValueError(f"plant must be SISO, got {plant.noutputs}x{plant.ninputs}")


def _frd_data(plant: control.FRD) -> tuple[np.ndarray, np.ndarray]:
    """(frequencies [rad/s], complex response) of a SISO FRD, without deprecated attributes."""
    data = getattr(plant, "frdata", None)
    if data is None:  # pragma: no cover - older python-control
        data = plant.fresp
    return np.asarray(plant.omega, dtype=float), np.asarray(data, dtype=complex)[0, 0]


def frequency_response(sys: object, freqs: object, fs: float | None = None) -> np.ndarray:
    """Complex frequency response of a discrete SISO system at ``freqs`` [Hz].

    Transfer functions are evaluated exactly at ``z = exp(2j pi f / fs)`` (vectorised
    polynomial evaluation). FRDs are read at their own grid points; between grid points the
    log-magnitude and the unwrapped phase are interpolated linearly. Requesting a frequency
    outside the FRD's measured range raises.

    Parameters
    ----------
    sys : control.TransferFunction or control.FRD
        Discrete SISO system.
    freqs : array_like, shape (n,)
        Frequencies [Hz] in [0, fs/2].
    fs : float, optional
        Loop rate [Hz]; required if ``sys`` lost its ``dt`` (FRD arithmetic).

    Returns
    -------
    numpy.ndarray of complex, shape (n,)
    """
    fs = plant_fs(sys, fs)
    freqs = check_finite_array("freqs", freqs, ndim=(0, 1))
    scalar = freqs.ndim == 0
    freqs = np.atleast_1d(freqs)
    if np.any(freqs < 0) or np.any(freqs > fs / 2 * (1 + 1e-12)):
        raise ValueError(f"freqs must lie in [0, fs/2] = [0, {fs / 2}] Hz")
    if isinstance(sys, control.TransferFunction):
        z = np.exp(2j * np.pi * freqs / fs)
        num = np.asarray(sys.num[0][0], dtype=float)
        den = np.asarray(sys.den[0][0], dtype=float)
        # Evaluate in powers of z^-1 to keep high-order delays well conditioned on |z| = 1.
        n = max(num.size, den.size)
        zi = 1.0 / z
        b = np.concatenate([np.zeros(n - num.size), num])
        a = np.concatenate([np.zeros(n - den.size), den])
        out = np.polyval(b[::-1], zi) / np.polyval(a[::-1], zi)
    else:
        omega, data = _frd_data(sys)
        f_grid = omega / (2 * np.pi)
        lo, hi = f_grid[0], f_grid[-1]
        tol = 1e-9 * fs
        if np.any(freqs < lo - tol) or np.any(freqs > hi + tol):
            raise ValueError(
                f"freqs must lie within the FRD's measured range [{lo}, {hi}] Hz, got "
                f"[{freqs.min()}, {freqs.max()}] Hz"
            )
        mag = np.log(np.abs(data))
        phase = np.unwrap(np.angle(data))
        fq = np.clip(freqs, lo, hi)
        out = np.exp(np.interp(fq, f_grid, mag) + 1j * np.interp(fq, f_grid, phase))
        # Exact grid points keep their measured value (no interpolation error).
        idx = np.clip(np.searchsorted(f_grid, fq), 0, f_grid.size - 1)
        prev = np.clip(idx - 1, 0, f_grid.size - 1)
        near = np.where(np.abs(f_grid[prev] - fq) < np.abs(f_grid[idx] - fq), prev, idx)
        hit = np.abs(f_grid[near] - fq) <= tol
        out[hit] = data[near[hit]]
    return out[0] if scalar else out
