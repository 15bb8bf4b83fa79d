"""A controller bank that redesigns itself from its own telemetry (adaptive control).

:class:`AdaptiveController` is a :class:`~aocontrol.controllers.ControllerBank` wrapping an
:class:`~aocontrol.controllers.IIRBank`. It records the measurements it receives and the
commands it returns, and every ``period`` seconds:

1. **Estimate.** Pseudo-open-loop PSDs and white noise levels from the last ``window``
   seconds of its telemetry, with the control layer's pipeline
   (:func:`aocontrol.synthesis.pseudo_open_loop`, then
   :func:`aocontrol.synthesis.disturbance_from_telemetry`). The pseudo open loop ``m + G u``
   is rebuilt over the window plus a lead-in of the plant's delay, which is dropped: a
   window cut from a running loop has no transient of unknown earlier commands.
2. **Design.** A *designer* proposes a new bank from those PSDs, warm-started from the
   current one: :func:`datadriven_designer` (``datadriven(..., initial=current)``),
   :func:`modal_gain_designer` (the optimised integrator gain of Gendron & Léna, the usual
   practice today) or :func:`lqg_designer` (LQG re-identified from the same window, run as
   its exact transfer function).
3. **Certify.** Each mode of the proposal is checked here, whatever the designer said:
   closed-loop stability (:func:`aocontrol.analysis.is_stable` through
   :func:`aocontrol.analysis.margins`), modulus margin at least ``modulus_margin`` (the
   margin of :func:`~aocontrol.analysis.margins`, the certificate the analysis layer owns)
   and every controller pole of modulus at most ``max_pole_radius`` (a controller that
   survives an open loop: a WFS dropout, a saturated DM). A mode that fails, or that the
   designer could not design, keeps its current controller and is reported; a proposal
   with no certified mode is not switched in at all (counted). **An uncertified controller
   is never used.**
4. **Switch** after the design latency (a set value, or the measured compute time rounded up
   to frames), **bumplessly**: the new bank's Direct-Form I state is set from the recent
   measurements and the commands actually applied (:meth:`IIRBank.set_history`), so the
   first command of the new filter continues the loop instead of restarting from zero.

Timing: frame ``k`` (counted from :meth:`reset`; a frame rejected for a non-finite measurement
is not stepped, hence not counted) is at ``k / fs``. Designs are requested at
the frames ``j * period * fs`` (``j >= 1``) that have a full window behind them, on the
telemetry up to the previous frame; the switch happens at the start of frame
``k_design + latency_frames``. A design requested while the previous one is still pending
(latency longer than the period) is skipped and counted. In a simulation the design runs
synchronously inside :meth:`step` (the simulated loop waits; its frames are unchanged), and
the latency is simulated by the scheduled switch.

Run by :func:`aocontrol.sim.run_loop` like any bank. The runner resets the controller at the
start and the end of a run; the record of the last run (:class:`Redesign` events and
counters) survives that reset as :attr:`AdaptiveController.last_run`.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import control
import numpy as np

from aocontrol._validation import check_in_range, check_int, check_nonnegative, check_positive
from aocontrol.analysis import margins, residual_variance
from aocontrol.controllers import ControllerBank, IIRBank
from aocontrol.plant import check_system, plant_fs, z_inverse_coefficients
from aocontrol.synthesis import (
    DataDrivenError,
    ModalGainError,
    TelemetryPSD,
    datadriven,
    disturbance_from_telemetry,
    lqg,
    optimal_modal_gain,
    pseudo_open_loop,
)

__all__ = [
    "AdaptiveController",
    "AdaptiveRun",
    "Proposal",
    "Redesign",
    "certify",
    "datadriven_designer",
    "lqg_designer",
    "modal_gain_designer",
    "residual_shift",
    "redesign",
    "Update",
    "select_modes",
]

logger = logging.getLogger(__name__)

#: Fewest frames in a window (a Welch estimate needs at least 8; a useful one, hundreds).
MIN_WINDOW_FRAMES = 64
#: Frames over which a new filter's past outputs are fitted to the applied commands at a switch.
BUMPLESS_FRAMES = 100
#: E-folding age [frames] of the weights of that fit, and the weight of the last frame.
BUMPLESS_MEMORY = 20.0
BUMPLESS_LAST_WEIGHT = 100.0
# Relative slack on the modulus margin certificate (rounding of the margin computation).
_MARGIN_RTOL = 1e-9
# Slack on the controller pole radius (rounding of companion-matrix eigenvalues).
_POLE_RTOL = 1e-9
# Relative size of a(1) below which a controller has a pole at z = 1 (integral action).
_INTEGRATOR_RTOL = 1e-9


@dataclass(frozen=True)
class Proposal:
    """A designer's answer: a bank and the modes it could not design.

    Attributes
    ----------
    controller : IIRBank
        Proposed bank, one row per mode.
    failed : dict of int to str
        Modes the designer could not design, with the reason (they are not certified and keep
        the current controller).
    """

    controller: IIRBank
    failed: dict[int, str] = field(default_factory=dict)


Designer = Callable[[TelemetryPSD, control.TransferFunction, IIRBank], Proposal]


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
    final : IIRBank or None
        The bank in use at the end of the run (set when the run is archived by a reset).
    """

    frames: int = 0
    redesigns: list[Redesign] = field(default_factory=list)
    n_skipped: int = 0
    final: IIRBank | None = None

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
    def switch_frames(self) -> list[int]:
        """Frames at which a new bank started."""
        return [r.switch_frame for r in self.redesigns if r.switch_frame is not None]


