"""Designers of :class:`aocontrol.adaptive.AdaptiveController`: data-driven, modal gain, LQG."""

from __future__ import annotations

import logging
import warnings

import control
import numpy as np

from aocontrol._validation import check_in_range, check_int, check_nonnegative
from aocontrol.adaptive._realisation import StateSpaceRows
from aocontrol.adaptive._redesign import Designer, Proposal, _join, _subset
from aocontrol.analysis import residual_variance
from aocontrol.controllers import IIRBank
from aocontrol.synthesis import (
    REJECTED_WORSE,
    DataDrivenError,
    DataDrivenResult,
    InitialPoleRadiusError,
    ModalGainError,
    TelemetryPSD,
    datadriven,
    has_integrator,
    lqg,
    optimal_modal_gain,
)

logger = logging.getLogger(__name__)

#: Default ``rtol`` of ``cancel_near_pairs`` (pole/zero distance over the pole's distance
#: to the unit circle).
CANCEL_RTOL = 0.1
#: Default largest relative change of an LQG's response made by a cancellation.
CANCEL_MAX_ERROR = 0.05
#: Points of the unit circle on which that change is measured.
_CHECK_POINTS = 2048
# The LQG fit's note on a spectrum still rising at the PSD's lowest frequency (synthesis._arfit).
_LOW_FREQUENCY_NOTE = "keeps rising down to the lowest grid frequency"


def _certified(res: DataDrivenResult) -> np.ndarray:
    """The margins the synthesis certified (exact over the circle, closed loop stable; ``nan``
    for a failed mode), passed on so that the adaptive layer does not certify them again."""
    ok = res.ok & res.stable
    return np.where(ok, res.modulus_margin, np.nan)


def _kept(res: DataDrivenResult) -> tuple[int, ...]:
    """Modes whose design was worse than their start, replaced by it (the synthesis' reports:
    :data:`aocontrol.synthesis.REJECTED_WORSE` in ``start``)."""
    return tuple(r.mode for r in res.reports if r.ok and r.start == REJECTED_WORSE)


