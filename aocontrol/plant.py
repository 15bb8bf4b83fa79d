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
* What a control object contains is checked in one place, :func:`check_system`, by every entry
  point of the control layer: SISO, finite coefficients / FRD points, a causal (proper)
  transfer function, a definite sampling period (``dt = 1.0`` is 1 s; ``dt = True`` is
  python-control's "unspecified" and needs ``fs``). Errors name the argument (``plant``,
  ``controller``, ``initial``...).
* A stability verdict from an FRD needs the whole of [0, fs/2] (:func:`check_frd_coverage`):
  the first point within ``FRD_END_GAP_FRACTION`` = 0.5 of the first grid step of 0 Hz, the
  last within 0.5 of the last step of fs/2; otherwise the missing band is named.
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
    "check_system",
    "check_frd_coverage",
    "plant_delay_frames",
    "plant_latency",
    "with_latency",
    "pure_delay_form",
    "split_latency",
    "MAX_LATENCY_FRAMES",
    "FRD_END_GAP_FRACTION",
    "FREQ_RTOL",
]

# Relative tolerance to decide that a fractional delay is an integer (numerical noise of
# e.g. 0.83 * 3 computed in floating point).
_INTEGER_DELAY_RTOL = 1e-9
#: Largest accepted latency [frames]: an AO loop's RTC latency is a few frames; beyond this a
#: request is taken for a unit error (seconds or microseconds passed as frames) rather than
#: allocating a delay line of that length.
MAX_LATENCY_FRAMES = 1000.0
#: An FRD "covers" [0, fs/2] when its first point lies within this fraction of its first grid
#: step of 0 Hz and its last point within this fraction of its last step of fs/2. The winding
#: number closes the contour from the end points to the real axis (where ``P`` is real for
#: real-coefficient systems); a gap shorter than half a step is bridged under the same
#: resolution assumption as the interior of the grid (phase steps checked < pi/3), a larger
#: one is a band that was never measured.
FRD_END_GAP_FRACTION = 0.5
#: Relative tolerance (a fraction of ``fs``) for every comparison of frequencies that went
#: through a round trip between Hz and rad/s (an FRD stores ``omega = 2 pi f``; ``f`` read back
#: as ``omega / 2 pi`` may exceed ``fs/2`` by an ulp). The one owner of that tolerance: the
#: coverage check, the FRD's measured range and the public ``[0, fs/2]`` check all use it.
FREQ_RTOL = 1e-9


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

    Parameters
    ----------
    b, a : array_like, shape (nb,) and (na,)
        Numerator and denominator coefficients in powers of ``z^-1`` (finite; ``a`` not all
        zero, the filter causal).
    dt : float
        Sampling period [s], ``1/fs``.

    Returns
    -------
    control.TransferFunction

    Raises
    ------
    ValueError
        NaN/inf coefficients, ``a`` zero everywhere, or a non-causal ratio (``a`` starts
        with more zeros than ``b``, e.g. ``b = [1], a = [0, 1]`` is ``z``).

    Examples
    --------
    >>> H = tf_from_z_inverse([0.5], [1.0, -1.0], dt=1e-3)   # 0.5 / (1 - z^-1)
    >>> float(H(1j).real), float(H(1j).imag)                  # z = j
    (0.25, -0.25)
    """
    b = np.atleast_1d(check_finite_array("b", b, ndim=(0, 1)))
    a = np.atleast_1d(check_finite_array("a", a, ndim=(0, 1)))
    if not np.any(a):
        raise ValueError(f"a must not be zero everywhere (a denominator), got {a.tolist()}")
    # Causal iff the first nonzero coefficient of a comes no later than that of b (a common
    # leading z^-1 factor cancels): e.g. b = [1], a = [0, 1] is K = z.
    if np.any(b) and np.flatnonzero(a)[0] > np.flatnonzero(b)[0]:
        raise ValueError(
            "b/a must be causal (a[0] != 0 after cancelling common leading zeros; a 1-frame "
            f"advance z is not realisable), got b={_short_list(b)}, a={_short_list(a)}"
        )
    n = max(b.size, a.size)
    num = np.concatenate([b, np.zeros(n - b.size)])
    den = np.concatenate([a, np.zeros(n - a.size)])
    return control.tf(num, den, dt)


def z_inverse_coefficients(
    sys: control.TransferFunction, name: str = "sys"
) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(b, a)`` in powers of ``z^-1`` of a discrete SISO transfer function.

    Inverse of :func:`tf_from_z_inverse` (up to trailing zeros); ``a[0]`` is normalised to 1.

    Parameters
    ----------
    sys : control.TransferFunction
        Causal (proper) SISO discrete transfer function with finite coefficients.
    name : str, default "sys"
        Name of the argument in error messages (``"plant"``, ``"controller"``...).

    Returns
    -------
    b, a : numpy.ndarray
        Coefficients in powers of ``z^-1``, ``a[0] == 1``.

    Raises
    ------
    TypeError
        If ``sys`` is not a ``control.TransferFunction``.
    ValueError
        Not SISO, NaN/inf coefficients, a zero denominator or an improper (non-causal)
        system, e.g. ``3 z``.
    """
    if not isinstance(sys, control.TransferFunction):
        raise TypeError(f"{name} must be a control.TransferFunction, got {type(sys).__name__}")
    if not sys.issiso():
        raise ValueError(f"{name} must be SISO, got {sys.noutputs}x{sys.ninputs}")
    num, den = _tf_polynomials(name, sys)
    n = max(num.size, den.size)
    # Positive powers of z, highest first; dividing by z^(n-1) gives powers of z^-1.
    b = np.concatenate([np.zeros(n - num.size), num])
    a = np.concatenate([np.zeros(n - den.size), den])
    scale = a[0]
    return b / scale, a / scale


