"""The multi-mode predictor that retrains, certifies and switches itself (see
:mod:`aocontrol.adaptive`)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import control
import numpy as np

from aocontrol._validation import (
    check_finite_array,
    check_in_range,
    check_instance,
    check_int,
    check_nonnegative,
)
from aocontrol.adaptive._controller import AdaptiveRun, Redesign
from aocontrol.adaptive._schedule import MIN_WINDOW_FRAMES, SelfDesigningBank
from aocontrol.controllers import ControllerBank, MultiModeBank
from aocontrol.plant import check_system, plant_fs
from aocontrol.synthesis import (
    EOFNotCertifiedError,
    eof_from_pseudo_open_loop,
    eof_min_frames,
    plant_latency,
)

logger = logging.getLogger(__name__)


class AdaptivePredictor(SelfDesigningBank):
    """A multi-mode predictor (EOF / LMMSE) that retrains, certifies and switches itself.

    The multi-mode counterpart of :class:`AdaptiveController`, on the same schedule (designs
    every ``period`` from the last ``window`` of telemetry, switched in ``latency`` later;
    module docstring of :mod:`aocontrol.adaptive`). A design is
    :func:`aocontrol.synthesis.eof_from_pseudo_open_loop` on the window's pseudo-open loop
    (regularised least squares, the weight chosen on the window's last
    ``validation_fraction``), certified by :func:`aocontrol.analysis.multimode_certificate`
    (stability, multivariable modulus margin at least ``modulus_margin`` over the whole
    circle; below it the weight is raised until the margin is met). The whole predictor
    switches or nothing does: a training that cannot be certified
    (:class:`~aocontrol.synthesis.EOFNotCertifiedError`) leaves the controller in use and
    is recorded (``certified`` all False, the reason for every mode). The switch is
    bumpless: the new predictor's state is the window's last POL frames and applied
    commands (:meth:`~aocontrol.controllers.MultiModeBank.set_history`), so its first
    command is the one it would give had it been running on this loop.

    Parameters
    ----------
    initial : ControllerBank
        The controller the loop starts with (e.g. an :class:`~aocontrol.controllers.Integrator`,
        or a trained :class:`~aocontrol.controllers.MultiModeBank`), running until the first
        certified predictor switches in.
    plant : control.TransferFunction
        Loop plant of the :func:`aocontrol.loop_plant` form (a pure delay: the predictor's
        model of the loop, from which its latency is read).
    period : float
        Time between trainings ``T`` [s], > 0.
    window : float
        Telemetry of a training ``W`` [s]: at least what a history-``h`` predictor of
        ``n_modes`` needs (:func:`aocontrol.synthesis.eof_min_frames`), and
        :data:`MIN_WINDOW_FRAMES`.
    latency : float or None, default None
        Training latency [s] (switch ``ceil(latency fs)`` frames after the request, shorter
        than ``period``); ``None``: the measured compute time.
    history : int, default 5
        POL frames per command ``h`` (>= 1).
    modulus_margin : float, default 0.5
        Required multivariable modulus margin, in (0, 1).
    regularisation : float, optional
        A fixed Tikhonov weight (>= 0); ``None`` (default): chosen on each window.
    validation_fraction : float, default 0.2
        Fraction of the window held back to choose the weight.
    integral_action : bool, default True
        ``F(1) = I`` (see :func:`~aocontrol.synthesis.eof_from_pseudo_open_loop`).
    command_limit : float or array_like of shape (n_modes,), optional
        The predictors' limit on their command.
    precision : {"float32", "float64"}, default "float32"
        Precision of the predictors' real-time product.
    max_designs : int, optional
        Stop after this many trainings (``1``: a fixed predictor from the first window).
    oracle : callable, optional
        ``oracle(frame) -> array (n_frames, n_modes)``: a record to train on at ``frame``
        instead of the window's pseudo-open loop (a yardstick that knows the truth, e.g. the
        true disturbance one frame late plus the true noise, in a simulation).
    blas_threads : int or None, default 1
        BLAS threads of the training.

    Attributes
    ----------
    current : ControllerBank
        The controller in use (``initial``, then the last certified predictor).
    run : AdaptiveRun
        Record of the run in progress (its :class:`Redesign` events: ``certified`` and
        ``modulus_margin`` are the whole loop's, the same for every mode;
        ``regularisation`` the certified weight); :attr:`last_run` that of the previous one.

    Raises
    ------
    TypeError
        ``initial`` not a :class:`~aocontrol.controllers.ControllerBank`, ``plant`` not a
        transfer function, ``oracle`` not callable.
    ValueError
        A plant not of the loop-plant form, a rate that differs from ``initial``'s, a window
        too short for the predictor (the message says how many frames it needs), or a bad
        ``history``, ``modulus_margin`` or ``regularisation``.
    """

    def __init__(
        self,
        initial: ControllerBank,
        plant: control.TransferFunction,
        *,
        period: float,
        window: float,
        latency: float | None = None,
        history: int = 5,
        modulus_margin: float = 0.5,
        regularisation: float | None = None,
        validation_fraction: float = 0.2,
        integral_action: bool = True,
        command_limit: float | np.ndarray | None = None,
        precision: str = "float32",
        max_designs: int | None = None,
        oracle: Callable[[int], np.ndarray] | None = None,
        blas_threads: int | None = 1,
    ) -> None:
        check_instance("initial", initial, ControllerBank)
        if not isinstance(plant, control.TransferFunction):
            raise TypeError(f"plant must be a control.TransferFunction, got {type(plant).__name__}")
        fs = plant_fs(plant)
        if not np.isclose(initial.fs, fs, rtol=1e-9):
            raise ValueError(f"initial runs at {initial.fs:g} Hz, the plant at {fs:g} Hz")
        self._latency_model = plant_latency(plant)
        if not isinstance(initial, MultiModeBank):
            check_system("initial", initial.transfer_function(0), fs, rate_of="the plant")
        self._initial = initial
        self._n_modes = initial.n_modes
        self._h = check_int("history", history, minimum=1)
        self._mu = check_in_range("modulus_margin", modulus_margin, 0.0, 1.0,
                                  low_inclusive=False, high_inclusive=False)  # fmt: skip
        if regularisation is not None:
            regularisation = check_nonnegative("regularisation", regularisation)
        validation = None if regularisation is not None else validation_fraction
        needed = max(
            MIN_WINDOW_FRAMES,
            eof_min_frames(
                self._n_modes, self._h, self._latency_model, validation_fraction=validation
            ),
        )
        self._options = dict(
            history=self._h,
            modulus_margin=self._mu,
            regularisation=regularisation,
            validation_fraction=validation_fraction,
            integral_action=integral_action,
            command_limit=command_limit,
            precision=precision,
            blas_threads=blas_threads,
        )
        if oracle is not None and not callable(oracle):
            raise TypeError(f"oracle must be callable, got {oracle!r}")
        self._oracle = oracle
        super().__init__(
            plant,
            period=period,
            window=window,
            latency=latency,
            max_designs=max_designs,
            min_window_frames=needed,
        )

    # -- interface ------------------------------------------------------------------------
    @property
    def current(self) -> ControllerBank:
        """The controller in use (``initial``, then the last certified predictor)."""
        return self._current

    @property
    def history(self) -> int:
        """POL frames per command of the predictors."""
        return self._h

    def transfer_function(self, mode: int = 0) -> control.TransferFunction:
        """The controller in use's transfer function of ``mode``; a predictor has none
        (:meth:`aocontrol.controllers.MultiModeBank.transfer_function` says why)."""
        return self._current.transfer_function(mode)

    # -- internals ------------------------------------------------------------------------
    def _new_record(self) -> AdaptiveRun:
        return AdaptiveRun()

    def _start(self) -> None:
        self._current = self._initial
        self._initial.reset()

    def _runtime_step(self, m: np.ndarray) -> np.ndarray:
        return self._current.step(m)

    def _switch(self, bank: MultiModeBank) -> None:
        # The state: the last h POL frames and k0 + 2 commands, rebuilt from the record.
        m, u = self._history(self._cap)
        bank.reset()
        bank.set_history(m, u)
        self._current = bank

    def _training_record(self, k: int) -> np.ndarray:
        if self._oracle is None:
            return self._window_pol()
        record = check_finite_array("oracle(frame)", self._oracle(k), ndim=2)
        if record.shape[1] != self.n_modes:
            raise ValueError(
                f"oracle(frame) must return (n_frames, {self.n_modes}), got {record.shape}"
            )
        return record

    def _redesign(self, k: int) -> None:
        t0 = time.perf_counter()
        pol = self._training_record(k)
        n = self.n_modes
        reasons: dict[int, str] = {}
        margin, lam, switch = np.nan, None, None
        try:
            res = eof_from_pseudo_open_loop(pol, self._fs, self._latency_model, **self._options)
        except EOFNotCertifiedError as exc:
            reasons = dict.fromkeys(range(n), f"predictor not certified: {exc}")
            logger.warning("predictor training at frame %d not certified: %s", k, exc)
        else:
            cert = res.certificate
            margin, lam = cert.margin, res.regularisation
            if cert.certified:  # eof_from_pseudo_open_loop returns certified banks only
                switch = self._schedule(k, time.perf_counter() - t0, res.controller)
            else:  # pragma: no cover - a guard, never expected
                reasons = dict.fromkeys(range(n), "predictor not certified")
        seconds = time.perf_counter() - t0
        self.run.redesigns.append(
            Redesign(
                frame=k,
                switch_frame=switch,
                design_seconds=seconds,
                certified=np.full(n, switch is not None),
                reasons=reasons,
                modulus_margin=np.full(n, margin),
                disturbance_variance=pol.var(axis=0),
                noise_variance=np.full(n, np.nan),
                regularisation=lam,
            )
        )

    def __repr__(self) -> str:
        return (
            f"AdaptivePredictor(n_modes={self.n_modes}, fs={self._fs:g}, period="
            f"{self._period:g} s, window={self._window:g} s, history={self._h})"
        )
