"""Input checks shared by every layer.

Each check raises ``ValueError`` or ``TypeError`` whose message names the argument, the value
received and what was expected, e.g. ``ValueError("fs must be a finite number > 0, got -1.0")``.
"""

from __future__ import annotations

import numbers

import numpy as np

__all__ = [
    "check_positive",
    "check_nonnegative",
    "check_finite_array",
    "check_instance",
    "as_float_array",
    "check_frequency_grid",
    "check_psd",
    "check_nonnegative_psd",
    "check_in_range",
    "check_int",
    "mode_psds",
    "check_broadcast",
    "is_programming_error",
    "PerModeError",
    "PROGRAMMING_ERRORS",
    "MAX_MODES",
]

#: Largest number of modes accepted where a count allocates per-mode arrays (an ELT has
#: ~10^4 controlled modes); beyond this a request is taken for a mistake, not allocated.
MAX_MODES = 100_000

#: Exception types that signal a bug in our code or a wrong call, never a numerical failure:
#: per-mode designs report every other exception for the failing mode and keep the others,
#: and let these propagate.
PROGRAMMING_ERRORS: tuple[type[BaseException], ...] = (
    TypeError,
    AttributeError,
    NameError,
    LookupError,
    AssertionError,
    ImportError,
    NotImplementedError,
    SyntaxError,
    MemoryError,
)


def _short(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def check_positive(name: str, value: object) -> float:
    """Return ``value`` as a float, requiring a finite number > 0."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number > 0, got {_short(value)}")
    value = float(value)
    if not np.isfinite(value) or value <= 0.0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return value


def check_nonnegative(name: str, value: object) -> float:
    """Return ``value`` as a float, requiring a finite number >= 0."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number >= 0, got {_short(value)}")
    value = float(value)
    if not np.isfinite(value) or value < 0.0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return value


def check_in_range(
    name: str,
    value: object,
    low: float,
    high: float,
    *,
    low_inclusive: bool = True,
    high_inclusive: bool = False,
) -> float:
    """Return ``value`` as a float, requiring it to lie in the stated interval."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {_short(value)}")
    value = float(value)
    ok_low = value >= low if low_inclusive else value > low
    ok_high = value <= high if high_inclusive else value < high
    if not (np.isfinite(value) and ok_low and ok_high):
        left = "[" if low_inclusive else "("
        right = "]" if high_inclusive else ")"
        raise ValueError(f"{name} must be in {left}{low}, {high}{right}, got {value!r}")
    return value


def check_int(
    name: str, value: object, *, minimum: int | None = None, maximum: int | None = None
) -> int:
    """Return ``value`` as an int, requiring an integer (not bool) in [``minimum``, ``maximum``]."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {_short(value)}")
    value = int(value)
    if maximum is not None and (value > maximum or (minimum is not None and value < minimum)):
        low = "" if minimum is None else f"[{minimum}, "
        raise ValueError(
            f"{name} must be an integer {'in ' + low if low else '<= '}{maximum}"
            f"{']' if low else ''}, got {value}"
        )
    if minimum is not None and value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value}")
    return value


def check_instance(name: str, value: object, cls: type | tuple[type, ...]) -> object:
    """Return ``value`` if it is an instance of ``cls``, else a ``TypeError`` naming ``name``.

    The type check at a public boundary that takes an object (a mirror, a pupil, a basis):
    a wrong object is named there, not met later as an ``AttributeError`` deep inside.

    Examples
    --------
    >>> check_instance("dm", "dm", int)
    Traceback (most recent call last):
    ...
    TypeError: dm must be a int, got str 'dm'
    """
    if not isinstance(value, cls):
        names = " or ".join(c.__name__ for c in (cls if isinstance(cls, tuple) else (cls,)))
        raise TypeError(f"{name} must be a {names}, got {type(value).__name__} {_short(value)}")
    return value


def as_float_array(name: str, value: object, dtype: type = float) -> np.ndarray:
    """``numpy.asarray(value, dtype)``, a conversion failure named as a ``TypeError``.

    No other check (the real-time path calls it every frame: finiteness is its own policy).

    Raises
    ------
    TypeError
        ``"measurement must be array-like of numbers, got ['a', 'b']"``.
    """
    try:
        return np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be array-like of numbers, got {_short(value)}") from exc


def check_finite_array(
    name: str, value: object, *, ndim: int | tuple[int, ...] | None = None, dtype: type = float
) -> np.ndarray:
    """Return ``value`` as an array, requiring finite entries (and ``ndim`` if given)."""
    arr = as_float_array(name, value, dtype)
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else ndim
        if arr.ndim not in allowed:
            raise ValueError(
                f"{name} must have {' or '.join(map(str, allowed))} dimension(s), "
                f"got shape {arr.shape}"
            )
    if not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise ValueError(f"{name} must contain only finite values, found {bad} NaN/inf")
    return arr