def _short_list(x: np.ndarray) -> str:
    text = np.array2string(np.asarray(x), precision=4, threshold=8)
    return text if len(text) <= 80 else text[:77] + "..."


def _tf_polynomials(name: str, sys: control.TransferFunction) -> tuple[np.ndarray, np.ndarray]:
    """Numerator and denominator of a SISO TF in powers of z (leading zeros dropped), checked.

    The one check of a transfer function's contents: finite coefficients, a nonzero
    denominator and causality (``deg num <= deg den`` in ``z``).
    """
    num = np.atleast_1d(np.asarray(sys.num[0][0], dtype=float))
    den = np.atleast_1d(np.asarray(sys.den[0][0], dtype=float))
    for part, arr in (("numerator", num), ("denominator", den)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} has NaN/inf in its {part} coefficients: {_short_list(arr)}")
    den = np.trim_zeros(den, "f")
    if den.size == 0:
        raise ValueError(f"{name} has a zero denominator")
    num = np.trim_zeros(num, "f")
    if num.size == 0:
        num = np.zeros(1)
    if num.size > den.size:
        raise ValueError(
            f"{name} must be causal (proper): its numerator has degree {num.size - 1} in z, "
            f"above the denominator's {den.size - 1} (e.g. K = 3z needs the next measurement); "
            f"got num={_short_list(num)}, den={_short_list(den)}"
        )
    return num, den


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
    return tf_from_z_inverse(_delay_numerator(latency_frames), [1.0], 1.0 / fs)


def _delay_numerator(latency_frames: float) -> np.ndarray:
    """``z^-1 ((1-f) z^-k + f z^-(k+1))`` in powers of ``z^-1`` (the one construction)."""
    k, f = split_latency(latency_frames)
    b = np.zeros(k + 3)
    b[k + 1] = 1.0 - f
    b[k + 2] = f
    return b[:-1] if f == 0.0 else b


def plant_delay_frames(
    plant: control.TransferFunction | control.FRD,
    fs: float | None = None,
) -> float:
    """Low-frequency group delay of a plant [frames] (``1 + latency_frames`` for loop_plant).

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.

    Returns
    -------
    float
        Group delay [frames] at ``1e-4 fs``.
    """
    fs_ = plant_fs(plant, fs)
    f0 = fs_ * 1e-4
    resp = frequency_response(plant, np.array([f0, 2 * f0]), fs_)
    dphi = np.angle(resp[1] / resp[0])
    return float(-dphi / (2 * np.pi * f0 / fs_))


def pure_delay_form(b: np.ndarray) -> tuple[np.ndarray, float] | None:
    """A plant numerator as ``core(w) w^(1+k) ((1-f) + f w)``: ``(core, k + f)`` (``w = z^-1``).

    The one reading of a latency from a plant (:func:`plant_latency`, :func:`with_latency`,
    the delay margins of :func:`aocontrol.analysis.margins`).

    Parameters
    ----------
    b : array_like
        Numerator in powers of ``z^-1`` (lowest first).


    Two non-zero terms of one sign are the interpolation pair of a fractional latency
    (:func:`loop_plant`, times any gain); otherwise the leading zeros are the whole-frame delay
    and ``core`` the rest. ``None`` without the WFS frame's delay (no latency to move).
    """
    b = np.trim_zeros(np.asarray(b, dtype=float), "b")
    nz = np.flatnonzero(b)
    if nz.size == 0 or nz[0] < 1:
        return None
    j, tail = int(nz[0]), b[nz[0] :]
    if tail.size == 2 and tail[0] * tail[1] > 0:
        c = float(tail.sum())
        return np.array([c]), (j - 1) + float(tail[1] / c)
    return tail, float(j - 1)


