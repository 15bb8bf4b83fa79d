"""The one controller interface of the project and the general IIR bank.

Every controller is a bank of ``n_modes`` independent SISO controllers (modal control):

* ``step(measurement) -> command``: the real-time path, vectorised over modes
  (arrays of shape ``(n_modes,)``), with internal state;
* ``reset()``: back to the zero initial state;
* ``transfer_function(mode=0) -> control.TransferFunction``: the linear controller of one mode,
  ``dt = 1/fs``. The real-time path and the transfer function agree (impulse responses equal
  to rounding; tested for every controller).

The multi-mode controller :class:`~aocontrol.controllers.MultiModeBank` (each command uses
every mode's measurements) honours the same interface, the bad-frame policy below included;
its ``transfer_function(mode)`` raises ``NotImplementedError`` (no per-mode SISO controller
exists) and its transfer matrix is ``frequency_response`` / ``impulse_matrix``.

Real-time policy for bad frames (shared by every controller)
-----------------------------------------------------------
The public :meth:`ControllerBank.step` lives in the base class; subclasses implement the
protected ``_step(m)`` on a validated, finite measurement. A frame whose measurement holds any
NaN or inf is **rejected as a whole**: the controller's state is not touched, the previous
command is returned again (zeros after :meth:`~ControllerBank.reset`), ``n_rejected`` (frames
rejected since the last reset) is incremented and a warning is logged on the first rejection
and then on every 1000th, not on every frame. A real RTC does not stop on one bad frame, and
a rejected frame never poisons the filter history: the commands that follow are exactly those
of the same run with that frame removed and the command held.
"""

from __future__ import annotations

import abc
import functools
import logging
import math
from collections.abc import Sequence

import control
import numpy as np

from aocontrol._deprecation import DeprecatedAttribute, renamed_keyword
from aocontrol._validation import (
    MAX_MODES,
    as_float_array,
    check_broadcast,
    check_finite_array,
    check_int,
    check_positive,
)
from aocontrol.plant import check_system, tf_from_z_inverse, z_inverse_coefficients

__all__ = ["ControllerBank", "IIRBank"]

logger = logging.getLogger(__name__)


def _check_n_modes(n_modes: object) -> int:
    return check_int("n_modes", n_modes, minimum=1, maximum=MAX_MODES)


#: What a controller's ``command_limit`` is (the deprecation warnings of ``stroke`` say it).
_LIMIT_NOTE = "the controller's own limit on its modal command; the DM's stroke is the DM's"


def _check_command_limit(command_limit: object, n: int) -> np.ndarray | None:
    """``command_limit`` as a read-only array of shape (n,) of values > 0, or ``None``."""
    if command_limit is None:
        return None
    s = check_finite_array("command_limit", command_limit, ndim=(0, 1))
    s = check_broadcast("command_limit", s, (n,), f"scalar or (n_modes,) = ({n},)").astype(float)
    if np.any(s <= 0):
        raise ValueError(f"command_limit must be > 0, got min {float(s.min())!r}")
    s.setflags(write=False)
    return s


def _command_limit_in(arrays: dict) -> np.ndarray | None:
    """A controller file's command limit (``stroke`` in files written before its rename)."""
    return arrays.get("command_limit", arrays.get("stroke"))


#: A rejected frame is logged on its first occurrence and then every this many rejections.
_REJECT_LOG_EVERY = 1000


def _all_finite(x: np.ndarray) -> bool:
    """True if every element of the 1-D float array ``x`` is finite (the real-time check).

    A finite ``x . x`` proves every element finite (an inf or NaN element makes it inf or
    NaN), so the common case costs one BLAS dot product, which raises no floating-point
    warning; a non-finite result (a bad element, or elements above ~1e154 whose squares
    overflow) falls back to the element-wise test, which decides.
    """
    return math.isfinite(np.vdot(x, x)) or bool(np.isfinite(x).all())


