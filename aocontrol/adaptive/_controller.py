"""The adaptive controller bank and its run record (see :mod:`aocontrol.adaptive`)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import control
import numpy as np

from aocontrol._validation import check_in_range, check_int, check_positive
from aocontrol.adaptive._realisation import RealisedBank, StateSpaceRows
from aocontrol.adaptive._redesign import RANKINGS, Designer, redesign
from aocontrol.adaptive._schedule import MIN_WINDOW_FRAMES, SelfDesigningBank
from aocontrol.controllers import ControllerBank, IIRBank
from aocontrol.plant import check_system, plant_fs
from aocontrol.synthesis import TelemetryPSD, disturbance_from_telemetry

logger = logging.getLogger(__name__)

__all__ = ["BUMPLESS_FRAMES", "MIN_WINDOW_FRAMES", "AdaptiveController", "AdaptiveRun", "Redesign"]
#: Frames over which a new filter's past outputs are fitted to the applied commands at a switch.
BUMPLESS_FRAMES = 100


@dataclass(frozen=True)
class Redesign:
    """One redesign of an :class:`AdaptiveController`.

    Attributes
    ----------
    frame : int
        Frame at which the design was requested (telemetry up to ``frame - 1``).
    switch_frame : int or None
        Frame from which the new bank runs (``None``: not switched in).
    design_seconds : float
        Measured compute time of estimation, design and certification [s].
    certified : ndarray of bool, shape (n_modes,)
        Modes whose proposed controller passed every certificate (and are switched in).
    reasons : dict of int to str
        Why each other mode kept its controller.
    modulus_margin : ndarray, shape (n_modes,)
        Certified modulus margin of each mode's proposed controller (``nan`` if none).
    disturbance_variance : ndarray, shape (n_modes,)
        Variance of the estimated disturbance over the window [units^2] (the PSD integrated).
    noise_variance : ndarray, shape (n_modes,)
        Estimated per-frame noise variance [units^2].
    selected : ndarray of bool, shape (n_modes,) or None
        Modes that were redesigned (``None``: all; see ``select`` of
        :class:`AdaptiveController`).
    kept : ndarray of bool, shape (n_modes,) or None
        Modes whose new design was worse than their controller, which stayed (``None``:
        none; :attr:`Proposal.kept`).
    regularisation : float or None
        The certified Tikhonov weight of an :class:`AdaptivePredictor`'s training (``None``
        for the modal designs, or when nothing was certified). Its ``disturbance_variance``
        is the window's pseudo-open-loop variance (noise included) and ``noise_variance``
        is not estimated (``nan``).
    """

    frame: int
    switch_frame: int | None
    design_seconds: float
    certified: np.ndarray
    reasons: dict[int, str]
    modulus_margin: np.ndarray
    disturbance_variance: np.ndarray
    noise_variance: np.ndarray
    selected: np.ndarray | None = None
    kept: np.ndarray | None = None
    regularisation: float | None = None

    @property
    def switched(self) -> bool:
        """Whether the (partly) certified bank was switched in."""
        return self.switch_frame is not None


@dataclass
class AdaptiveRun:
    """Record of one run of an :class:`AdaptiveController` (between two resets).

    Attributes
    ----------
    frames : int
        Frames stepped.
    redesigns : list of Redesign
        Every design, in order.
    n_skipped : int
        Designs skipped because the previous one was still pending.
    final : ControllerBank or None
        The controller in use at the end of the run (set when the run is archived by a
        reset): an :class:`IIRBank` for :class:`AdaptiveController`, the last certified
        predictor (or the initial controller) for :class:`AdaptivePredictor`.
    """

    frames: int = 0
    redesigns: list[Redesign] = field(default_factory=list)
    n_skipped: int = 0
    final: ControllerBank | None = None

    @property
    def n_switches(self) -> int:
        """Banks switched in."""
        return sum(r.switched for r in self.redesigns)

    @property
    def n_rejected_banks(self) -> int:
        """Proposals with no certified mode (not switched in; the last certified bank stayed);
        a redesign that selected no mode proposes nothing and is not counted."""
        return sum(
            not r.switched and (r.selected is None or bool(r.selected.any()))
            for r in self.redesigns
        )

    @property
    def n_rejected_modes(self) -> int:
        """Mode designs that were not certified, summed over redesigns (those modes kept their
        controller; modes not selected for a redesign are not counted)."""
        return int(
            sum(
                (~r.certified & (True if r.selected is None else r.selected)).sum()
                for r in self.redesigns
            )
        )

    @property
    def n_designed_modes(self) -> int:
        """Mode designs, summed over redesigns (every mode, or the selected ones)."""
        return int(
            sum(
                r.certified.size if r.selected is None else r.selected.sum() for r in self.redesigns
            )
        )

    @property
    def n_kept_modes(self) -> int:
        """Mode designs worse than the mode's running controller, which stayed (summed over
        redesigns; the synthesis never proposes a design worse than its start)."""
        return int(sum(0 if r.kept is None else r.kept.sum() for r in self.redesigns))

    @property
    def switch_frames(self) -> list[int]:
        """Frames at which a new bank started."""
        return [r.switch_frame for r in self.redesigns if r.switch_frame is not None]


class AdaptiveController(SelfDesigningBank):
    """An IIR bank that redesigns, certifies and bumplessly switches its own controllers.

    Parameters
    ----------
    initial : IIRBank
        The bank the loop starts with (e.g. an :class:`~aocontrol.controllers.Integrator`).
    plant : control.TransferFunction
        Loop plant (command to measurement, :func:`aocontrol.loop_plant`), used for the pseudo
        open loop and the certificates.
    designer : callable
        ``designer(telemetry_psd, plant, current_bank) -> Proposal``, e.g.
        :func:`datadriven_designer`.
    period : float
        Time between designs ``T`` [s], > 0.
    window : float
        Telemetry used by a design ``W`` [s]: at least ``MIN_WINDOW_FRAMES`` frames and
        ``nperseg`` frames.
    latency : float or None, default None
        Design latency [s] (switch ``ceil(latency fs)`` frames after the request; must be
        shorter than ``period``). ``None``: the measured compute time (runs are then not
        reproducible bit for bit).
    modulus_margin : float, default 0.5
        Margin every switched-in controller must have (certificate).
    max_pole_radius : float, default 1.0
        Largest controller pole modulus accepted (certificate).
    nperseg : int, optional
        Welch segment [frames] (default ``min(window frames, 1024)``).
    noise_band : (float, float), default (0.8, 1.0)
        Noise-floor band of :func:`~aocontrol.synthesis.disturbance_from_telemetry`.
    estimator : callable, optional
        ``estimator(pol, plant) -> TelemetryPSD`` from the window's pseudo-open loop
        ``(n_frames, n_modes)``; default
        :func:`~aocontrol.synthesis.disturbance_from_telemetry` (``pol`` as measurements,
        zero commands) with ``nperseg`` and ``noise_band``. E.g. a pre-whitened estimate.
    max_designs : int, optional
        Stop after this many designs (``1``: a fixed design from the first window).
    oracle : callable, optional
        ``oracle(frame) -> TelemetryPSD``: the disturbance and noise PSDs to design from at
        ``frame`` instead of the telemetry estimate (a yardstick that knows the truth, e.g. in
        a simulation; its ``pseudo_open_loop`` is not used).
    select : float, optional
        Redesign only the modes predicted to gain the most: the fewest modes, largest first,
        whose predicted gains (see ``rank``) cover this share, in (0, 1], of the total;
        modes never designed always. ``None`` (default): every mode at every design. The
        others keep their controller (not counted as rejected). See :func:`select_modes`.
    max_modes : int, optional
        At most this many modes per design (with ``select``; the largest gains first).
    rank : {"bound", "shift"}, default "shift"
        The predicted gain of a mode (with ``select``): the residual a redesign is predicted
        to recover (:func:`recoverable_gain`: the current residual minus the design's
        efficiency times the Wiener bound on the new estimate) or how far the residual moved
        since the design (:func:`residual_shift`). Neither ranking concentrates the gain
        in a few modes (``benchmarks/bench_adaptive.py --parts c --sweep``,
        ``docs/benchmarks.md``).

    Attributes
    ----------
    current : IIRBank
        The bank in use (every mode's transfer function).
    realisation : StateSpaceRows
        The modes of ``current`` the loop runs in state space (``realisation.used``; e.g. an
        LQG's observer form), the others running ``current``'s Direct-Form I recursion.
    run : AdaptiveRun
        Record of the run in progress; :attr:`last_run` that of the previous one.
    """

    def __init__(
        self,
        initial: IIRBank,
        plant: control.TransferFunction,
        designer: Designer,
        *,
        period: float,
        window: float,
        latency: float | None = None,
        modulus_margin: float = 0.5,
        max_pole_radius: float = 1.0,
        nperseg: int | None = None,
        noise_band: tuple[float, float] = (0.8, 1.0),
        estimator: Callable[[np.ndarray, control.TransferFunction], TelemetryPSD] | None = None,
        max_designs: int | None = None,
        oracle: Callable[[int], TelemetryPSD] | None = None,
        select: float | None = None,
        max_modes: int | None = None,
        rank: str = "shift",
    ) -> None:
        if not isinstance(initial, IIRBank):
            raise TypeError(f"initial must be an IIRBank, got {type(initial).__name__}")
        if not isinstance(plant, control.TransferFunction):
            raise TypeError(f"plant must be a control.TransferFunction, got {type(plant).__name__}")
        fs = plant_fs(plant)
        check_system("initial", initial.transfer_function(0), fs, rate_of="the plant")
        if not callable(designer):
            raise TypeError(f"designer must be callable, got {designer!r}")
        self._initial = initial
        self._n_modes = initial.n_modes
        self._designer = designer
        window_frames = round(check_positive("window", window) * fs)
        if nperseg is not None:
            nperseg = check_int("nperseg", nperseg, minimum=8)
            if nperseg > window_frames:
                raise ValueError(
                    f"window must hold at least nperseg={nperseg} frames "
                    f"({nperseg / fs:.3g} s), got {window!r} s"
                )
        self._nperseg = nperseg
        self._noise_band = noise_band
        if oracle is not None and not callable(oracle):
            raise TypeError(f"oracle must be callable, got {oracle!r}")
        self._oracle = oracle
        self._select = (
            None
            if select is None
            else check_in_range("select", select, 0.0, 1.0, low_inclusive=False)
        )
        self._max_modes = (
            None if max_modes is None else check_int("max_modes", max_modes, minimum=1)
        )
        if rank not in RANKINGS:
            raise ValueError(f"rank must be one of {list(RANKINGS)}, got {rank!r}")
        self._rank = rank
        if estimator is not None and not callable(estimator):
            raise TypeError(f"estimator must be callable, got {estimator!r}")
        self._estimator = estimator
        self._mu = check_in_range("modulus_margin", modulus_margin, 0.0, 1.0, high_inclusive=False)
        self._rmax = check_positive("max_pole_radius", max_pole_radius)
        super().__init__(
            plant, period=period, window=window, latency=latency, max_designs=max_designs
        )

    # -- interface ------------------------------------------------------------------------
    @property
    def current(self) -> IIRBank:
        """The bank in use (every mode's transfer function; it changes at each switch)."""
        return self._current

    def transfer_function(self, mode: int = 0) -> control.TransferFunction:
        """The current bank's controller of ``mode`` (it changes at each switch)."""
        return self.current.transfer_function(mode)

    # -- internals ------------------------------------------------------------------------
    def _new_record(self) -> AdaptiveRun:
        return AdaptiveRun()

    def _start(self) -> None:
        self._current = self._initial.rows(np.arange(self.n_modes))  # a fresh copy
        self.realisation = StateSpaceRows.none(self.n_modes)
        self._runtime = RealisedBank(self._current, self.realisation)
        self._last_ratio = np.full(self.n_modes, np.nan)

    def _runtime_step(self, m: np.ndarray) -> np.ndarray:
        return self._runtime.step(m)

    def _switch(self, proposal: tuple[IIRBank, StateSpaceRows]) -> None:
        bank, rows = proposal
        depth = max(bank.b.shape[1], bank.a.shape[1], rows.ns + 1)
        fit = max(BUMPLESS_FRAMES, 4 * depth)
        # Direct-Form I rows: fitted over the last `fit` frames (after `depth` frames of
        # initial state); state-space rows: run over the whole record (bumpless_state).
        m, u = self._history(self._cap if rows.used.any() else fit + depth)
        bank.reset()
        runtime = RealisedBank(bank, rows)
        runtime.set_history(m, u, fit_frames=min(fit, m.shape[0] - depth))
        self._current, self.realisation, self._runtime = bank, rows, runtime

    def _estimate(self, k: int) -> TelemetryPSD:
        """The disturbance and noise estimate of a design requested at frame ``k``."""
        if self._oracle is not None:
            return self._oracle(k)
        pol = self._window_pol()
        if self._estimator is not None:
            return self._estimator(pol, self._plant)
        return disturbance_from_telemetry(
            pol,
            np.zeros_like(pol),
            self._plant,
            nperseg=self._nperseg,
            noise_band=self._noise_band,
        )

    def _redesign(self, k: int) -> None:
        t0 = time.perf_counter()
        tel = self._estimate(k)
        up = redesign(
            self._plant,
            self.current,
            tel,
            self._designer,
            modulus_margin=self._mu,
            max_pole_radius=self._rmax,
            last_ratio=self._last_ratio if self._select is not None else None,
            select=self._select,
            max_modes=self._max_modes,
            rank=self._rank,
        )
        if up.ratio is not None:
            self._last_ratio = up.ratio
        seconds = time.perf_counter() - t0
        switch = None
        if up.certified.any():
            rows = self.realisation
            if up.realisation is not None:
                rows = rows.merge(up.realisation, up.certified)
            else:  # the replaced modes run in Direct-Form I
                rows = rows.merge(StateSpaceRows.none(self.n_modes), up.certified)
            switch = self._schedule(k, seconds, (up.bank, rows))
        elif up.selected is None or up.selected.any():
            logger.warning(
                "redesign at frame %d: no mode certified, the current bank stays (%s)",
                k,
                "; ".join(f"mode {i}: {r}" for i, r in list(up.reasons.items())[:5]),
            )
        if up.reasons:
            logger.info("redesign at frame %d: %d modes kept their controller", k, len(up.reasons))
        self.run.redesigns.append(
            Redesign(
                frame=k,
                switch_frame=switch,
                design_seconds=seconds,
                certified=up.certified,
                reasons=up.reasons,
                modulus_margin=up.modulus_margin,
                disturbance_variance=np.trapezoid(tel.psd, tel.freqs, axis=-1),
                noise_variance=tel.noise_variance,
                selected=up.selected,
                kept=up.kept,
            )
        )

    def __repr__(self) -> str:
        return (
            f"AdaptiveController(n_modes={self.n_modes}, fs={self._fs:g}, period={self._period:g}"
            f" s, window={self._window:g} s, designer={getattr(self._designer, '__name__', '?')})"
        )