def _pole_radius(a: np.ndarray) -> np.ndarray:
    """Largest root modulus of each row of ``a`` (powers of ``z^-1``), shape (n_modes,)."""
    nz = np.flatnonzero(np.any(a != 0, axis=0))
    a = a[:, : nz[-1] + 1] / a[:, :1]
    order = a.shape[1] - 1
    if order == 0:
        return np.zeros(a.shape[0])
    comp = np.zeros((a.shape[0], order, order))
    comp[:, 0, :] = -a[:, 1:]
    idx = np.arange(order - 1)
    comp[:, idx + 1, idx] = 1.0
    return np.abs(np.linalg.eigvals(comp)).max(axis=1)


def certify(
    plant: control.TransferFunction,
    bank: IIRBank,
    *,
    modulus_margin: float,
    max_pole_radius: float = 1.0,
    modes: object = None,
) -> tuple[np.ndarray, np.ndarray, dict[int, str]]:
    """Certificates of each mode of ``bank`` on ``plant``: what may be switched into a loop.

    A mode passes when its closed loop is stable, its modulus margin ``min |1 + G K|`` is at
    least ``modulus_margin`` (both from :func:`aocontrol.analysis.margins`) and every pole of
    its controller has modulus at most ``max_pole_radius`` (batched companion matrices; 1
    admits an integrator's pole at ``z = 1``).

    Parameters
    ----------
    plant : control.TransferFunction
        Loop plant (e.g. :func:`aocontrol.loop_plant`).
    bank : IIRBank
        Controllers to certify.
    modulus_margin : float
        Required modulus margin, in [0, 1).
    max_pole_radius : float, default 1.0
        Largest controller pole modulus accepted, > 0.
    modes : array_like of int, optional
        Modes to check (default all); the others are reported as not certified.

    Returns
    -------
    ok : ndarray of bool, shape (n_modes,)
    margin : ndarray, shape (n_modes,)
        Modulus margin of each checked mode (``nan`` for the others).
    reasons : dict of int to str
        Why each failing checked mode failed.
    """
    mu = check_in_range("modulus_margin", modulus_margin, 0.0, 1.0, high_inclusive=False)
    rmax = check_positive("max_pole_radius", max_pole_radius)
    n = bank.n_modes
    todo = np.arange(n) if modes is None else np.asarray(modes, dtype=int)
    ok = np.zeros(n, dtype=bool)
    margin = np.full(n, np.nan)
    reasons: dict[int, str] = {}
    radius = _pole_radius(bank.a)
    for i in todo:
        i = int(i)
        if radius[i] > rmax * (1 + _POLE_RTOL):
            reasons[i] = f"controller pole radius {radius[i]:.6g} > {rmax:g}"
            continue
        m = margins(plant, bank.transfer_function(i))
        margin[i] = m.modulus_margin
        if not m.stable:
            reasons[i] = "closed loop unstable"
        elif m.modulus_margin < mu * (1 - _MARGIN_RTOL):
            reasons[i] = f"modulus margin {m.modulus_margin:.4g} < {mu:g}"
        else:
            ok[i] = True
    return ok, margin, reasons


