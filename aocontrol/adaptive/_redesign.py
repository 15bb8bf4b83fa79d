"""Certification, mode selection and one redesign of a bank (see :mod:`aocontrol.adaptive`)."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import control
import numpy as np

from aocontrol._validation import check_in_range, check_positive
from aocontrol.adaptive._realisation import StateSpaceRows, state_space_gains
from aocontrol.analysis import (
    is_stable,
    modulus_certificate,
    rational_modulus_minima,
    residual_variance,
    wiener_bound,
)
from aocontrol.controllers import IIRBank
from aocontrol.plant import z_inverse_coefficients
from aocontrol.synthesis import TelemetryPSD

# Relative slack on the modulus margin certificate (rounding of the margin computation).
_MARGIN_RTOL = 1e-9
# Slack on the controller pole radius (rounding of companion-matrix eigenvalues).
_POLE_RTOL = 1e-9
#: Default largest closed-loop gain from a perturbation of a controller's recursion to its
#: command (:func:`recursion_gain`): a well-conditioned filter has tens to hundreds; the
#: Direct-Form I transfer function of an LQG with nearly cancelling pole/zero pairs near
#: ``z = 1`` had ``1e12`` and diverged at a bumpless switch (issue 17).
MAX_RECURSION_GAIN = 1e5
#: Criteria that rank the modes of a selective redesign (``rank`` of :func:`redesign`).
RANKINGS = ("bound", "shift")
#: FFT size of the Wiener bound of the ``"bound"`` ranking (a ranking, not a certificate:
#: 0.3 s of CPU for 540 modes against 56 s at the bound's default of 32768; its
#: resolution error on the lowest modes largely cancels in the ratio to the same bound).
BOUND_N_FFT = 1024


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
    margin : ndarray, shape (n_modes,), optional
        Modulus margin each mode was certified with by the designer on the same plant, with
        the analysis layer's certificates (:func:`aocontrol.analysis.modulus_certificate`,
        exact over the whole circle for a transfer-function plant, and
        :func:`aocontrol.analysis.is_stable`): the data-driven synthesis certifies every
        design so. :func:`certify` then reuses it instead of certifying the mode again
        (the pole radius and the margin against ``modulus_margin`` are still checked);
        ``nan`` (or ``None`` for all) where the designer did not certify.
    realisation : StateSpaceRows, optional
        State-space realisations the loop runs instead of ``controller``'s Direct-Form I
        recursion, for the modes in ``realisation.used`` (e.g. an LQG's observer form: its
        exact transfer function is an ill-conditioned recursion); ``controller`` still
        holds their transfer functions (certified from it). ``None``: every mode in
        Direct-Form I.
    kept : tuple of int, default ()
        Modes (indices into the proposal) whose new design was worse than the current
        controller, so that the designer proposes the current one again (the synthesis'
        "never worse than its start"): counted, not an error.
    """

    controller: IIRBank
    failed: dict[int, str] = field(default_factory=dict)
    margin: np.ndarray | None = None
    realisation: StateSpaceRows | None = None
    kept: tuple[int, ...] = ()


Designer = Callable[[TelemetryPSD, control.TransferFunction, IIRBank], Proposal]


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


def recursion_gain(plant: control.TransferFunction, b: np.ndarray, a: np.ndarray) -> float:
    """Closed-loop gain from a perturbation of a Direct-Form I recursion to its command.

    A controller ``u = (b / a) m`` on a plant ``G = gb / ga`` (powers of ``z^-1``) run as
    ``a u = b m + w``, where ``w`` is any mismatch of its recursion (a switch's initial
    state, round-off), gives ``u = ga / (a ga + b gb) w``. The transfer function of a
    controller can be exact and its closed loop stable with a margin while this gain is
    ``1e12`` (nearly cancelling pole/zero pairs near ``z = 1``): the command then diverges
    from any mismatch. Returned: ``max |ga| / min |a ga + b gb|`` over the unit circle, an
    upper bound of the gain ``max |ga / (a ga + b gb)|`` (refusing on it is conservative),
    both extremes certified over the whole circle by
    ``aocontrol.analysis.rational_modulus_minima`` (stationary points as polynomial
    roots, and a grid refined around every root near the circle).

    Parameters
    ----------
    plant : control.TransferFunction
        Loop plant.
    b, a : ndarray, shape (nb,), (na,)
        Controller coefficients in powers of ``z^-1``.

    Returns
    -------
    float
        The gain (``inf`` if ``a ga + b gb`` vanishes on the unit circle).
    """
    gb, ga = z_inverse_coefficients(plant, "plant")
    return _recursion_gain(gb, ga, _plant_peak(ga), b, a)


