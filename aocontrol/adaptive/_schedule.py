"""The schedule every self-designing bank shares (private): when designs are requested,
when they switch in, and the telemetry they are made from.

:class:`SelfDesigningBank` records the measurements it receives and the commands it returns
in a ring buffer of the design window plus the plant's memory, requests a design at the
frames ``(window + j * period) * fs`` (``j >= 0``) on the telemetry up to the previous
frame, and switches the proposal in ``latency`` frames later (a design still pending when the
next is due is skipped and counted). What a design is (PSDs and per-mode filters, or a
multi-mode predictor trained on the time series), how it is certified and how the new
controller takes over are the subclass's: :class:`~aocontrol.adaptive.AdaptiveController`
(modal IIR banks) and :class:`~aocontrol.adaptive.AdaptivePredictor` (the multi-mode
predictor).
"""

from __future__ import annotations

import abc
import math
from typing import Any

import control
import numpy as np

from aocontrol._validation import check_int, check_nonnegative, check_positive
from aocontrol.controllers import ControllerBank
from aocontrol.plant import plant_fs, z_inverse_coefficients
from aocontrol.synthesis import pseudo_open_loop

#: Fewest frames in a window (a Welch estimate needs at least 8; a useful one, hundreds).
MIN_WINDOW_FRAMES = 64


class SelfDesigningBank(ControllerBank):
    """A controller bank that redesigns itself on a schedule (module docstring).

    Subclasses set ``_n_modes`` before calling ``__init__`` of this class and implement
    :meth:`_start` (the controller a run starts with), :meth:`_redesign` (a design requested
    at frame ``k``: it may call :meth:`_schedule`), :meth:`_switch` (the scheduled proposal
    takes over) and :meth:`_runtime_step`.
    """

    def __init__(
        self,
        plant: control.TransferFunction,
        *,
        period: float,
        window: float,
        latency: float | None,
        max_designs: int | None,
        min_window_frames: int = MIN_WINDOW_FRAMES,
    ) -> None:
        if not isinstance(plant, control.TransferFunction):
            raise TypeError(f"plant must be a control.TransferFunction, got {type(plant).__name__}")
        fs = plant_fs(plant)
        self._plant = plant
        self._fs = fs
        self._period = check_positive("period", period)
        self._window = check_positive("window", window)
        self._period_frames = max(1, round(self._period * fs))
        self._window_frames = round(self._window * fs)
        if self._window_frames < min_window_frames:
            raise ValueError(
                f"window must hold at least {min_window_frames} frames "
                f"({min_window_frames / fs:.3g} s at {fs:g} Hz), got {window!r} s"
            )
        self._max_designs = (
            None if max_designs is None else check_int("max_designs", max_designs, minimum=1)
        )
        if latency is None:
            self._latency_frames = None
        else:
            latency = check_nonnegative("latency", latency)
            if latency >= self._period:
                raise ValueError(
                    f"latency must be shorter than period={self._period:g} s, got {latency!r} s"
                )
            self._latency_frames = math.ceil(latency * fs - 1e-9)
        b, a = z_inverse_coefficients(plant, "plant")
        # Frames of the pseudo open loop's start-up transient (the plant's memory), dropped.
        self._lead = max(b.size, a.size)
        self.last_run: Any = None
        self.run = self._new_record()
        self.reset()

    # -- what a subclass provides ---------------------------------------------------------
    @abc.abstractmethod
    def _new_record(self) -> Any:
        """An empty run record (with ``frames``, ``redesigns``, ``n_skipped`` and ``final``)."""

    @abc.abstractmethod
    def _start(self) -> None:
        """Set the controller a run starts with (called by :meth:`reset`)."""

    @abc.abstractmethod
    def _runtime_step(self, m: np.ndarray) -> np.ndarray:
        """The command of the controller in use."""

    @abc.abstractmethod
    def _redesign(self, k: int) -> None:
        """A design requested at frame ``k`` (telemetry up to ``k - 1``)."""

    @abc.abstractmethod
    def _switch(self, proposal: Any) -> None:
        """The proposal scheduled by :meth:`_schedule` takes over."""

    @property
    @abc.abstractmethod
    def current(self) -> Any:
        """The controller in use."""

    # -- interface ------------------------------------------------------------------------
    @property
    def n_modes(self) -> int:
        return self._n_modes

    @property
    def fs(self) -> float:
        return self._fs

    @property
    def period(self) -> float:
        """Time between designs [s]."""
        return self._period

    @property
    def window(self) -> float:
        """Telemetry window of a design [s]."""
        return self._window

    def reset(self) -> None:
        if self.run.frames:
            self.run.final = self.current
            self.last_run = self.run
        self.run = self._new_record()
        cap = self._window_frames + self._lead
        self._cap = cap
        self._m = np.zeros((cap, self.n_modes))
        self._u = np.zeros((cap, self.n_modes))
        self._k = 0
        self._pending: tuple[int, Any] | None = None
        self._start()

    def _step(self, m: np.ndarray) -> np.ndarray:
        k = self._k
        if self._pending is not None and self._pending[0] == k:
            self._take_pending()
        # The first design once a window is available, then every period: every period
        # starts from the same first design (that of the fixed strategy).
        w = self._window_frames
        due = k >= w and (k - w) % self._period_frames == 0
        if due and self._max_designs is not None:
            due = len(self.run.redesigns) < self._max_designs
        if due:
            if self._pending is None:
                self._redesign(k)
                if self._pending is not None and self._pending[0] == k:  # zero latency
                    self._take_pending()
            else:
                self.run.n_skipped += 1
        u = self._runtime_step(m)
        slot = k % self._cap
        self._m[slot] = m
        self._u[slot] = u
        self._k = k + 1
        self.run.frames = self._k
        return u

    # -- for the subclasses ---------------------------------------------------------------
    def _take_pending(self) -> None:
        proposal = self._pending[1]
        self._pending = None
        self._switch(proposal)

    def _latency_of(self, seconds: float) -> int:
        """Switch latency [frames] of a design that took ``seconds`` of compute."""
        if self._latency_frames is None:
            return math.ceil(seconds * self._fs)
        return self._latency_frames

    def _schedule(self, k: int, seconds: float, proposal: Any) -> int:
        """Schedule ``proposal`` requested at frame ``k``; returns its switch frame."""
        switch = k + self._latency_of(seconds)
        self._pending = (switch, proposal)
        return switch

    def _history(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The last ``n`` frames of (m, u), oldest first (fewer if fewer were stepped)."""
        n = min(n, self._k, self._cap)
        idx = np.arange(self._k - n, self._k) % self._cap
        return self._m[idx], self._u[idx]

    def _window_pol(self) -> np.ndarray:
        """The pseudo-open loop ``m + G u`` of the last window, ``(window frames, n_modes)``
        (rebuilt over the window plus the plant's memory, which is dropped: a window cut
        from a running loop has no transient of unknown earlier commands)."""
        m, u = self._history(self._window_frames + self._lead)
        lead = m.shape[0] - self._window_frames
        return pseudo_open_loop(m, u, self._plant)[lead:]