def plant_latency(plant: control.TransferFunction) -> float | None:
    """The latency [frames] of a plant's pure delay, as :func:`loop_plant` models it.

    A numerator ``c z^-(1+k) ((1-f) + f z^-1)`` (:func:`loop_plant` times a gain, any
    denominator: a DM's lag) has latency ``k + f``; any other numerator ``z^-(1+k) B(z^-1)``
    has the whole frames ``k`` of its leading delay. ``None`` for a plant without the WFS
    frame's delay.

    Parameters
    ----------
    plant : control.TransferFunction

    Examples
    --------
    >>> plant_latency(loop_plant(3000.0, 0.83))
    0.83
    """
    form = pure_delay_form(z_inverse_coefficients(plant, "plant")[0])
    return None if form is None else round(form[1], 12)


def with_latency(
    plant: control.TransferFunction, latency_frames: float
) -> control.TransferFunction:
    """The plant with its pure delay moved to ``latency_frames`` (the rest kept).

    The latency model of :func:`loop_plant` (linear interpolation between whole frames: the
    exact sampled model of a held command): the numerator's delay pair (or its leading
    delay, see :func:`plant_latency`) becomes ``z^-(1+k) ((1-f) + f z^-1)`` times the
    numerator's other factors; the denominator is kept.

    Parameters
    ----------
    plant : control.TransferFunction
    latency_frames : float
        New latency beyond the WFS frame [frames], >= 0.

    Raises
    ------
    ValueError
        A plant without the WFS frame's delay, or a bad latency.

    Examples
    --------
    >>> G = with_latency(loop_plant(1000.0, 0.5), 1.25)
    >>> plant_latency(G)
    1.25
    """
    b, a = z_inverse_coefficients(plant, "plant")
    form = pure_delay_form(b)
    if form is None:
        raise ValueError("plant has no pure delay of the WFS frame to move (numerator b[0] != 0)")
    core, _ = form
    new = np.convolve(_delay_numerator(latency_frames), core)
    return tf_from_z_inverse(new, np.trim_zeros(a, "b"), float(plant.dt))


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


def _sampling_period(sys: object) -> float | None:
    """The system's ``dt`` [s] if it is a definite sampling period > 0, else None.

    python-control keeps ``dt=True`` ("discrete, period unspecified") distinct from
    ``dt=1.0``; ``True == 1.0`` in Python, so test the type, not the value.
    """
    dt = getattr(sys, "dt", None)
    if dt is None or isinstance(dt, (bool, np.bool_)):
        return None
    try:
        dt = float(dt)
    except (TypeError, ValueError):
        return None
    return dt if np.isfinite(dt) and dt > 0 else None


def _check_contents(name: str, sys: object) -> None:
    """Type, SISO and finite (and, for a TF, causal) contents of a control object."""
    if not isinstance(sys, (control.TransferFunction, control.FRD)):
        raise TypeError(
            f"{name} must be a control.TransferFunction or control.FRD, got {type(sys).__name__}"
        )
    if sys.ninputs != 1 or sys.noutputs != 1:
        raise ValueError(f"{name} must be SISO, got {sys.noutputs}x{sys.ninputs}")
    if isinstance(sys, control.TransferFunction):
        _tf_polynomials(name, sys)
    else:
        omega, data = _frd_data(sys)
        bad = int(np.count_nonzero(~np.isfinite(data)) + np.count_nonzero(~np.isfinite(omega)))
        if bad:
            raise ValueError(f"{name} (FRD) has {bad} NaN/inf frequency or response value(s)")


