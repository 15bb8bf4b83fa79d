"""A multi-mode controller: a matrix FIR predictor acting on the pseudo-open loop.

A modal bank gives each mode a filter of its own measurements. Frozen-flow turbulence moves
phase across the pupil, so the past of one mode predicts another; a multi-mode predictor
uses every mode's past for every command. This module runs such a predictor in the loop,
behind the one controller interface (:class:`~aocontrol.controllers.ControllerBank`).

Conventions (those of :mod:`aocontrol.plant` and :mod:`aocontrol.synthesis`): the loop plant
is ``G(z) = z^-1 ((1 - f) z^-k + f z^-(k+1))`` with ``(k, f) =
split_latency(latency_frames)`` (scalar, the same for every mode), the measurement
``m = z^-1 e + n`` and the residual ``e = d - DM(u)``. Per frame ``k`` the controller

1. rebuilds the pseudo-open loop (POL) ``p[k] = m[k] + (1 - f) u[k-1-k] + f u[k-2-k]``
   from the commands it applied (``p = z^-1 d + n`` whatever the controller);
2. predicts ``u[k] = sum_{j < h} A_j p[k-j]`` (``h`` the history, ``A_j`` of shape
   ``(n_modes, n_modes)``): one matrix-vector product ``[A_0 | ... | A_{h-1}] @ [p[k]; ...;
   p[k-h+1]]`` per frame;
3. clips ``u`` to its command limit, if any, and keeps the *applied* command for step 1.

As a transfer matrix the controller is ``K = (I - F G)^-1 F`` with ``F(z) = sum_j A_j z^-j``
(the Youla form with the stable plant ``G``): with the loop's plant equal to the model,
``S = (I + G K)^-1 = I - G F`` and ``K S = F``, so every closed-loop map is an FIR filter,
the loop is stable by construction (all closed-loop poles at ``z = 0``) and the
multivariable modulus margin is ``min sigma_min(I + G K) = 1 / max sigma_max(I - G F)`` on
the circle (:func:`aocontrol.analysis.multimode_certificate`). The controller itself need
not be stable: its poles are the zeros of ``det(I - F G)``.

Anti-windup is exact: a clipped command enters step 1 as applied, so the POL stays
``z^-1 d + n`` and the predictor sees no windup at all (a DM clip *after* the controller,
not told to it, breaks that: give the controller a ``command_limit`` at or inside the DM's).

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
"""

from __future__ import annotations

import control
import numpy as np

from aocontrol._validation import check_finite_array, check_int, check_positive
from aocontrol.controllers._base import (
    ControllerBank,
    _all_finite,
    _check_command_limit,
    _command_limit_in,
)
from aocontrol.plant import split_latency

__all__ = ["MultiModeBank", "PRECISIONS"]

#: Precisions of the real-time product: ``"float32"`` (default: half the memory traffic of
#: the matrix, the bound of a frame's cost) and ``"float64"``.
PRECISIONS = ("float32", "float64")