def check_frequency_grid(
    name: str, freqs: object, fs: float, *, allow_zero: bool = True
) -> np.ndarray:
    """Return a 1-D, strictly increasing frequency grid in [0, fs/2] [Hz].

    Raises
    ------
    ValueError
        If the grid is empty, not strictly increasing, negative or beyond Nyquist.
    """
    arr = check_finite_array(name, freqs, ndim=1)
    if arr.size == 0:
        raise ValueError(f"{name} must not be empty")
    if arr.size > 1 and np.any(np.diff(arr) <= 0):
        i = int(np.argmax(np.diff(arr) <= 0))
        raise ValueError(
            f"{name} must be strictly increasing, got {name}[{i}]={arr[i]!r} "
            f">= {name}[{i + 1}]={arr[i + 1]!r}"
        )
    if arr[0] < 0 or (not allow_zero and arr[0] == 0):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be {bound} Hz, got {name}[0]={arr[0]!r}")
    nyquist = fs / 2.0
    if arr[-1] > nyquist * (1 + 1e-12):
        raise ValueError(
            f"{name} must not exceed the Nyquist frequency fs/2={nyquist!r} Hz, "
            f"got {name}[-1]={arr[-1]!r}"
        )
    return arr


def check_nonnegative_psd(name: str, arr: np.ndarray) -> np.ndarray:
    """Return ``arr`` unless it has a negative value (a PSD is >= 0), naming ``name``.

    The one sign check of every PSD the toolbox accepts (disturbance and noise alike).

    Raises
    ------
    ValueError
        ``"psd must be >= 0 everywhere (a PSD), found min -1.0 at index (3,)"``.
    """
    if np.any(arr < 0):
        where = np.unravel_index(int(np.argmin(arr)), arr.shape) if arr.ndim else ()
        raise ValueError(
            f"{name} must be >= 0 everywhere (a PSD), found min {float(arr.min())!r}"
            + (f" at index {tuple(int(i) for i in where)}" if arr.ndim else "")
        )
    return arr


def check_psd(
    name: str,
    psd: object,
    n_freqs: int,
    *,
    allow_scalar: bool = False,
    allow_all_zero: bool = True,
    ndim: int | tuple[int, ...] | None = (1, 2),
) -> np.ndarray:
    """Return a one-sided PSD [units^2/Hz] of shape ``(n_freqs,)`` or ``(n_modes, n_freqs)``.

    A scalar (white PSD) is accepted when ``allow_scalar`` and returned as a 0-d array;
    ``ndim=None`` accepts any leading shape ``(..., n_freqs)``.

    Raises
    ------
    ValueError
        NaN/inf or negative values, a last axis that does not match the frequency grid,
        or (unless ``allow_all_zero``) a PSD that is zero everywhere.
    """
    if ndim is not None and allow_scalar:
        ndim = (0, *((ndim,) if isinstance(ndim, int) else ndim))
    arr = check_finite_array(name, psd, ndim=ndim)
    if arr.ndim >= 1 and arr.shape[-1] != n_freqs:
        raise ValueError(
            f"{name} must have {n_freqs} values along its last axis (one per frequency), "
            f"got shape {arr.shape}"
        )
    if arr.ndim == 0 and not allow_scalar:
        raise ValueError(f"{name} must be an array with {n_freqs} values, got a scalar")
    check_nonnegative_psd(name, arr)
    if not allow_all_zero:
        zero_rows = ~np.any(arr > 0, axis=-1) if arr.ndim >= 1 else np.array(arr == 0)
        if np.any(zero_rows):
            where = f" (rows {np.flatnonzero(zero_rows)[:10].tolist()})" if arr.ndim == 2 else ""
            raise ValueError(f"{name} must not be zero everywhere{where}")
    return arr