def _plant_peak(ga: np.ndarray) -> float:
    """``max 1 / |ga|`` over the unit circle (certified), the plant's part of
    :func:`recursion_gain`: the same for every mode of a bank, computed once per plant."""
    return 1.0 / float(np.min(rational_modulus_minima(np.ones(1), ga)[1]))


def _recursion_gain(
    gb: np.ndarray, ga: np.ndarray, peak: float, b: np.ndarray, a: np.ndarray
) -> float:
    """:func:`recursion_gain` from the plant's coefficients and ``peak = _plant_peak(ga)``."""
    bg = np.convolve(b, gb)
    ag = np.convolve(a, ga)
    ch = np.zeros(max(bg.size, ag.size))
    ch[: bg.size] += bg
    ch[: ag.size] += ag
    den = float(np.min(rational_modulus_minima(ch, np.ones(1))[1]))
    return float(peak / den) if den > 0 else float("inf")


def certify(
    plant: control.TransferFunction,
    bank: IIRBank,
    *,
    modulus_margin: float,
    max_pole_radius: float = 1.0,
    modes: object = None,
    certified_margin: np.ndarray | None = None,
    max_recursion_gain: float = MAX_RECURSION_GAIN,
    realisation: StateSpaceRows | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[int, str]]:
    """Certificates of each mode of ``bank`` on ``plant``: what may be switched into a loop.

    A mode passes when its closed loop is stable (:func:`aocontrol.analysis.is_stable`), its
    modulus margin ``min |1 + G K|`` is at least ``modulus_margin``
    (:func:`aocontrol.analysis.modulus_certificate`: exact over the whole circle for a
    transfer-function plant; the values :func:`aocontrol.analysis.margins` reports), every
    pole of its controller has modulus at most ``max_pole_radius`` (batched companion
    matrices; 1 admits an integrator's pole at ``z = 1``) and the coefficients the loop runs
    are a well-conditioned recursion: the closed-loop gain from a mismatch of the Direct-Form
    I state to the command (:func:`recursion_gain`) is at most ``max_recursion_gain``; a mode
    the loop runs in state space (``realisation``) is checked on that realisation instead:
    the closed-loop gain from a mismatch of its state to the command
    (:func:`~aocontrol.adaptive._realisation.state_space_gains`) is at most
    ``max_recursion_gain``. A mode
    whose margin and stability the designer already certified with these certificates
    (``certified_margin``, :attr:`Proposal.margin`) does not have them computed twice (its
    pole radius and recursion gain are still checked).

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
    certified_margin : ndarray, shape (n_modes,), optional
        Margins already certified on ``plant`` (closed loop stable), ``nan`` where not: those
        modes are checked against ``modulus_margin`` and the pole radius only.
    max_recursion_gain : float, default :data:`MAX_RECURSION_GAIN`
        Largest :func:`recursion_gain` (or state-space gain) accepted, > 0.
    realisation : StateSpaceRows, optional
        The state-space realisations the loop will run for the modes in ``realisation.used``
        (rows aligned with ``bank``); their transfer functions are ``bank``'s.

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
    gmax = check_positive("max_recursion_gain", max_recursion_gain)
    n = bank.n_modes
    todo = np.arange(n) if modes is None else np.asarray(modes, dtype=int)
    ok = np.zeros(n, dtype=bool)
    margin = np.full(n, np.nan)
    reasons: dict[int, str] = {}
    known = np.full(n, np.nan)
    if certified_margin is not None:
        known = np.asarray(certified_margin, dtype=float)
        if known.shape != (n,):
            raise ValueError(
                f"certified_margin must have shape ({n},) (one per mode), got {known.shape}"
            )
    if realisation is not None and realisation.n_modes != n:
        raise ValueError(
            f"realisation must have {n} modes (one per mode), got {realisation.n_modes}"
        )
    ss_gain = np.full(n, np.nan)
    if realisation is not None and realisation.used.any():
        ss_gain = state_space_gains(plant, realisation)
    radius = _pole_radius(bank.a)
    plant_part = None  # recursion_gain's plant part (gb, ga, peak): once for every mode
    for i in todo:
        i = int(i)
        if radius[i] > rmax * (1 + _POLE_RTOL):
            reasons[i] = f"controller pole radius {radius[i]:.6g} > {rmax:g}"
            continue
        stable = True
        if np.isfinite(known[i]):
            margin[i] = known[i]
        else:
            K = bank.transfer_function(i)
            margin[i] = modulus_certificate(plant, K).value
            stable = is_stable(plant, K)
        if not stable:
            reasons[i] = "closed loop unstable"
        elif margin[i] < mu * (1 - _MARGIN_RTOL):
            reasons[i] = f"modulus margin {margin[i]:.4g} < {mu:g}"
        elif realisation is not None and realisation.used[i]:
            if not ss_gain[i] <= gmax:
                reasons[i] = (
                    f"state-space gain {ss_gain[i]:.3g} > {gmax:g} (ill-conditioned realisation)"
                )
            else:
                ok[i] = True
        else:
            if plant_part is None:
                gb, ga = z_inverse_coefficients(plant, "plant")
                plant_part = (gb, ga, _plant_peak(ga))
            if (g := _recursion_gain(*plant_part, bank.b[i], bank.a[i])) > gmax:
                reasons[i] = f"recursion gain {g:.3g} > {gmax:g} (ill-conditioned realisation)"
            else:
                ok[i] = True
    return ok, margin, reasons


def _subset(tel: TelemetryPSD, modes: np.ndarray) -> TelemetryPSD:
    """The modes ``modes`` of a telemetry estimate (``tel`` itself for all of them, in order:
    no copy of its pseudo-open-loop record, 66 MB for 540 modes of 15,300 frames)."""
    n = tel.psd.shape[0]
    if modes.size == n and np.array_equal(modes, np.arange(n)):
        return tel
    return dataclasses.replace(
        tel,
        psd=tel.psd[modes],
        noise_psd=tel.noise_psd[modes],
        pseudo_open_loop=tel.pseudo_open_loop[:, modes],
        pol_psd=tel.pol_psd[modes],
    )


def _join(current: IIRBank, parts: list[tuple[np.ndarray, Proposal]]) -> Proposal:
    """One proposal from proposals for disjoint sets of modes (rows of ``current`` elsewhere)."""
    bank = current
    failed: dict[int, str] = {}
    margin = np.full(current.n_modes, np.nan)
    kept: list[int] = []
    for modes, p in parts:
        bank = bank.with_rows(modes, p.controller)
        failed.update({int(modes[i]): msg for i, msg in p.failed.items()})
        if p.margin is not None:
            margin[modes] = p.margin
        kept.extend(int(modes[i]) for i in p.kept)
    return Proposal(bank, failed, margin, kept=tuple(sorted(kept)))


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


def _bound(plant: control.TransferFunction, tel: TelemetryPSD) -> np.ndarray:
    """Wiener bound of each mode of ``tel`` at :data:`BOUND_N_FFT` [units^2], shape (n_modes,)."""
    with warnings.catch_warnings():
        # At this FFT size the bound of the lowest modes is coarse (a UserWarning): expected.
        warnings.simplefilter("ignore", UserWarning)
        b = wiener_bound(plant, tel.freqs, tel.psd, tel.noise_psd, n_fft=BOUND_N_FFT)
    return np.atleast_1d(np.asarray(b, dtype=float))


def recoverable_gain(
    current: IIRBank,
    plant: control.TransferFunction,
    tel: TelemetryPSD,
    last_efficiency: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Residual a redesign of each mode is predicted to recover [units^2].

    ``eta = J / B``: the current controller's predicted residual on the estimate
    (:func:`~aocontrol.analysis.residual_variance`) over the smallest residual any causal
    controller reaches on it (:func:`~aocontrol.analysis.wiener_bound`, at
    :data:`BOUND_N_FFT`). A design reaches some efficiency ``eta_d`` on the estimate it was
    designed from (``last_efficiency``: its order, its margin); redesigned on the new
    estimate it is predicted to reach the same, so the gain is ``J - eta_d B`` (at least 0).
    Unlike :func:`residual_shift` (where the residual moved), this ranks where a redesign
    gets it back: a mode whose residual grew with the seeing but is still at its design
    efficiency has nothing to recover. A mode never designed (``nan``) has an infinite gain.

    Parameters
    ----------
    current : IIRBank
        The controllers in use (certified: their loops are stable).
    plant : control.TransferFunction
    tel : TelemetryPSD
        The new estimate.
    last_efficiency : ndarray, shape (n_modes,)
        ``eta`` of each mode's controller on the estimate it was designed from.

    Returns
    -------
    gain : ndarray, shape (n_modes,)
        ``max(J - last_efficiency B, 0)`` [units^2] (``inf`` where ``last_efficiency`` is
        ``nan``).
    eta : ndarray, shape (n_modes,)
        ``J / B`` of the current controllers on the estimate.
    """
    j = residual_variance(plant, current, tel.freqs, tel.psd, tel.noise_psd, check_stability=False)
    b = _bound(plant, tel)
    with np.errstate(divide="ignore", invalid="ignore"):
        eta = np.where(b > 0, j / b, 1.0)
        gain = np.maximum(j - last_efficiency * b, 0.0)
    return np.where(np.isnan(last_efficiency), np.inf, gain), eta


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
    realisation : StateSpaceRows or None
        State-space realisations of the replaced modes that run in state space (rows of all
        modes; ``used`` only where certified), ``None`` if none.
    kept : ndarray of bool, shape (n_modes,) or None
        Modes whose new design was worse than their controller, which the designer proposed
        again (:attr:`Proposal.kept`; ``None``: none).
    """

    bank: IIRBank
    certified: np.ndarray
    modulus_margin: np.ndarray
    reasons: dict[int, str]
    selected: np.ndarray | None
    ratio: np.ndarray | None
    realisation: StateSpaceRows | None = None
    kept: np.ndarray | None = None


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
    rank: str = "shift",
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
        Per mode, the ranking's ratio when its controller was designed (``nan``: never):
        ``eta`` of :func:`recoverable_gain` (``rank="bound"``) or ``rho`` of
        :func:`residual_shift` (``rank="shift"``); with ``select``.
    select : float, optional
        Share of the total predicted gain to cover (:func:`select_modes`);
        ``None``: every mode.
    max_modes : int, optional
        At most this many modes (with ``select``), the largest predicted gains first.
    rank : {"bound", "shift"}, default "shift"
        What ranks the modes (with ``select``): the residual a redesign is predicted to
        recover (:func:`recoverable_gain`) or how far the residual moved since the design
        (:func:`residual_shift`); see :mod:`aocontrol.adaptive`.

    Returns
    -------
    Update
    """
    if rank not in RANKINGS:
        raise ValueError(f"rank must be one of {list(RANKINGS)}, got {rank!r}")
    score = recoverable_gain if rank == "bound" else residual_shift
    n = current.n_modes
    modes = np.arange(n)
    selected = ratio = None
    if select is not None:
        last = np.full(n, np.nan) if last_ratio is None else np.asarray(last_ratio, float)
        gain, _ = score(current, plant, tel, last)
        selected = select_modes(gain, select, max_modes)
        modes = np.flatnonzero(selected)
        ratio = last.copy()
    ok = np.zeros(n, dtype=bool)
    margin = np.full(n, np.nan)
    reasons: dict[int, str] = {}
    if not modes.size:
        return Update(current, ok, margin, reasons, selected, ratio)
    proposal = designer(_subset(tel, modes), plant, current.rows(modes))
    if not isinstance(proposal, Proposal):
        raise TypeError(f"the designer must return a Proposal, got {type(proposal).__name__}")
    if proposal.controller.n_modes != modes.size:
        raise ValueError(
            f"the designer proposed {proposal.controller.n_modes} modes, it was asked for "
            f"{modes.size}"
        )
    if proposal.margin is not None and np.shape(proposal.margin) != (modes.size,):
        raise ValueError(
            f"the designer's Proposal.margin must have shape ({modes.size},), got "
            f"{np.shape(proposal.margin)}"
        )
    rows = proposal.realisation
    if rows is not None and rows.n_modes != modes.size:
        raise ValueError(
            f"the designer's Proposal.realisation must have {modes.size} modes, got {rows.n_modes}"
        )
    todo = [i for i in range(modes.size) if i not in proposal.failed]
    ok_s, margin_s, reasons_s = certify(
        plant,
        proposal.controller,
        modulus_margin=modulus_margin,
        max_pole_radius=max_pole_radius,
        modes=todo,
        certified_margin=proposal.margin,
        realisation=rows,
    )
    ok[modes], margin[modes] = ok_s, margin_s
    reasons = {
        **{int(modes[i]): f"design failed: {msg}" for i, msg in proposal.failed.items()},
        **{int(modes[i]): msg for i, msg in reasons_s.items()},
    }
    if ratio is not None and ok_s.any():
        take = np.flatnonzero(ok_s)
        _, rho = score(
            proposal.controller.rows(take), plant, _subset(tel, modes[take]), ratio[modes[take]]
        )
        ratio[modes[take]] = rho
    full = _join(current, [(modes, proposal)]).controller
    realised = None
    if rows is not None and (rows.used & ok_s).any():
        taken = dataclasses.replace(rows, used=rows.used & ok_s)
        realised = taken.expand(modes, n)
    kept = None
    if proposal.kept:
        kept = np.zeros(n, dtype=bool)
        kept[modes[np.asarray(proposal.kept, dtype=int)]] = True
    return Update(current.where(ok, full), ok, margin, reasons, selected, ratio, realised, kept)