class ControllerBank(abc.ABC):
    """Abstract bank of per-mode SISO controllers running at ``fs`` [Hz].

    Subclasses implement ``n_modes``, ``fs``, ``_step``, ``reset`` and ``transfer_function``;
    the public :meth:`step` (shape check, rejection of non-finite frames, held command) is
    shared. A subclass's ``reset`` also clears the shared real-time state (``n_rejected`` and
    the held command): the base class wraps it.

    Attributes
    ----------
    n_rejected : int
        Frames rejected since the last reset because their measurement was not finite.
    """

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        own_reset = cls.__dict__.get("reset")
        if own_reset is not None and not getattr(own_reset, "_clears_rt_state", False):

            @functools.wraps(own_reset)
            def reset(self: ControllerBank) -> None:
                own_reset(self)
                self._clear_rt_state()

            reset._clears_rt_state = True  # type: ignore[attr-defined]
            cls.reset = reset  # type: ignore[method-assign]

    @property
    @abc.abstractmethod
    def n_modes(self) -> int:
        """Number of controlled modes."""

    @property
    @abc.abstractmethod
    def fs(self) -> float:
        """Loop rate [Hz]."""

    def step(self, measurement: np.ndarray) -> np.ndarray:
        """Advance one frame: modal measurement ``(n_modes,)`` -> modal command ``(n_modes,)``.

        Real-time policy: a measurement with any NaN or inf is rejected as a whole. The
        state is not touched, the previous command is returned (zeros after a reset),
        ``n_rejected`` is incremented and a warning is logged (first rejection, then every
        1000th). Otherwise the subclass's ``_step`` computes the command.

        Parameters
        ----------
        measurement : array_like, shape (n_modes,)
            Modal measurement of this frame (the unit of the controller's input).

        Returns
        -------
        numpy.ndarray, shape (n_modes,)
            Modal command (a new array; the held command is returned as a copy).

        Raises
        ------
        ValueError
            If ``measurement`` does not have shape ``(n_modes,)``.
        """
        m = self._check_measurement(measurement)
        if not _all_finite(m):
            return self._reject(m)
        u = self._step(m)
        # A copy: a caller that edits the returned command in place cannot change the held one.
        self._last_command = u.copy()
        return u

    @abc.abstractmethod
    def _step(self, m: np.ndarray) -> np.ndarray:
        """One frame of the controller on a finite measurement ``m`` of shape ``(n_modes,)``."""

    @abc.abstractmethod
    def reset(self) -> None:
        """Reset the internal state to zero."""

    @abc.abstractmethod
    def transfer_function(self, mode: int = 0) -> control.TransferFunction:
        """Linear controller of ``mode`` (measurement to command), ``dt = 1/fs``."""

    # -- real-time state shared by every controller ----------------------------------------
    @property
    def n_rejected(self) -> int:
        """Frames rejected since the last reset (non-finite measurement)."""
        return self.__dict__.get("_n_rejected", 0)

    def _clear_rt_state(self) -> None:
        self._n_rejected = 0
        self._last_command = None

    def _reject(self, m: np.ndarray) -> np.ndarray:
        n = self.n_rejected + 1
        self._n_rejected = n
        if n == 1 or n % _REJECT_LOG_EVERY == 0:
            bad = np.flatnonzero(~np.isfinite(m))
            logger.warning(
                "%s: frame rejected, measurement not finite for %d mode(s) (first %s); "
                "command held (%d frame(s) rejected since reset)",
                type(self).__name__,
                bad.size,
                bad[:10].tolist(),
                n,
            )
        last = self.__dict__.get("_last_command")
        return np.zeros(self.n_modes) if last is None else last.copy()

    # -- shared helpers -------------------------------------------------------------------
    def _check_mode(self, mode: int) -> int:
        mode = check_int("mode", mode, minimum=0)
        if mode >= self.n_modes:
            raise ValueError(f"mode must be in [0, {self.n_modes - 1}], got {mode}")
        return mode

    def _check_measurement(self, measurement: object) -> np.ndarray:
        # A float64 array (the simulator's frames) is taken as it is: np.asarray would
        # return it unchanged, at a call's cost on the real-time path.
        if type(measurement) is np.ndarray and measurement.dtype == np.float64:
            m = measurement
        else:
            m = as_float_array("measurement", measurement)
        if m.shape != (self.n_modes,):
            raise ValueError(
                f"measurement must have shape ({self.n_modes},) (one value per mode), got {m.shape}"
            )
        return m

    def impulse_response(self, n_samples: int) -> np.ndarray:
        """Response of ``step()`` to a unit impulse on every mode, shape ``(n_samples, n_modes)``.

        The controller is reset before and after.
        """
        n_samples = check_int("n_samples", n_samples, minimum=1)
        self.reset()
        out = np.empty((n_samples, self.n_modes))
        x = np.ones(self.n_modes)
        for k in range(n_samples):
            out[k] = self.step(x)
            x = np.zeros(self.n_modes)
        self.reset()
        return out