def bumpless_outputs(
    bank: IIRBank, measurements: np.ndarray, commands: np.ndarray, *, fit_frames: int
) -> np.ndarray:
    """Past outputs for a new filter entering a running loop: the bumpless initial state.

    Setting a new filter's Direct-Form I history to the commands another controller applied
    makes its next command an extrapolation of a trajectory that is not its own: with poles
    near ``z = 1`` (an LQG's turbulence model, a high-order data-driven filter) that
    extrapolation of the old filter's shape is a transient of many times the disturbance.
    Instead, per mode, the new filter is run over the last ``fit_frames`` frames on the
    measurements actually received, from the initial past outputs ``c`` (``na - 1`` values)
    that bring its outputs closest to the commands actually applied (least squares,
    ``min ||u - (zero-state response + F c)||``, ``F`` its free responses). Its virtual
    outputs then track the applied commands over the fit (exactly when the new filter is the
    old one), and its state is its own: the first command continues the loop without a jump
    and without the extrapolation transient.

    Parameters
    ----------
    bank : IIRBank
        The new filters.
    measurements, commands : ndarray, shape (n_frames, n_modes)
        Recent measurements and applied commands, oldest first.
    fit_frames : int
        Frames at the end of the history over which the outputs are fitted (the frames
        before them give the measurements' initial state).

    Returns
    -------
    ndarray, shape (fit_frames, n_modes)
        The new filters' outputs over the fit, for :meth:`IIRBank.set_history`.
    """
    from scipy import signal

    m = np.asarray(measurements, dtype=float)
    u = np.asarray(commands, dtype=float)
    n_total = m.shape[0]
    fit = check_int("fit_frames", fit_frames, minimum=0, maximum=n_total)
    if fit == 0 or bank.a.shape[1] == 1:
        return u[n_total - fit :]
    pre = n_total - fit
    # Recent frames count more (e-folding BUMPLESS_MEMORY frames); the last one most: the
    # first new command continues the last applied one.
    age = np.arange(fit)[::-1]
    weight = np.exp(-age / BUMPLESS_MEMORY)
    weight[-1] = BUMPLESS_LAST_WEIGHT
    out = np.empty((fit, bank.n_modes))
    nb, na = bank.b.shape[1], bank.a.shape[1]
    for i in range(bank.n_modes):  # at a switch only: a short loop of short filters
        b, a = bank.b[i], bank.a[i]
        x_past = m[max(pre - nb + 1, 0) : pre, i][::-1]
        zi = signal.lfiltic(b, a, np.zeros(na - 1), x_past)
        zero_state = signal.lfilter(b, a, m[pre:, i], zi=zi)[0]
        free = np.empty((fit, na - 1))
        for j in range(na - 1):
            y0 = np.zeros(na - 1)
            y0[j] = 1.0
            free[:, j] = signal.lfilter(b, a, np.zeros(fit), zi=signal.lfiltic(b, a, y0))[0]
        c, *_ = np.linalg.lstsq(
            free * weight[:, None], (u[pre:, i] - zero_state) * weight, rcond=None
        )
        out[:, i] = zero_state + free @ c
    return out


def _merge(current: IIRBank, proposal: IIRBank, take: np.ndarray) -> IIRBank:
    """Rows of ``proposal`` where ``take``, of ``current`` elsewhere (orders padded)."""
    nb = max(current.b.shape[1], proposal.b.shape[1])
    na = max(current.a.shape[1], proposal.a.shape[1])

    def pad(x: np.ndarray, k: int) -> np.ndarray:
        return np.pad(x, ((0, 0), (0, k - x.shape[1])))

    b = np.where(take[:, None], pad(proposal.b, nb), pad(current.b, nb))
    a = np.where(take[:, None], pad(proposal.a, na), pad(current.a, na))
    return IIRBank(b, a, current.fs, stroke=current.stroke)