def check_system(name: str, sys: object, fs: float | None = None, *, rate_of: str = "") -> float:
    """Validate a discrete SISO control object and return its loop rate [Hz].

    The one check of what a control object contains, used by every entry point of the
    control layer for plants, controllers and initial controllers: type (``TransferFunction``
    or ``FRD``), SISO, finite coefficients / FRD points, causality of a transfer function
    (numerator degree in ``z`` not above the denominator's: an AO controller cannot use the
    next measurement), and the sampling period. ``dt = 1.0`` is a period of 1 s;
    ``dt = True`` (python-control's "discrete, unspecified") and an FRD that lost ``dt``
    through arithmetic (``dt = 0``) need ``fs``; a continuous-time transfer function is refused.

    Parameters
    ----------
    name : str
        Argument name for error messages (``"plant"``, ``"controller"``, ``"initial"``...).
    sys : control.TransferFunction or control.FRD
        The object to check.
    fs : float, optional
        Expected loop rate [Hz]; required when ``sys`` has no definite ``dt``.
    rate_of : str, optional
        Where ``fs`` comes from, for messages (e.g. ``"the plant"``).

    Returns
    -------
    float
        Loop rate [Hz]: ``1/dt``, or ``fs``.

    Raises
    ------
    TypeError
        If ``sys`` is not a ``control.TransferFunction`` / ``control.FRD``.
    ValueError
        Not SISO; NaN/inf inside; an improper transfer function; a continuous-time transfer
        function; no ``dt`` and no ``fs``; ``fs`` disagreeing with ``dt``.

    Examples
    --------
    >>> check_system("controller", control.tf([0.5], [1.0, -1.0], 1.0))   # dt = 1 s
    1.0
    """
    _check_contents(name, sys)
    dt = _sampling_period(sys)
    is_tf = isinstance(sys, control.TransferFunction)
    if is_tf and not isinstance(sys.dt, (bool, np.bool_)) and (sys.dt is None or sys.dt == 0):
        raise ValueError(
            f"{name} must be a discrete-time transfer function with dt = 1/fs > 0, got "
            f"dt={sys.dt!r} (continuous time); discretise it first (control.sample_system)"
        )
    if fs is None:
        if dt is None:
            why = "python-control drops dt on FRD arithmetic" if not is_tf else "unspecified"
            raise ValueError(
                f"{name} must be discrete-time with dt = 1/fs > 0, got dt={sys.dt!r} ({why}); "
                "pass fs explicitly"
            )
        return 1.0 / dt
    fs = check_positive("fs", fs)
    if dt is not None and not math.isclose(1.0 / dt, fs, rel_tol=1e-9):
        source = f"{rate_of} ({fs!r} Hz)" if rate_of else f"fs={fs!r} Hz"
        raise ValueError(
            f"{name} runs at {1.0 / dt!r} Hz (dt={dt!r} s), expected the rate of {source}"
        )
    return fs


def plant_fs(plant: object, fs: float | None = None) -> float:
    """Loop rate [Hz] of a discrete plant, or ``fs`` when given (must then agree).

    :func:`check_system` with the argument named ``plant``.

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant.
    fs : float, optional
        Loop rate [Hz]; required when the plant has no definite ``dt``.

    Returns
    -------
    float
        Loop rate [Hz].

    Raises
    ------
    TypeError
        If ``plant`` is not a SISO ``control.TransferFunction`` / ``control.FRD``.
    ValueError
        See :func:`check_system`.
    """
    return check_system("plant", plant, fs)


def check_plant(plant: object) -> None:
    """Raise ``TypeError``/``ValueError`` unless ``plant`` is a valid SISO TF or FRD.

    Checks the contents as :func:`check_system` does (finite, causal), not the rate.

    Parameters
    ----------
    plant : object
        Candidate plant.
    """
    _check_contents("plant", plant)


def _frd_hz(sys: control.FRD) -> np.ndarray:
    """Grid of an FRD [Hz] (``omega / 2 pi``)."""
    return np.asarray(sys.omega, dtype=float) / (2 * np.pi)


def _covers_ends(f: np.ndarray, fs: float) -> tuple[bool, bool]:
    """Whether a grid [Hz] (increasing, >= 2 points) reaches 0 Hz and fs/2 (coverage rule).

    An end is reached when the gap to it is at most ``FRD_END_GAP_FRACTION`` of the end grid
    step, plus ``FREQ_RTOL * fs`` for the Hz <-> rad/s rounding; a point past the end by
    rounding (``f[-1] > fs/2`` by an ulp) reaches it too.
    """
    tol = FREQ_RTOL * fs
    covers_zero = f[0] <= FRD_END_GAP_FRACTION * (f[1] - f[0]) + tol
    covers_nyquist = fs / 2 - f[-1] <= FRD_END_GAP_FRACTION * (f[-1] - f[-2]) + tol
    return bool(covers_zero), bool(covers_nyquist)