class MultiModeBank(ControllerBank):
    """Multi-mode controller: a matrix FIR predictor on the pseudo-open loop (module doc).

    ``u[k] = sum_{j < h} A_j p[k-j]`` with ``p[k] = m[k] + (1 - f) u[k-1-k0] + f u[k-2-k0]``
    the pseudo-open loop rebuilt from the applied commands, ``(k0, f) =
    split_latency(latency_frames)``.

    Real-time path: the last ``h`` POL frames sit newest first in a circular buffer stored
    twice (the window is always one contiguous block, nothing is shifted), so a frame is one
    matrix-vector product ``M @ window`` with ``M = [A_0 | A_1 | ... | A_{h-1}]`` of shape
    ``(n_modes, h n_modes)``, plus ``O(n_modes)`` work. With ``precision="float32"`` the
    matrix and the POL window are stored in single precision and the product accumulates in
    single precision (BLAS ``sgemv``): the command differs from the float64 product by a
    rounding error of at most ``h n_modes 2^-24 sum_i |M_ki| |x_i|`` (the classical bound)
    and typically ``sqrt(h n_modes) 2^-24`` of it, i.e. ~1e-6 of the command RMS for 540
    modes and ``h = 5`` (tested: below 1e-4 of the command's scale); the POL itself is
    rebuilt in float64. That error enters the loop as a white command noise ~1e-6 of the
    command, ~1e-12 of its variance: far below any residual. (The certificate of
    :func:`aocontrol.analysis.multimode_certificate` is of the float64 taps; storing them in
    float32 moves ``sigma_max(I - G F)`` by at most ``2^-24 sum_j ||A_j||_F``.)

    The bad-frame policy is the base class's (:class:`ControllerBank`): a non-finite
    measurement is rejected whole, the state is not touched, the command is held.

    Parameters
    ----------
    taps : array_like, shape (h, n_modes, n_modes)
        Predictor matrices ``A_j`` [command units per measurement unit], ``h >= 1``;
        ``taps[j][i, l]`` weighs mode ``l``'s POL ``j`` frames ago in mode ``i``'s command.
    fs : float
        Loop rate [Hz].
    latency_frames : float
        RTC latency beyond the one-frame WFS integration [frames] of the plant model the POL
        is rebuilt with (:func:`aocontrol.plant.loop_plant`'s).
    command_limit : float or array_like of shape (n_modes,), optional
        The controller's own limit on its modal command (same unit, > 0), with exact
        anti-windup (the applied command enters the POL); ``None`` for no limit.
    precision : {"float32", "float64"}, default "float32"
        Precision of the real-time product (see above).

    Attributes
    ----------
    n_saturated : numpy.ndarray of int, shape (n_modes,)
        Frames each mode's command was clipped since the last reset.

    Raises
    ------
    ValueError
        Taps not finite or not of shape ``(h, n, n)`` with ``h >= 1``, a bad ``fs``,
        ``latency_frames``, ``command_limit`` or ``precision``.

    Examples
    --------
    One mode, no latency beyond the WFS frame, ``u = 0.5 p``: the POL is ``m + u[k-1]``.

    >>> bank = MultiModeBank([[[0.5]]], fs=1000.0, latency_frames=0.0, precision="float64")
    >>> [float(bank.step(np.array([x]))[0]) for x in (2.0, 0.0, 0.0)]
    [1.0, 0.5, 0.25]
    """

    def __init__(
        self,
        taps: object,
        fs: float,
        latency_frames: float,
        *,
        command_limit: float | np.ndarray | None = None,
        precision: str = "float32",
    ) -> None:
        a = check_finite_array("taps", taps, ndim=3)
        h, n, n2 = a.shape
        if h < 1 or n < 1 or n != n2:
            raise ValueError(
                f"taps must have shape (history, n_modes, n_modes) with history >= 1 and "
                f"n_modes >= 1, got {a.shape}"
            )
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {list(PRECISIONS)}, got {precision!r}")
        self._fs = check_positive("fs", fs)
        self._k0, self._frac = split_latency(latency_frames)
        self._latency = float(latency_frames)
        a = np.array(a, dtype=float)
        a.setflags(write=False)
        self._taps = a
        self._h, self._n = h, n
        self._precision = precision
        dtype = np.float32 if precision == "float32" else np.float64
        # M = [A_0 | A_1 | ... | A_{h-1}], C order: row i holds mode i's weights over the
        # window [p[k]; p[k-1]; ...], newest first.
        matrix = np.ascontiguousarray(a.transpose(1, 0, 2).reshape(n, h * n), dtype=dtype)
        matrix.setflags(write=False)
        self._matrix = matrix
        self._limit = _check_command_limit(command_limit, n)
        # Weights of the two delayed commands in the POL, u[k-1-k0] and u[k-2-k0].
        self._w1, self._w2 = 1.0 - self._frac, self._frac
        self._depth = self._k0 + 2  # command slots: u[k - i] at (k - i) % depth
        self.reset()

    # -- interface ------------------------------------------------------------------------
    @property
    def n_modes(self) -> int:
        return self._n

    @property
    def fs(self) -> float:
        return self._fs

    @property
    def taps(self) -> np.ndarray:
        """Predictor matrices ``A_j``, shape ``(history, n_modes, n_modes)`` (read-only)."""
        return self._taps

    @property
    def history(self) -> int:
        """Number of POL frames ``h`` each command uses."""
        return self._h

    @property
    def latency_frames(self) -> float:
        """Latency of the plant model the POL is rebuilt with [frames]."""
        return self._latency

    @property
    def precision(self) -> str:
        """Precision of the real-time product (``"float32"`` or ``"float64"``)."""
        return self._precision

    @property
    def command_limit(self) -> np.ndarray | None:
        """The controller's limit on its command per mode, shape (n_modes,), or ``None``."""
        return self._limit

    def reset(self) -> None:
        n, h = self._n, self._h
        # POL window rows r and r + h are the same frame; [head, head + h) newest first.
        self._window = np.zeros((2 * h, n), dtype=self._matrix.dtype)
        self._head = 0
        self._commands = np.zeros((self._depth, n))
        self._frame = 0
        self._pol = np.empty(n)
        self._out = np.empty(n, dtype=self._matrix.dtype)
        self.n_saturated = np.zeros(n, dtype=np.int64)

    def _step(self, m: np.ndarray) -> np.ndarray:
        h, depth, k = self._h, self._depth, self._frame
        cmd = self._commands
        # p[k] = m[k] + (1 - f) u[k-1-k0] + f u[k-2-k0]; with depth = k0 + 2 these sit in
        # the slots (k + 1) % depth and k % depth (the latter is overwritten below by u[k]).
        pol = np.multiply(cmd[(k + 1) % depth], self._w1, out=self._pol)
        pol += m
        if self._w2:
            pol += self._w2 * cmd[k % depth]
        head = self._head = (self._head - 1) % h
        win = self._window
        win[head] = pol
        win[head + h] = pol
        np.dot(self._matrix, win[head : head + h].reshape(-1), out=self._out)
        u = self._out.astype(np.float64)
        if self._limit is not None:
            clipped = np.abs(u) > self._limit
            if clipped.any():
                self.n_saturated += clipped
                u = np.clip(u, -self._limit, self._limit)
        if not _all_finite(u):
            bad = np.flatnonzero(~np.isfinite(u))[:10].tolist()
            raise FloatingPointError(f"controller command is not finite for modes {bad}")
        cmd[k % depth] = u
        self._frame = (k + 1) % depth
        return u

    def set_history(self, measurements: object, commands: object) -> None:
        """Set the state from past frames: a bumpless start inside a running loop.

        The state is the last ``h`` POL frames and the last ``k0 + 2`` applied commands, so
        after this call the next ``step(m[k])`` returns the command the bank would give had
        it been running on the same loop (the commands actually applied). The POL of the
        given frames is rebuilt with this bank's plant model; frames before the first row
        count as zeros (give at least ``h + k0 + 1`` rows for an exact start). Counters
        (``n_saturated``, ``n_rejected``) are not touched.

        Parameters
        ----------
        measurements : array_like, shape (n_frames, n_modes)
            Past measurements, oldest first.
        commands : array_like, shape (n_frames, n_modes)
            Commands applied at the same frames, oldest first.

        Raises
        ------
        ValueError
            If the arrays are not finite or not both ``(n_frames, n_modes)``.
        """
        m = check_finite_array("measurements", measurements, ndim=2)
        u = check_finite_array("commands", commands, ndim=2)
        if m.shape[1] != self._n or u.shape != m.shape:
            raise ValueError(
                f"measurements and commands must both have shape (n_frames, {self._n}), got "
                f"{m.shape} and {u.shape}"
            )
        n_frames, h, depth = m.shape[0], self._h, self._depth
        pol = m.copy()
        for lag, w in ((self._k0 + 1, self._w1), (self._k0 + 2, self._w2)):
            if w and lag < n_frames:
                pol[lag:] += w * u[: n_frames - lag]
        self._zero_state()
        # Layout of reset(): the next step writes frame k at row h - 1 (head 0 -> h - 1), so
        # frame k - j (1 <= j < h) sits at row h - 1 + j and its copy at row j - 1.
        for j in range(1, h):
            if j <= n_frames:
                self._window[[j - 1, h - 1 + j]] = pol[-j]
        for i in range(1, depth + 1):
            if i <= n_frames:
                self._commands[(-i) % depth] = u[-i]
        self._last_command = u[-1].copy() if n_frames else None

    def _zero_state(self) -> None:
        """Zero the filter state (POL window, command line), keeping the counters."""
        self._window[:] = 0.0
        self._head = 0
        self._commands[:] = 0.0
        self._frame = 0

    def transfer_function(self, mode: int = 0) -> control.TransferFunction:
        """Not defined: a multi-mode controller has no per-mode SISO transfer function.

        Each command depends on every mode's measurements, so the loop of one mode is not
        set by one row of the controller. Use :meth:`frequency_response` (the transfer
        matrix on a grid), :meth:`impulse_matrix` (its impulse response) and
        :func:`aocontrol.analysis.multimode_certificate` (stability and the multivariable
        margin).

        Parameters
        ----------
        mode : int, default 0
            Mode index (checked, then refused).

        Raises
        ------
        NotImplementedError
            Always.
        """
        self._check_mode(mode)
        raise NotImplementedError(
            f"{type(self).__name__} is a multi-mode controller: transfer_function(mode={mode}) "
            "has no meaning (each command uses every mode); use frequency_response(freqs) or "
            "impulse_matrix(n_samples) for its transfer matrix and "
            "aocontrol.analysis.multimode_certificate for its loop"
        )

    # -- linear maps ----------------------------------------------------------------------
    def _z_inverse(self, freqs: object) -> np.ndarray:
        f = check_finite_array("freqs", freqs, ndim=1)
        if f.size and (f.min() < 0 or f.max() > self._fs / 2 * (1 + 1e-9)):
            raise ValueError(f"freqs must lie in [0, fs/2] = [0, {self._fs / 2}] Hz")
        return np.exp(-2j * np.pi * f / self._fs)

    def predictor_response(self, freqs: object) -> np.ndarray:
        """``F(e^{j 2 pi f / fs}) = sum_j A_j e^{-j 2 pi f j / fs}`` on a grid.

        Parameters
        ----------
        freqs : array_like, shape (n_freqs,)
            Frequencies [Hz] in ``[0, fs/2]``.

        Returns
        -------
        numpy.ndarray, shape (n_freqs, n_modes, n_modes), complex
        """
        zi = self._z_inverse(freqs)
        powers = zi[:, None] ** np.arange(self._h)[None, :]
        return np.tensordot(powers, self._taps, axes=(1, 0))

    def plant_response(self, freqs: object) -> np.ndarray:
        """The model plant ``G = z^-1 ((1 - f) z^-k0 + f z^-(k0+1))`` (scalar) on a grid.

        Parameters
        ----------
        freqs : array_like, shape (n_freqs,)
            Frequencies [Hz] in ``[0, fs/2]``.

        Returns
        -------
        numpy.ndarray, shape (n_freqs,), complex
        """
        zi = self._z_inverse(freqs)
        return zi ** (self._k0 + 1) * (self._w1 + self._w2 * zi)

    def frequency_response(self, freqs: object) -> np.ndarray:
        """Transfer matrix ``K = (I - F G)^-1 F`` (measurement to command) on a grid.

        One ``n_modes x n_modes`` solve per frequency (``O(n_modes^3)`` each). Where
        ``I - F G`` is singular (a controller pole on the circle) the result is not finite.

        Parameters
        ----------
        freqs : array_like, shape (n_freqs,)
            Frequencies [Hz] in ``[0, fs/2]``.

        Returns
        -------
        numpy.ndarray, shape (n_freqs, n_modes, n_modes), complex
            ``K[i, r, c]``: command of mode ``r`` per unit measurement of mode ``c``.
        """
        F = self.predictor_response(freqs)
        g = self.plant_response(freqs)
        lhs = np.eye(self._n)[None] - g[:, None, None] * F
        return np.linalg.solve(lhs, F)

    def impulse_matrix(self, n_samples: int) -> np.ndarray:
        """Impulse response of the transfer matrix ``K``, shape ``(n_samples, n, n)``.

        ``out[t, r, c]`` is the command of mode ``r`` at frame ``t`` after a unit
        measurement on mode ``c`` at frame 0 (zero state), from the recursion
        ``K_t = sum_j A_j P_{t-j}``, ``P_t = delta_t I + (1 - f) K_{t-1-k0} + f K_{t-2-k0}``
        in float64 (``O(h n^3)`` per sample): the real-time path's responses to unit
        impulses (its columns) equal it to rounding (float64 precision) or within the
        float32 bound of the class docstring.

        Parameters
        ----------
        n_samples : int
            Number of frames (>= 1).

        Returns
        -------
        numpy.ndarray, shape (n_samples, n_modes, n_modes)
        """
        n_samples = check_int("n_samples", n_samples, minimum=1)
        n, h, k0 = self._n, self._h, self._k0
        P = np.zeros((n_samples, n, n))
        K = np.zeros((n_samples, n, n))
        for t in range(n_samples):
            if t == 0:
                P[t] = np.eye(n)
            for lag, w in ((k0 + 1, self._w1), (k0 + 2, self._w2)):
                if w and t - lag >= 0:
                    P[t] += w * K[t - lag]
            K[t] = sum(self._taps[j] @ P[t - j] for j in range(min(h, t + 1)))
        return K

    # -- controller files (aocontrol.controllers.save_controller) -------------------------
    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, object]]:
        """The bank as arrays and scalars for :func:`aocontrol.controllers.save_controller`."""
        arrays = {"taps": np.asarray(self._taps)}
        if self._limit is not None:
            arrays["command_limit"] = np.asarray(self._limit)
        return arrays, {"latency_frames": self._latency, "precision": self._precision}

    @classmethod
    def from_arrays(cls, arrays: dict, attrs: dict) -> MultiModeBank:
        """Inverse of :meth:`to_arrays` (``attrs`` also holds ``fs`` and ``n_modes``).

        Parameters
        ----------
        arrays : dict of str to ndarray
            ``taps`` and, when the bank had one, ``command_limit``.
        attrs : dict
            ``latency_frames``, ``precision`` and ``fs``.
        """
        return cls(
            arrays["taps"],
            float(attrs["fs"]),
            float(attrs["latency_frames"]),
            command_limit=_command_limit_in(arrays),
            precision=str(attrs["precision"]),
        )

    def __repr__(self) -> str:
        return (
            f"MultiModeBank(n_modes={self._n}, fs={self._fs}, history={self._h}, "
            f"latency_frames={self._latency}, precision={self._precision!r})"
        )