def datadriven_designer(
    *,
    order: int = 5,
    modulus_margin: float = 0.5,
    n_jobs: int | None = 1,
    warm_max_iter: int | None = 8,
    warm_tol: float = 1e-2,
    warm_n_grid: int | None = None,
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
        ``max_iter`` of a warm-started design (``None``: that of ``options``); chosen by
        ``benchmarks/bench_adaptive.py`` (``docs/benchmarks.md``).
    warm_tol : float, default 1e-2
        ``tol`` of a warm-started design.
    warm_n_grid : int or None, default None
        ``n_grid`` of a warm-started design (``None``: that of ``options``). A warm
        redesign needs less resolution than a cold one: the exact modulus certificate
        still guards the margin, and the synthesis' fine-grid check still refuses a design
        worse than the current controller. ``warm_n_grid=32`` with ``warm_max_iter=1`` keeps
        most of the gain for a fraction of the CPU on a large bank
        (``benchmarks/bench_adaptive.py --parts c --sweep``, ``docs/benchmarks.md``). The
        loop's defaults stay 8 iterations on the cold design's grid: a small loop affords
        them.
    **options
        Other keyword arguments of :func:`~aocontrol.synthesis.datadriven` (``n_grid``,
        ``max_iter``, ``hinf_weight``...).
    """
    if warm_max_iter is not None:
        warm_max_iter = check_int("warm_max_iter", warm_max_iter, minimum=1)
    warm_tol = check_nonnegative("warm_tol", warm_tol)
    if warm_n_grid is not None:
        warm_n_grid = check_int("warm_n_grid", warm_n_grid, minimum=8)

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
                res = exc.result
                return Proposal(res.controller, dict(exc.failed), _certified(res), kept=_kept(res))
            return Proposal(res.controller, margin=_certified(res), kept=_kept(res))

        if current.a.shape[1] - 1 < order:
            return run(tel, None)  # the loop's first bank: a cold design
        warm: dict[str, object] = {"tol": warm_tol}
        if warm_max_iter is not None:
            warm["max_iter"] = warm_max_iter
        if warm_n_grid is not None:
            warm["n_grid"] = warm_n_grid
        integral = has_integrator(current)
        parts = []
        try:
            for take, fixed in ((integral, [1.0, -1.0]), (~integral, None)):
                modes = np.flatnonzero(take)
                if modes.size:
                    sub = run(
                        _subset(tel, modes),
                        current.rows(modes),
                        fixed_denominator=fixed,
                        **warm,
                    )
                    parts.append((modes, sub))
        except InitialPoleRadiusError as exc:
            # The synthesis refuses a start whose free poles lie outside its max_pole_radius
            # (e.g. the loop's first controller): start from its own default instead (cold).
            logger.info("warm start refused (%s): cold start", exc)
            return run(tel, None)
        return _join(current, parts)

    design.__name__ = design.__qualname__ = f"datadriven(order={order})"
    return design


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


def cancel_near_pairs(tf: control.TransferFunction, rtol: float) -> control.TransferFunction:
    """``tf`` without its nearly cancelling pole/zero pairs near the unit circle.

    A zero ``z`` cancels the nearest remaining pole ``p`` when ``|z - p| <= rtol (1 - |p|)``
    (with exact roots each cancelled pair changes the response on the unit circle by at most
    ``rtol``; the roots of a high-order polynomial with clustered roots are not exact, so the
    caller measures the change). The gain (leading coefficients) is kept.

    Parameters
    ----------
    tf : control.TransferFunction
        Discrete SISO transfer function.
    rtol : float
        Largest ``|z - p| / (1 - |p|)`` cancelled, in [0, 1).

    Returns
    -------
    control.TransferFunction
        Same ``dt`` (``tf`` itself when nothing cancels).
    """
    num = np.atleast_1d(np.squeeze(tf.num[0][0]))
    den = np.atleast_1d(np.squeeze(tf.den[0][0]))
    poles = list(np.roots(den))
    kept = []
    zeros = np.roots(num)
    for z in zeros:
        if poles:
            dist = np.abs(np.asarray(poles) - z)
            j = int(np.argmin(dist))
            slack = 1.0 - abs(poles[j])
            if slack > 0 and dist[j] <= rtol * slack:
                poles.pop(j)
                continue
        kept.append(z)
    if len(kept) == len(zeros):
        return tf
    b = num[0] / den[0] * np.real(np.poly(kept))
    a = np.real(np.poly(poles))
    return control.tf(np.atleast_1d(b), np.atleast_1d(a), tf.dt)


def _response_error(tf: control.TransferFunction, F, G, H, J) -> float:
    """Largest relative error of ``tf`` against the state space ``J + H (zI - F)^-1 G``
    (shapes (ns, ns), (ns,), (ns,), ()) on :data:`_CHECK_POINTS` points of the unit circle."""
    z = np.exp(1j * np.linspace(0.0, np.pi, _CHECK_POINTS))
    lhs = z[:, None, None] * np.eye(F.shape[0]) - F
    x = np.linalg.solve(lhs, np.broadcast_to(G, (z.size, G.size))[..., None])[..., 0]
    ref = J + x @ H
    got = np.asarray(tf(z)).ravel()
    return float(np.max(np.abs(got - ref) / np.maximum(np.abs(ref), 1e-300)))


#: Realisations an LQG designer proposes (``realisation`` of :func:`lqg_designer`).
LQG_REALISATIONS = ("state-space", "direct")


def lqg_designer(
    *,
    n_vibrations: int = 2,
    control_weight: float = 0.0,
    cancel_rtol: float = CANCEL_RTOL,
    cancel_max_error: float = CANCEL_MAX_ERROR,
    realisation: str = "state-space",
    no_worse: bool = True,
) -> Designer:
    """Designer: LQG re-identified from the window (:func:`aocontrol.synthesis.lqg` on the
    estimated PSDs), certified, merged per mode and switched bumplessly like the others.

    ``realisation="state-space"`` (default): each mode runs in the LQG's own observer form
    (the state space :class:`~aocontrol.controllers.LQGBank` runs: the Kalman prediction of
    the loop state, ``x <- F x + G m``, ``u = H x + J m`` with ``F, G, H, J`` its
    ``controller_matrices``; the applied command enters the delay line, ``E = B``), its exact
    transfer function (``ss2tf``) held in the proposal's :class:`IIRBank` for the
    certificates and the mode selection; the certificate's conditioning check is then the
    state-space gain of that realisation (:class:`Proposal.realisation`), orders of magnitude
    below that of the Direct-Form I recursion of the same transfer function. No cancellation
    is needed (figures in ``docs/benchmarks.md``).

    ``realisation="direct"``: run as its transfer function in Direct-Form I. The LQG's exact
    transfer function (``ss2tf`` of its state space) carries nearly
    cancelling pole/zero pairs at the disturbance model's poles, close to ``z = 1``; in
    Direct-Form I they are internal modes with a closed-loop gain of ``1e7`` to ``1e9`` from
    any mismatch of the recursion's state, so a bumpless switch can diverge. They are
    cancelled (``cancel_near_pairs``) when the reduced
    transfer function stays within ``cancel_max_error`` of the LQG's state-space response
    (measured on the unit circle); the certificate (:func:`certify`, its recursion gain
    included) then decides what is switched in: a mode whose recursion stays ill-conditioned
    keeps its current controller.

    Parameters
    ----------
    n_vibrations : int, default 2
        Resonances fitted per mode.
    control_weight : float, default 0.0
        Weight of ``u^2`` in the LQ cost.
    cancel_rtol : float, default :data:`CANCEL_RTOL`
        ``rtol`` of ``cancel_near_pairs`` (0: the exact transfer function).
    cancel_max_error : float, default :data:`CANCEL_MAX_ERROR`
        Largest relative change of the response a cancellation may make.
    realisation : {"state-space", "direct"}, default "state-space"
        How the loop runs each mode (above); ``cancel_rtol`` and ``cancel_max_error`` apply
        to ``"direct"`` only.
    no_worse : bool, default True
        A mode whose LQG is predicted a larger residual on the very estimate it was designed
        from than the current controller (:func:`aocontrol.analysis.residual_variance`; the
        disturbance model fit failed, e.g. a 1-s window that does not resolve a slow mode's
        turbulence pole) is reported as not designed and keeps its controller, as the
        data-driven synthesis never returns a design worse than its start.
    """
    cancel_rtol = check_in_range("cancel_rtol", cancel_rtol, 0.0, 1.0, high_inclusive=False)
    max_error = check_nonnegative("cancel_max_error", cancel_max_error)
    if realisation not in LQG_REALISATIONS:
        raise ValueError(
            f"realisation must be one of {list(LQG_REALISATIONS)}, got {realisation!r}"
        )

    def _worse_than(tel, plant):
        def worse(proposal: IIRBank, current: IIRBank) -> dict[int, str]:
            if not no_worse:
                return {}
            args = (tel.freqs, tel.psd, tel.noise_psd)
            with np.errstate(all="ignore"):
                new = residual_variance(plant, proposal, *args, check_stability=False)
                old = residual_variance(plant, current, *args, check_stability=False)
            bad = ~(new <= old)
            return {
                int(i): f"predicted residual {new[i]:.4g} > {old[i]:.4g} of the current controller"
                for i in np.flatnonzero(bad)
            }

        return worse

    def design(tel: TelemetryPSD, plant: control.TransferFunction, current: IIRBank) -> Proposal:
        _worse = _worse_than(tel, plant)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            bank = lqg(
                plant,
                tel.freqs,
                tel.psd,
                noise_psd=tel.noise_psd,
                n_vibrations=n_vibrations,
                control_weight=control_weight,
            )
        for w in caught:
            # A window of W seconds resolves its PSD down to its Welch resolution only: the
            # fit's note that a spectrum keeps rising below it is expected at every redesign
            # (logged); any other warning passes on.
            if issubclass(w.category, UserWarning) and _LOW_FREQUENCY_NOTE in str(w.message):
                logger.info("%s", w.message)
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        F, G, H, J = bank.state_space.controller_matrices
        if realisation == "state-space":
            tfs = [bank.transfer_function(i) for i in range(bank.n_modes)]  # at a redesign only
            rows = StateSpaceRows(
                np.ones(bank.n_modes, bool), F, G, H, J, np.asarray(bank.state_space.B)
            )
            proposal = IIRBank.from_transfer_functions(tfs)
            return Proposal(proposal, _worse(proposal, current), realisation=rows)
        tfs = []
        for i in range(bank.n_modes):  # at a redesign only: a short loop of small systems
            exact = bank.transfer_function(i)
            reduced = cancel_near_pairs(exact, cancel_rtol) if cancel_rtol > 0 else exact
            moved = reduced is not exact and (
                _response_error(reduced, F[i], G[i], H[i], J[i]) > max_error
            )
            tfs.append(exact if moved else reduced)  # moved: keep the exact one
        proposal = IIRBank.from_transfer_functions(tfs)
        return Proposal(proposal, _worse(proposal, current))

    design.__name__ = design.__qualname__ = "LQG"
    return design