def check_frd_coverage(name: str, freqs: object, fs: float) -> None:
    """Require a frequency grid (an FRD's, or the one a winding number uses) to span [0, fs/2].

    Stability cannot be certified from a response that was not measured: the winding
    number would close the contour across the missing band. The first point must lie within
    ``FRD_END_GAP_FRACTION`` (0.5) of the first grid step of 0 Hz, the last within that
    fraction of the last step of ``fs/2``.

    Parameters
    ----------
    name : str
        Argument name for the message (e.g. ``"plant"``).
    freqs : control.FRD or array_like, shape (n_freqs,)
        An FRD, or its grid [Hz], increasing.
    fs : float
        Loop rate [Hz].

    Raises
    ------
    ValueError
        Naming the band(s) of [0, fs/2] that the grid does not cover.
    """
    if isinstance(freqs, control.FRD):
        freqs = _frd_hz(freqs)
    f = np.asarray(freqs, dtype=float)
    nyq = fs / 2.0
    if f.size < 2:
        raise ValueError(
            f"{name} must cover [0, fs/2] = [0, {nyq:g}] Hz to certify stability, got "
            f"{f.size} frequency point(s)"
        )
    covers_zero, covers_nyquist = _covers_ends(f, fs)
    missing = []
    if not covers_zero:
        missing.append(f"[0, {f[0]:.6g}] Hz")
    if not covers_nyquist:
        missing.append(f"[{f[-1]:.6g}, {nyq:.6g}] Hz")
    if missing:
        raise ValueError(
            f"{name} must cover [0, fs/2] = [0, {nyq:g}] Hz to certify closed-loop stability "
            f"(winding number), but the band {' and '.join(missing)} is missing; measure the "
            "response there or use a transfer-function model"
        )


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
    outside the FRD's measured range raises, except in a gap to 0 Hz or to fs/2 shorter than
    ``FRD_END_GAP_FRACTION`` of the end grid step (an FRD that covers the band, see
    :func:`check_frd_coverage`), where the end value is held.

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
    fs = check_system("sys", sys, fs)
    freqs = check_finite_array("freqs", freqs, ndim=(0, 1))
    scalar = freqs.ndim == 0
    freqs = np.atleast_1d(freqs)
    if np.any(freqs < 0) or np.any(freqs > fs / 2 + FREQ_RTOL * fs):
        raise ValueError(f"freqs must lie in [0, fs/2] = [0, {fs / 2}] Hz")
    out = frequency_response_unchecked(sys, freqs, fs)
    return out[0] if scalar else out


def frequency_response_unchecked(sys: object, freqs: np.ndarray, fs: float) -> np.ndarray:
    """:func:`frequency_response` of an already validated system on a 1-D grid [Hz].

    Internal to aocontrol (shared by the analysis and the synthesis; not in ``__all__``):
    for inner loops (root refinement, bisection) that evaluate the same checked system many
    times. The public function validates, this one only computes: the caller must have
    checked ``sys`` (:func:`check_system`) and ``freqs`` (1-D, in ``[0, fs/2]``).

    Parameters
    ----------
    sys : control.TransferFunction or control.FRD
        Validated discrete SISO system.
    freqs : numpy.ndarray, shape (n,)
        Frequencies [Hz].
    fs : float
        Loop rate [Hz].

    Returns
    -------
    numpy.ndarray of complex, shape (n,)
    """
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
        tol = FREQ_RTOL * fs
        # An FRD that covers an end of [0, fs/2] (check_frd_coverage) is held constant over
        # the gap of less than half a grid step to it; elsewhere its range is strict. Either
        # way the range is widened by the Hz <-> rad/s rounding tolerance: a grid stored as
        # omega may read back a last point an ulp above fs/2, and a request built from
        # ``fs / 2`` must still fall inside it.
        lo_ok, hi_ok = lo - tol, hi + tol
        if f_grid.size > 1:
            covers_zero, covers_nyquist = _covers_ends(f_grid, fs)
            if covers_zero:
                lo_ok = min(lo_ok, 0.0)
            if covers_nyquist:
                hi_ok = max(hi_ok, fs / 2 + tol)
        if np.any(freqs < lo_ok) or np.any(freqs > hi_ok):
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
    return out


#: Former private name of :func:`frequency_response_unchecked` (same function), kept for code
#: inside :mod:`aocontrol.plant`'s own namespace; other packages use the documented name.
_response = frequency_response_unchecked