def residual_shift(
    current: IIRBank,
    plant: control.TransferFunction,
    tel: TelemetryPSD,
    last_ratio: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """How far each mode's residual moved from what a change of scale explains [units^2].

    ``rho = J / v``: the current controller's predicted residual on the estimate
    (:func:`~aocontrol.analysis.residual_variance`) over the measured variance ``v`` (the
    disturbance PSD integrated plus the per-frame noise variance). A change of scale of the
    disturbance and noise (the seeing alone, noise-limited or not) leaves ``rho`` as it was;
    a change of shape (the wind: the disturbance moves in frequency; the noise against the
    disturbance) moves it, and the controller is then tuned to the wrong disturbance. The
    shift ``v |rho - last_ratio|`` is the residual that change moved, in either direction (a
    wind that drops leaves a controller too fast, its residual lower but not optimal): the
    screen of :func:`select_modes`. A mode never designed (``last_ratio`` ``nan``) has an
    infinite shift.

    Parameters
    ----------
    current : IIRBank
        The controllers in use (certified: their loops are stable).
    plant : control.TransferFunction
    tel : TelemetryPSD
        The new estimate.
    last_ratio : ndarray, shape (n_modes,)
        ``rho`` of each mode's controller on the estimate it was designed from.

    Returns
    -------
    shift : ndarray, shape (n_modes,)
        ``v |rho - last_ratio|`` [units^2] (``inf`` where ``last_ratio`` is ``nan``).
    rho : ndarray, shape (n_modes,)
        ``J / v`` of the current controllers on the estimate.
    """
    v = np.trapezoid(tel.psd, tel.freqs, axis=-1) + tel.noise_variance
    j = residual_variance(plant, current, tel.freqs, tel.psd, tel.noise_psd, check_stability=False)
    rho = j / v
    with np.errstate(invalid="ignore"):
        shift = v * np.abs(rho - last_ratio)
    return np.where(np.isnan(last_ratio), np.inf, shift), rho


def select_modes(gain: np.ndarray, share: float, max_modes: int | None = None) -> np.ndarray:
    """The fewest modes whose predicted gains cover ``share`` of their total, largest first.

    Modes of infinite gain (never designed) come first and are always taken (``max_modes``
    apart); modes of zero gain never.

    Parameters
    ----------
    gain : ndarray, shape (n_modes,)
        Predicted recoverable residual per mode (>= 0, ``inf`` allowed).
    share : float
        Share in (0, 1] of the total finite gain to cover.
    max_modes : int, optional
        At most this many modes.

    Returns
    -------
    ndarray of bool, shape (n_modes,)
    """
    order = np.argsort(-gain, kind="stable")
    g = gain[order]
    finite = np.where(np.isfinite(g), g, 0.0)
    total = finite.sum()
    covered = np.cumsum(finite) - finite  # gain covered before taking each mode
    take = (g > 0) & (np.isinf(g) | (covered < share * total))
    if max_modes is not None:
        take &= np.arange(g.size) < max_modes
    out = np.zeros(gain.size, dtype=bool)
    out[order[take]] = True
    return out


@dataclass(frozen=True)
class Update:
    """Result of :func:`redesign`.

    Attributes
    ----------
    bank : IIRBank
        The current bank with every certified mode replaced by its new design.
    certified : ndarray of bool, shape (n_modes,)
        Modes redesigned and certified (replaced in ``bank``).
    modulus_margin : ndarray, shape (n_modes,)
        Certified margin of each checked new design (``nan`` elsewhere).
    reasons : dict of int to str
        Why each redesigned mode that is not replaced was refused.
    selected : ndarray of bool, shape (n_modes,) or None
        Modes redesigned (``None``: all).
    ratio : ndarray, shape (n_modes,) or None
        ``last_ratio`` updated for the replaced modes (``None`` without selection).
    """

    bank: IIRBank
    certified: np.ndarray
    modulus_margin: np.ndarray
    reasons: dict[int, str]
    selected: np.ndarray | None
    ratio: np.ndarray | None


def redesign(
    plant: control.TransferFunction,
    current: IIRBank,
    tel: TelemetryPSD,
    designer: Designer,
    *,
    modulus_margin: float,
    max_pole_radius: float = 1.0,
    last_ratio: np.ndarray | None = None,
    select: float | None = None,
    max_modes: int | None = None,
) -> Update:
    """One redesign: select the modes, design them, certify them, merge the certified ones.

    The step of :class:`AdaptiveController` at each period, as a function (a benchmark
    times it alone).

    Parameters
    ----------
    plant : control.TransferFunction
    current : IIRBank
        The bank in use.
    tel : TelemetryPSD
        Disturbance and noise estimate.
    designer : callable
        As in :class:`AdaptiveController`.
    modulus_margin, max_pole_radius : float
        Certificates (:func:`certify`).
    last_ratio : ndarray, shape (n_modes,), optional
        Per mode, ``rho`` of :func:`residual_shift` when its controller was designed
        (``nan``: never); with ``select``.
    select : float, optional
        Share of the total residual shift to cover (:func:`select_modes`);
        ``None``: every mode.
    max_modes : int, optional
        At most this many modes (with ``select``).

    Returns
    -------
    Update
    """
    n = current.n_modes
    modes = np.arange(n)
    selected = ratio = None
    if select is not None:
        last = np.full(n, np.nan) if last_ratio is None else np.asarray(last_ratio, float)
        shift, _ = residual_shift(current, plant, tel, last)
        selected = select_modes(shift, select, max_modes)
        modes = np.flatnonzero(selected)
        ratio = last.copy()
    ok = np.zeros(n, dtype=bool)
    margin = np.full(n, np.nan)
    reasons: dict[int, str] = {}
    if not modes.size:
        return Update(current, ok, margin, reasons, selected, ratio)
    proposal = designer(_subset(tel, modes), plant, _rows(current, modes))
    if not isinstance(proposal, Proposal):
        raise TypeError(f"the designer must return a Proposal, got {type(proposal).__name__}")
    if proposal.controller.n_modes != modes.size:
        raise ValueError(
            f"the designer proposed {proposal.controller.n_modes} modes, it was asked for "
            f"{modes.size}"
        )
    todo = [i for i in range(modes.size) if i not in proposal.failed]
    ok_s, margin_s, reasons_s = certify(
        plant,
        proposal.controller,
        modulus_margin=modulus_margin,
        max_pole_radius=max_pole_radius,
        modes=todo,
    )
    ok[modes], margin[modes] = ok_s, margin_s
    reasons = {
        **{int(modes[i]): f"design failed: {msg}" for i, msg in proposal.failed.items()},
        **{int(modes[i]): msg for i, msg in reasons_s.items()},
    }
    if ratio is not None and ok_s.any():
        take = np.flatnonzero(ok_s)
        _, rho = residual_shift(
            _rows(proposal.controller, take), plant, _subset(tel, modes[take]), ratio[modes[take]]
        )
        ratio[modes[take]] = rho
    full = _join(current, [(modes, proposal)]).controller
    return Update(_merge(current, full, ok), ok, margin, reasons, selected, ratio)


# ---------------------------------------------------------------------------- designers
def _has_integrator(bank: IIRBank) -> np.ndarray:
    """Modes whose controller has a pole at ``z = 1`` (``a(1) = 0``: integral action),
    shape (n_modes,)."""
    scale = np.abs(bank.a).sum(axis=1)
    return np.abs(bank.a.sum(axis=1)) <= _INTEGRATOR_RTOL * scale


def _rows(bank: IIRBank, modes: np.ndarray) -> IIRBank:
    """The rows ``modes`` of ``bank`` as a bank of their own."""
    stroke = None if bank.stroke is None else bank.stroke[modes]
    return IIRBank(bank.b[modes], bank.a[modes], bank.fs, stroke=stroke)


def _subset(tel: TelemetryPSD, modes: np.ndarray) -> TelemetryPSD:
    """The modes ``modes`` of a telemetry estimate."""
    return dataclasses.replace(
        tel,
        psd=tel.psd[modes],
        noise_psd=tel.noise_psd[modes],
        pseudo_open_loop=tel.pseudo_open_loop[:, modes],
        pol_psd=tel.pol_psd[modes],
    )


def _warm_start_refused(exc: ValueError) -> bool:
    """Whether :func:`~aocontrol.synthesis.datadriven` refused ``initial`` as a start (its
    free poles outside ``max_pole_radius``), the one test of that refusal; when the synthesis
    raises a class of its own for it, ``except`` that class where this is called instead."""
    return "max_pole_radius" in str(exc)


def datadriven_designer(
    *,
    order: int = 5,
    modulus_margin: float = 0.5,
    n_jobs: int | None = 1,
    warm_max_iter: int | None = 8,
    warm_tol: float = 1e-2,
    **options: object,
) -> Designer:
    """Designer: :func:`aocontrol.synthesis.datadriven` warm-started from the current bank.

    A warm start keeps each mode's structure: the modes whose current controller has integral
    action (a pole at ``z = 1``) are redesigned with that factor fixed
    (``fixed_denominator = 1 - z^-1``), the others with every pole free, in two calls; the
    synthesis certifies both. A warm start is close to the optimum after a drift, so it runs
    at most ``warm_max_iter`` convex iterations with tolerance ``warm_tol`` (the synthesis
    never returns a design worse than its start). The loop's first bank (order below
    ``order``, e.g. the starting integrator) is not a warm start: that design starts cold
    (the synthesis chooses each mode's structure), with the full ``options``. A warm start the
    synthesis refuses anyway falls back to a cold start (logged).

    Parameters
    ----------
    order : int, default 5
        Controller order.
    modulus_margin : float, default 0.5
        Margin the synthesis enforces (certify with the same or a lower value).
    n_jobs : int or None, default 1
        Worker processes of the synthesis.
    warm_max_iter : int or None, default 8
        ``max_iter`` of a warm-started design (``None``: that of ``options``). Measured on
        turbulence modes after a 20 % wind change (3 kHz, 0.83 frame): 5 iterations reach
        the residual of 60 within 0.5 %.
    warm_tol : float, default 1e-2
        ``tol`` of a warm-started design.
    **options
        Other keyword arguments of :func:`~aocontrol.synthesis.datadriven` (``n_grid``,
        ``max_iter``, ``stroke_weight``...).
    """
    if warm_max_iter is not None:
        warm_max_iter = check_int("warm_max_iter", warm_max_iter, minimum=1)
    warm_tol = check_nonnegative("warm_tol", warm_tol)

    def design(tel: TelemetryPSD, plant: control.TransferFunction, current: IIRBank) -> Proposal:
        kwargs = dict(
            noise_psd=tel.noise_psd,
            order=order,
            modulus_margin=modulus_margin,
            n_jobs=n_jobs,
            progress=False,
        )
        kwargs.update(options)

        def run(psd: TelemetryPSD, initial: IIRBank | None, **extra: object) -> Proposal:
            kw = {**kwargs, "noise_psd": psd.noise_psd, **extra}
            try:
                res = datadriven(plant, psd.freqs, psd.psd, initial=initial, **kw)
            except DataDrivenError as exc:
                return Proposal(exc.result.controller, dict(exc.failed))
            return Proposal(res.controller)

        if current.a.shape[1] - 1 < order:
            return run(tel, None)  # the loop's first bank: a cold design
        warm: dict[str, object] = {"tol": warm_tol}
        if warm_max_iter is not None:
            warm["max_iter"] = warm_max_iter
        integral = _has_integrator(current)
        parts = []
        try:
            for take, fixed in ((integral, [1.0, -1.0]), (~integral, None)):
                modes = np.flatnonzero(take)
                if modes.size:
                    sub = run(
                        _subset(tel, modes),
                        _rows(current, modes),
                        fixed_denominator=fixed,
                        **warm,
                    )
                    parts.append((modes, sub))
        except ValueError as exc:
            if not _warm_start_refused(exc):
                raise
            logger.info("warm start refused (%s): cold start", exc)
            return run(tel, None)
        return _join(current, parts)

    design.__name__ = design.__qualname__ = f"datadriven(order={order})"
    return design


def _join(current: IIRBank, parts: list[tuple[np.ndarray, Proposal]]) -> Proposal:
    """One proposal from proposals for disjoint sets of modes (rows of ``current`` elsewhere)."""
    nb = max([current.b.shape[1]] + [p.controller.b.shape[1] for _, p in parts])
    na = max([current.a.shape[1]] + [p.controller.a.shape[1] for _, p in parts])
    b = np.pad(current.b, ((0, 0), (0, nb - current.b.shape[1])))
    a = np.pad(current.a, ((0, 0), (0, na - current.a.shape[1])))
    failed: dict[int, str] = {}
    for modes, p in parts:
        c = p.controller
        b[modes] = np.pad(c.b, ((0, 0), (0, nb - c.b.shape[1])))
        a[modes] = np.pad(c.a, ((0, 0), (0, na - c.a.shape[1])))
        failed.update({int(modes[i]): msg for i, msg in p.failed.items()})
    return Proposal(IIRBank(b, a, current.fs, stroke=current.stroke), failed)


def modal_gain_designer(*, modulus_margin: float | None = 0.5, leak: float = 0.0) -> Designer:
    """Designer: the residual-minimising integrator gain per mode
    (:func:`aocontrol.synthesis.optimal_modal_gain`), the usual adaptive practice.

    Parameters
    ----------
    modulus_margin : float or None, default 0.5
        Margin constraint of the gain search (``None``: stability limit only).
    leak : float, default 0.0
        Integrator leak.
    """

    def design(tel: TelemetryPSD, plant: control.TransferFunction, current: IIRBank) -> Proposal:
        try:
            bank = optimal_modal_gain(
                plant, tel.freqs, tel.psd, tel.noise_psd, modulus_margin=modulus_margin, leak=leak
            )
            failed: dict[int, str] = {}
        except ModalGainError as exc:
            bank, failed = exc.result, dict(exc.failed)
        return Proposal(IIRBank(bank.b, bank.a, bank.fs), failed)

    design.__name__ = design.__qualname__ = "modal gain"
    return design


def lqg_designer(*, n_vibrations: int = 2, control_weight: float = 0.0) -> Designer:
    """Designer: LQG re-identified from the window (:func:`aocontrol.synthesis.lqg` on the
    estimated PSDs), run as its exact transfer function per mode (an :class:`IIRBank`), so
    that it is certified, merged per mode and switched bumplessly like the others.

    Parameters
    ----------
    n_vibrations : int, default 2
        Resonances fitted per mode.
    control_weight : float, default 0.0
        Weight of ``u^2`` in the LQ cost.
    """

    def design(tel: TelemetryPSD, plant: control.TransferFunction, current: IIRBank) -> Proposal:
        bank = lqg(
            plant,
            tel.freqs,
            tel.psd,
            noise_psd=tel.noise_psd,
            n_vibrations=n_vibrations,
            control_weight=control_weight,
        )
        tfs = [bank.transfer_function(i) for i in range(bank.n_modes)]
        return Proposal(IIRBank.from_transfer_functions(tfs))

    design.__name__ = design.__qualname__ = "LQG"
    return design


# ---------------------------------------------------------------------------- controller
class AdaptiveController(ControllerBank):
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
        Redesign only the modes whose disturbance changed enough to matter: the fewest modes,
        largest first, whose residual shifts (:func:`residual_shift`: how far the current
        controller's residual moved from what a change of the disturbance's scale explains,
        since its design) cover this share, in (0, 1], of the total;
        modes never designed always. ``None`` (default): every mode at every design. The
        others keep their controller (not counted as rejected). See :func:`select_modes`.
    max_modes : int, optional
        At most this many modes per design (with ``select``; the largest predicted gains).

    Attributes
    ----------
    current : IIRBank
        The bank in use.
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
        self._plant = plant
        self._designer = designer
        self._fs = fs
        self._period = check_positive("period", period)
        self._window = check_positive("window", window)
        self._period_frames = max(1, round(self._period * fs))
        self._window_frames = round(self._window * fs)
        if self._window_frames < MIN_WINDOW_FRAMES:
            raise ValueError(
                f"window must hold at least {MIN_WINDOW_FRAMES} frames for a PSD "
                f"({MIN_WINDOW_FRAMES / fs:.3g} s at {fs:g} Hz), got {window!r} s"
            )
        if nperseg is not None:
            nperseg = check_int("nperseg", nperseg, minimum=8)
            if nperseg > self._window_frames:
                raise ValueError(
                    f"window must hold at least nperseg={nperseg} frames "
                    f"({nperseg / fs:.3g} s), got {window!r} s"
                )
        self._nperseg = nperseg
        self._noise_band = noise_band
        self._max_designs = (
            None if max_designs is None else check_int("max_designs", max_designs, minimum=1)
        )
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
        if estimator is not None and not callable(estimator):
            raise TypeError(f"estimator must be callable, got {estimator!r}")
        self._estimator = estimator
        if latency is None:
            self._latency_frames = None
        else:
            latency = check_nonnegative("latency", latency)
            if latency >= self._period:
                raise ValueError(
                    f"latency must be shorter than period={self._period:g} s, got {latency!r} s"
                )
            self._latency_frames = math.ceil(latency * fs - 1e-9)
        self._mu = check_in_range("modulus_margin", modulus_margin, 0.0, 1.0, high_inclusive=False)
        self._rmax = check_positive("max_pole_radius", max_pole_radius)
        b, a = z_inverse_coefficients(plant, "plant")
        # Frames of the pseudo open loop's start-up transient (the plant's memory), dropped.
        self._lead = max(b.size, a.size)
        self.last_run: AdaptiveRun | None = None
        self.run = AdaptiveRun()
        self.reset()

    # -- interface ------------------------------------------------------------------------
    @property
    def n_modes(self) -> int:
        return self._initial.n_modes

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
        self.run = AdaptiveRun()
        self.current = _merge(self._initial, self._initial, np.zeros(self.n_modes, dtype=bool))
        self._last_ratio = np.full(self.n_modes, np.nan)
        cap = self._window_frames + self._lead
        self._cap = cap
        self._m = np.zeros((cap, self.n_modes))
        self._u = np.zeros((cap, self.n_modes))
        self._k = 0
        self._pending: tuple[int, IIRBank] | None = None

    def transfer_function(self, mode: int = 0) -> control.TransferFunction:
        """The current bank's controller of ``mode`` (it changes at each switch)."""
        return self.current.transfer_function(mode)

    def _step(self, m: np.ndarray) -> np.ndarray:
        k = self._k
        if self._pending is not None and self._pending[0] == k:
            self._switch(self._pending[1])
            self._pending = None
        due = k and k % self._period_frames == 0 and k >= self._window_frames
        if due and self._max_designs is not None:
            due = len(self.run.redesigns) < self._max_designs
        if due:
            if self._pending is None:
                self._redesign(k)
                if self._pending is not None and self._pending[0] == k:  # zero latency
                    self._switch(self._pending[1])
                    self._pending = None
            else:
                self.run.n_skipped += 1
        u = self.current.step(m)
        slot = k % self._cap
        self._m[slot] = m
        self._u[slot] = u
        self._k = k + 1
        self.run.frames = self._k
        return u

    # -- internals ------------------------------------------------------------------------
    def _history(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The last ``n`` frames of (m, u), oldest first (fewer if fewer were stepped)."""
        n = min(n, self._k, self._cap)
        idx = np.arange(self._k - n, self._k) % self._cap
        return self._m[idx], self._u[idx]

    def _switch(self, bank: IIRBank) -> None:
        depth = max(bank.b.shape[1], bank.a.shape[1])
        m, u = self._history(max(BUMPLESS_FRAMES, 4 * depth) + depth)
        bank.reset()
        bank.set_history(m, bumpless_outputs(bank, m, u, fit_frames=m.shape[0] - depth))
        self.current = bank

    def _estimate(self, k: int) -> TelemetryPSD:
        """The disturbance and noise estimate of a design requested at frame ``k``."""
        if self._oracle is not None:
            return self._oracle(k)
        m, u = self._history(self._window_frames + self._lead)
        lead = m.shape[0] - self._window_frames
        pol = pseudo_open_loop(m, u, self._plant)[lead:]
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
        )
        if up.ratio is not None:
            self._last_ratio = up.ratio
        seconds = time.perf_counter() - t0
        latency = (
            math.ceil(seconds * self._fs) if self._latency_frames is None else self._latency_frames
        )
        switch = None
        if up.certified.any():
            switch = k + latency
            self._pending = (switch, up.bank)
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
            )
        )

    def __repr__(self) -> str:
        return (
            f"AdaptiveController(n_modes={self.n_modes}, fs={self._fs:g}, period={self._period:g}"
            f" s, window={self._window:g} s, designer={getattr(self._designer, '__name__', '?')})"
        )