class IIRBank(ControllerBank):
    """Bank of IIR filters in Direct-Form I, one per mode (the paper's command equation)::

        u[k] = sum_{i=0}^{nb-1} b_i m[k-i] - sum_{i=1}^{na-1} a_i u[k-i]

    with ``a_0 = 1``. With a command limit the command is clipped to
    ``[-command_limit, command_limit]`` and the *applied* command is what enters the recursion
    (anti-windup: the filter state stays consistent with what the DM did).

    Real-time implementation: the past inputs and commands of all modes sit side by side in
    a circular buffer stored twice (so that the last ``max(nb, na)`` frames are always one
    contiguous block); a frame writes one row and computes every mode's two sums with one
    multiply and one reduction, with no history shifted. Each sum is accumulated in a fixed
    order, tap by tap (``b_0 m[k] + b_1 m[k-1] + ...``, then ``-a_1 u[k-1] - ...``, the two
    added last), so the command is the same bit for bit on every machine; it differs from
    another summation order (e.g. ``scipy.signal.lfilter``) by rounding only.

    Parameters
    ----------
    b : array_like, shape (n_modes, nb) or (nb,)
        Numerator coefficients in powers of ``z^-1`` (a 1-D array is shared by every mode).
    a : array_like, shape (n_modes, na) or (na,)
        Denominator coefficients in powers of ``z^-1``; ``a[:, 0]`` must be nonzero and is
        normalised to 1.
    fs : float
        Loop rate [Hz].
    n_modes : int, optional
        Number of modes when both ``b`` and ``a`` are 1-D (default 1).
    command_limit : float or array of shape (n_modes,), optional
        The controller's own limit on its modal command (same unit as the command, > 0),
        with anti-windup; ``None`` for no limit. A controller setting, not the DM's stroke
        (which the simulator's :class:`~aocontrol.sim.dm.ModalDM` owns and applies after the
        controller); ``stroke`` is its deprecated name.

    Attributes
    ----------
    n_saturated : numpy.ndarray of int, shape (n_modes,)
        Number of frames each mode's command was clipped since the last reset.

    Examples
    --------
    >>> bank = IIRBank(b=[0.5], a=[1.0, -1.0], fs=1000.0, n_modes=2)  # integrators, g = 0.5
    >>> bank.step(np.array([1.0, 2.0]))
    array([0.5, 1. ])
    >>> bank.step(np.array([1.0, 2.0]))
    array([1., 2.])
    """

    #: Deprecated name of :attr:`command_limit`.
    stroke = DeprecatedAttribute("command_limit", _LIMIT_NOTE)

    @renamed_keyword("stroke", "command_limit", _LIMIT_NOTE)
    def __init__(
        self,
        b: object,
        a: object,
        fs: float,
        *,
        n_modes: int | None = None,
        command_limit: float | np.ndarray | None = None,
    ) -> None:
        self._fs = check_positive("fs", fs)
        b = check_finite_array("b", b, ndim=(1, 2))
        a = check_finite_array("a", a, ndim=(1, 2))
        rows = {x.shape[0] for x in (b, a) if x.ndim == 2}
        if len(rows) > 1:
            raise ValueError(f"b and a must have the same number of modes, got {sorted(rows)}")
        if rows:
            n = rows.pop()
            if n_modes is not None and _check_n_modes(n_modes) != n:
                raise ValueError(f"n_modes={n_modes} disagrees with coefficient rows {n}")
        else:
            n = 1 if n_modes is None else _check_n_modes(n_modes)
        if n < 1:
            raise ValueError(f"n_modes must be >= 1, got {n}")
        b = np.broadcast_to(b, (n, b.shape[-1])).astype(float)
        a = np.broadcast_to(a, (n, a.shape[-1])).astype(float)
        if b.shape[1] < 1 or a.shape[1] < 1:
            raise ValueError("b and a must each have at least one coefficient per mode")
        if np.any(a[:, 0] == 0):
            bad = np.flatnonzero(a[:, 0] == 0)[:10].tolist()
            raise ValueError(f"a[:, 0] must be nonzero (causal filter), zero for modes {bad}")
        b = b / a[:, :1]
        a = a / a[:, :1]
        b.setflags(write=False)
        a.setflags(write=False)
        self._b, self._a = b, a
        self._n = n
        self._limit = _check_command_limit(command_limit, n)
        self.reset()

    # -- interface ------------------------------------------------------------------------
    @property
    def n_modes(self) -> int:
        return self._n

    @property
    def fs(self) -> float:
        return self._fs

    @property
    def b(self) -> np.ndarray:
        """Numerator coefficients, shape ``(n_modes, nb)`` (read-only)."""
        return self._b

    @property
    def a(self) -> np.ndarray:
        """Denominator coefficients, shape ``(n_modes, na)``, ``a[:, 0] == 1`` (read-only)."""
        return self._a

    @property
    def command_limit(self) -> np.ndarray | None:
        """The controller's limit on its command per mode, shape (n_modes,), or ``None``."""
        return self._limit

    def reset(self) -> None:
        n, nb, na = self._n, self._b.shape[1], self._a.shape[1]
        depth = max(nb, na)
        if not hasattr(self, "_taps"):
            # Tap weights over the history window, shape (depth, 2 n): columns [0, n) weigh
            # the inputs m[k - i] (b_i), columns [n, 2 n) the commands u[k - i] (-a_i, i >= 1;
            # row 0 is the command being computed, weight 0). Zero rows pad the shorter side.
            taps = np.zeros((depth, 2 * n))
            taps[:nb, :n] = self._b.T
            taps[1:na, n:] = -self._a[:, 1:].T
            taps.setflags(write=False)
            self._taps = taps
            self._products = np.empty((depth, 2 * n))
            self._sums = np.empty(2 * n)
        # History row r holds (m, u) of one frame; rows r and r + depth are the same frame, so
        # that the window [head, head + depth) is contiguous, newest first.
        self._history = np.zeros((2 * depth, 2 * n))
        self._head = 0
        self.n_saturated = np.zeros(n, dtype=np.int64)

    def set_history(self, measurements: object, commands: object) -> None:
        """Set the filter state from past frames: a bumpless start inside a running loop.

        The Direct-Form I state *is* the past inputs and outputs, so after this call the next
        ``step(m[k])`` returns ``sum_i b_i m[k-i] - sum_i a_i u[k-i]`` with ``m[k-1], m[k-2],
        ...`` the last rows of ``measurements`` and ``u[k-1], ...`` the last rows of
        ``commands``: the command the filter would give had it been running on the same loop
        (the commands actually applied, as with anti-windup). Rows missing for a short history
        count as zeros. Counters (``n_saturated``, ``n_rejected``) are not touched.

        Parameters
        ----------
        measurements : array_like, shape (n_frames, n_modes)
            Past measurements, oldest first (``n_frames >= 0``).
        commands : array_like, shape (n_frames', n_modes)
            Past commands, oldest first.

        Raises
        ------
        ValueError
            If the arrays are not finite or not ``(n_frames, n_modes)``.

        Examples
        --------
        >>> bank = IIRBank(b=[0.5], a=[1.0, -1.0], fs=1000.0)         # integrator, g = 0.5
        >>> bank.set_history(np.array([[0.0]]), np.array([[3.0]]))   # u[k-1] = 3
        >>> bank.step(np.array([2.0]))                               # 3 + 0.5 * 2
        array([4.])
        """
        hist = []
        for name, value in (("measurements", measurements), ("commands", commands)):
            arr = check_finite_array(name, value, ndim=2)
            if arr.shape[1] != self._n:
                raise ValueError(
                    f"{name} must have shape (n_frames, {self._n}) (one column per mode), "
                    f"got {arr.shape}"
                )
            hist.append(arr)
        m, u = hist
        n, depth = self._n, self._taps.shape[0]
        # Layout of reset(): the next step writes frame k at row depth - 1 when head is 0, so
        # frame k - i (i >= 1) sits at row i - 1 and its copy at row i - 1 + depth.
        self._history[:] = 0.0
        self._head = 0
        for i in range(1, depth):
            if i <= m.shape[0]:
                self._history[[i - 1, i - 1 + depth], :n] = m[-i]
            if i <= u.shape[0]:
                self._history[[i - 1, i - 1 + depth], n:] = u[-i]
        self._last_command = u[-1].copy() if u.shape[0] else None

    def _recursion_state(self) -> tuple | None:
        """The state of the plain recursion, for the simulator's fused frame loop.

        ``aocontrol.sim._stage_run`` runs the frames of a chunk of a linear stage in one loop
        that performs, per frame, exactly the operations of :meth:`step` on a finite
        measurement (same values bit for bit, tested), without the per-call checks it makes
        redundant (its measurements are finite by construction; a non-finite command is
        reported with the same ``FloatingPointError``). Only for this class's own
        :meth:`step` and ``_step`` and no command limit.

        Returns
        -------
        tuple or None
            ``(taps, history, products, sums)`` (the layout of :meth:`reset`; the loop moves
            ``_head`` and sets the held command when it ends), or ``None`` when the bank
            is not the plain recursion (a command limit, or a subclass that changes
            ``step`` or ``_step``).
        """
        cls = type(self)
        if (
            self._limit is not None
            or cls._step is not IIRBank._step
            or cls.step is not ControllerBank.step
        ):
            return None
        return self._taps, self._history, self._products, self._sums

    def _step(self, m: np.ndarray) -> np.ndarray:
        n = self._n
        depth = self._taps.shape[0]
        head = self._head = (self._head - 1) % depth
        hist = self._history
        hist[head, :n] = m
        hist[head + depth, :n] = m
        # The stale command in row `head` (a frame `depth` old, finite) has weight 0.
        products = np.multiply(self._taps, hist[head : head + depth], out=self._products)
        if depth == 2:  # the reduction of two rows is one sum, in the same order
            sums = np.add(products[0], products[1], out=self._sums)
        else:
            sums = np.add.reduce(products, axis=0, out=self._sums)
        u = sums[:n] + sums[n:]
        if self._limit is not None:
            clipped = np.abs(u) > self._limit
            if clipped.any():
                self.n_saturated += clipped
                u = np.clip(u, -self._limit, self._limit)
        if not _all_finite(u):
            bad = np.flatnonzero(~np.isfinite(u))[:10].tolist()
            raise FloatingPointError(f"controller command is not finite for modes {bad}")
        hist[head, n:] = u
        hist[head + depth, n:] = u
        return u

    def transfer_function(self, mode: int = 0) -> control.TransferFunction:
        mode = self._check_mode(mode)
        return tf_from_z_inverse(self._b[mode], self._a[mode], 1.0 / self._fs)

    # -- row operations -------------------------------------------------------------------
    # The one home of a bank's row operations (take rows, replace rows, choose per mode,
    # build from ragged rows): orders are padded with zeros, the command limit follows its
    # rows.
    @classmethod
    def from_rows(
        cls,
        b_rows: Sequence[object],
        a_rows: Sequence[object],
        fs: float,
        *,
        command_limit: float | np.ndarray | None = None,
    ) -> IIRBank:
        """Bank from one coefficient row per mode, of any lengths (padded with zeros).

        Parameters
        ----------
        b_rows, a_rows : sequence of array_like, each 1-D
            Numerator and denominator of each mode in powers of ``z^-1``.
        fs : float
            Loop rate [Hz].
        command_limit : float or array of shape (n_modes,), optional
            As for :class:`IIRBank`.

        Examples
        --------
        >>> bank = IIRBank.from_rows([[0.5], [0.2, 0.1]], [[1.0, -1.0], [1.0]], fs=1000.0)
        >>> bank.b.tolist(), bank.a.tolist()
        ([[0.5, 0.0], [0.2, 0.1]], [[1.0, -1.0], [1.0, 0.0]])
        """
        if len(b_rows) != len(a_rows) or len(b_rows) == 0:
            raise ValueError(
                f"b_rows and a_rows must hold one row per mode (at least one), got "
                f"{len(b_rows)} and {len(a_rows)}"
            )
        return cls(_pad_rows("b_rows", b_rows), _pad_rows("a_rows", a_rows), fs,
                   command_limit=command_limit)  # fmt: skip

    @classmethod
    def from_parts(cls, parts: Sequence[tuple[object, IIRBank]], n_modes: int) -> IIRBank:
        """One bank from banks for disjoint sets of modes that together cover ``n_modes``.

        Parameters
        ----------
        parts : sequence of (modes, IIRBank)
            Mode indices and the bank of their filters, in that order (same rate). Each part's
            command limits follow its rows (none if any part has none).
        n_modes : int
            Modes of the result; every one in exactly one part.
        """
        b_rows: list = [None] * n_modes
        a_rows: list = [None] * n_modes
        limit = np.full(n_modes, np.nan)
        for modes, bank in parts:
            idx = np.atleast_1d(np.asarray(modes, dtype=int))
            if idx.size != bank.n_modes:
                raise ValueError(f"a part has {idx.size} mode indices for {bank!r}")
            for j, i in enumerate(idx):
                if b_rows[i] is not None:
                    raise ValueError(f"mode {i} is in two parts")
                b_rows[i], a_rows[i] = bank.b[j], bank.a[j]
            if bank.command_limit is not None:
                limit[idx] = bank.command_limit
        missing = [i for i, r in enumerate(b_rows) if r is None]
        if missing:
            raise ValueError(f"parts do not cover modes {missing[:10]} of {n_modes}")
        fs = parts[0][1].fs
        return cls.from_rows(
            b_rows, a_rows, fs, command_limit=None if np.isnan(limit).any() else limit
        )

    def rows(self, modes: object) -> IIRBank:
        """The filters of ``modes`` (indices or a boolean mask) as a bank of their own, with
        their command limits."""
        idx = self._mode_index("modes", modes)
        limit = None if self._limit is None else self._limit[idx]
        return IIRBank(self._b[idx], self._a[idx], self._fs, command_limit=limit)

    def trim_orders(self) -> IIRBank:
        """The same filters without the coefficient columns that are zero in every mode."""
        nb = max(1, int(np.flatnonzero(np.any(self._b != 0, axis=0)).max(initial=0)) + 1)
        na = max(1, int(np.flatnonzero(np.any(self._a != 0, axis=0)).max(initial=0)) + 1)
        return IIRBank(self._b[:, :nb], self._a[:, :na], self._fs, command_limit=self._limit)

    def with_rows(self, modes: object, other: IIRBank) -> IIRBank:
        """This bank with the filters of ``modes`` replaced by ``other``'s rows, in order.

        ``other`` holds one filter per selected mode (its command limit is not used: the
        limits stay this bank's).
        """
        idx = self._mode_index("modes", modes)
        if not isinstance(other, IIRBank) or other.n_modes != idx.size:
            raise ValueError(
                f"other must be an IIRBank of {idx.size} modes (one per selected mode), got "
                f"{other!r}"
            )
        if abs(other.fs - self._fs) > 1e-9 * self._fs:
            raise ValueError(f"other runs at fs={other.fs!r} Hz, this bank at {self._fs!r} Hz")
        nb = max(self._b.shape[1], other.b.shape[1])
        na = max(self._a.shape[1], other.a.shape[1])
        b, a = _pad(self._b, nb), _pad(self._a, na)
        b[idx], a[idx] = _pad(other.b, nb), _pad(other.a, na)
        return IIRBank(b, a, self._fs, command_limit=self._limit)

    def where(self, take: object, other: IIRBank) -> IIRBank:
        """Per mode, ``other``'s filter where ``take`` is True, this bank's elsewhere.

        Parameters
        ----------
        take : array_like of bool, shape (n_modes,)
        other : IIRBank
            Same number of modes and rate.
        """
        take = np.asarray(take, dtype=bool)
        if take.shape != (self._n,):
            raise ValueError(f"take must be a boolean array of shape ({self._n},), got "
                             f"{take.shape}")  # fmt: skip
        if not take.any():
            return self.rows(np.arange(self._n))
        return self.with_rows(np.flatnonzero(take), other.rows(take))

    def _mode_index(self, name: str, modes: object) -> np.ndarray:
        idx = np.asarray(modes)
        if idx.dtype == bool:
            if idx.shape != (self._n,):
                raise ValueError(f"{name} as a mask must have shape ({self._n},), got "
                                 f"{idx.shape}")  # fmt: skip
            return np.flatnonzero(idx)
        idx = np.atleast_1d(idx).astype(int, casting="unsafe").ravel()
        if idx.size and (idx.min() < 0 or idx.max() >= self._n):
            raise ValueError(f"{name} must be mode indices in [0, {self._n - 1}], got "
                             f"{idx.tolist()[:10]}")  # fmt: skip
        return idx

    # -- constructors ---------------------------------------------------------------------
    @classmethod
    @renamed_keyword("stroke", "command_limit", _LIMIT_NOTE)
    def from_transfer_functions(
        cls,
        tfs: list[control.TransferFunction],
        *,
        command_limit: float | np.ndarray | None = None,
    ) -> IIRBank:
        """Bank from one discrete SISO transfer function per mode (same ``dt``).

        ``command_limit`` as for :class:`IIRBank` (``stroke``: its deprecated name).
        """
        if len(tfs) == 0:
            raise ValueError("tfs must contain at least one transfer function")
        # Each one discrete (dt = True, "unspecified", is refused), causal, finite, and at
        # the rate of the first.
        fs = check_system("tfs[0]", tfs[0])
        for i, t in enumerate(tfs[1:], start=1):
            check_system(f"tfs[{i}]", t, fs, rate_of="tfs[0]")
        if not all(isinstance(t, control.TransferFunction) for t in tfs):
            raise TypeError("tfs must all be control.TransferFunction (not FRD)")
        coeffs = [z_inverse_coefficients(t, f"tfs[{i}]") for i, t in enumerate(tfs)]
        return cls.from_rows([c[0] for c in coeffs], [c[1] for c in coeffs], fs,
                             command_limit=command_limit)  # fmt: skip

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(n_modes={self._n}, fs={self._fs}, "
            f"nb={self._b.shape[1]}, na={self._a.shape[1]})"
        )


def _pad(x: np.ndarray, width: int) -> np.ndarray:
    """Rows of ``x`` padded with zeros to ``width`` columns (a copy)."""
    out = np.zeros((x.shape[0], width))
    out[:, : x.shape[1]] = x
    return out


def _pad_rows(name: str, rows: Sequence[object]) -> np.ndarray:
    """Ragged 1-D rows as one zero-padded 2-D array."""
    arrs = [np.atleast_1d(np.asarray(r, dtype=float)) for r in rows]
    for i, r in enumerate(arrs):
        if r.ndim != 1 or r.size == 0:
            raise ValueError(f"{name}[{i}] must be a non-empty 1-D row, got shape {r.shape}")
    out = np.zeros((len(arrs), max(r.size for r in arrs)))
    for i, r in enumerate(arrs):
        out[i, : r.size] = r
    return out