def mode_psds(psd: object, noise_psd: object, n_freqs: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """Validate a disturbance and a noise PSD and broadcast both to ``(n_modes, n_freqs)``.

    Parameters
    ----------
    psd : array_like, shape (n_freqs,) or (n_modes, n_freqs)
        Disturbance PSD, one-sided [units^2/Hz], >= 0, finite.
    noise_psd : float or array_like
        Noise PSD, one-sided [units^2/Hz]: a scalar (white, every mode), shape ``(n_freqs,)``
        (every mode), ``(n_modes, n_freqs)``, ``(n_modes, 1)`` or ``(n_modes,)`` (one white
        level per mode; a 1-D array of length ``n_freqs`` is read per frequency).
    n_freqs : int
        Number of frequencies.

    Returns
    -------
    psd, noise : ndarray, shape (n_modes, n_freqs)
    squeeze : bool
        True when the inputs describe a single mode given as 1-D (callers return a scalar).
    """
    psd = check_psd("psd", psd, n_freqs)
    noise = check_finite_array("noise_psd", noise_psd, ndim=(0, 1, 2))
    check_nonnegative_psd("noise_psd", noise)
    n_modes = psd.shape[0] if psd.ndim == 2 else None
    if noise.ndim == 1 and noise.size != n_freqs:
        if n_modes is None or noise.size != n_modes:
            raise ValueError(
                f"noise_psd of shape {noise.shape} must have {n_freqs} values (one per "
                f"frequency) or {n_modes if n_modes is not None else 'n_modes'} (one white "
                "level per mode, with a 2-D psd)"
            )
        noise = noise[:, None]
    if noise.ndim == 2:
        if noise.shape[1] not in (1, n_freqs):
            raise ValueError(f"noise_psd must have 1 or {n_freqs} columns, got {noise.shape}")
        if n_modes is None:
            n_modes = noise.shape[0]
        elif noise.shape[0] != n_modes:
            raise ValueError(f"noise_psd has {noise.shape[0]} modes, psd has {n_modes}")
    squeeze = psd.ndim == 1 and noise.ndim < 2
    n_modes = 1 if n_modes is None else n_modes
    psd2 = np.broadcast_to(psd, (n_modes, n_freqs))
    noise2 = np.broadcast_to(noise if noise.ndim else noise[None, None], (n_modes, n_freqs))
    return psd2, noise2, squeeze


class PerModeError(RuntimeError):
    """Base of the errors of per-mode computations that failed for some modes only.

    A per-mode design or bound keeps every mode that succeeded: the error carries them in
    ``result`` and names the failed modes with their reasons in ``failed`` (the first ten in
    the message). Subclasses: :class:`aocontrol.synthesis.ModalGainError`,
    :class:`aocontrol.analysis.ConstrainedBoundError` and
    :class:`aocontrol.synthesis.DataDrivenError`; ``except PerModeError`` catches them all.

    Parameters
    ----------
    failed : dict of int to str
        Mode index -> reason (exception type and message).
    result : object
        The result over every mode (what the failed modes hold is the subclass' to say).
    n_modes : int
        Number of modes of the computation.
    operation : str
        What failed, for the message (e.g. ``"optimal modal gain"``).
    note : str, default ". The other modes are in this error's .result"
        End of the message.

    Attributes
    ----------
    failed : dict of int to str
    result : object
    """

    def __init__(
        self,
        failed: dict[int, str],
        result: object,
        *,
        n_modes: int,
        operation: str,
        note: str = ". The other modes are in this error's .result",
    ) -> None:
        lines = "; ".join(f"mode {m}: {msg}" for m, msg in list(failed.items())[:10])
        more = f" (and {len(failed) - 10} more)" if len(failed) > 10 else ""
        super().__init__(
            f"{operation} failed for {len(failed)} of {n_modes} modes: {lines}{more}{note}"
        )
        self.failed = failed
        self.result = result


def is_programming_error(exc: BaseException) -> bool:
    """True if ``exc`` is a programming error (see ``PROGRAMMING_ERRORS``), not numerics.

    Parameters
    ----------
    exc : BaseException
        The exception caught while designing one mode.

    Returns
    -------
    bool
        True for ``TypeError``, ``AttributeError``, ``NameError``, ``LookupError``... and for
        anything not derived from ``Exception`` (``KeyboardInterrupt``); False for solver,
        linear-algebra and floating-point failures and ``ValueError``/``RuntimeError``.
    """
    return isinstance(exc, PROGRAMMING_ERRORS) or not isinstance(exc, Exception)


def check_broadcast(name: str, value: object, shape: tuple[int, ...], expected: str) -> np.ndarray:
    """Return ``value`` broadcast to ``shape``, or a ``ValueError`` naming the argument.

    The one check for arrays that are broadcast against the modes/frequencies of another
    argument (PSDs, noise levels, optical gains): a mismatch names ``name``, its shape and
    the expected one instead of surfacing as a bare numpy broadcast error.

    Parameters
    ----------
    name : str
        Argument name.
    value : array_like
        The array (already validated for finiteness).
    shape : tuple of int
        Target shape.
    expected : str
        Human-readable description of the accepted shapes, e.g. ``"(n_modes,) = (3,)"``.

    Returns
    -------
    numpy.ndarray
        Read-only broadcast view of shape ``shape``.

    Raises
    ------
    ValueError
        If ``value`` does not broadcast to ``shape``.

    Examples
    --------
    >>> check_broadcast("gain", [1.0, 2.0], (3,), "scalar or (n_modes,) = (3,)")
    Traceback (most recent call last):
    ...
    ValueError: gain must have shape scalar or (n_modes,) = (3,), got shape (2,)
    """
    arr = np.asarray(value)
    try:
        return np.broadcast_to(arr, shape)
    except ValueError:
        raise ValueError(f"{name} must have shape {expected}, got shape {arr.shape}") from None
