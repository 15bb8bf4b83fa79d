"""Assembly of the data-driven synthesis' result (private; see :mod:`._datadriven`).

The bank from the per-mode outcomes, the predicted residuals on the input grid and on the fine
check, the fallback to the start for a design worse than it, and the per-mode reports.
"""

from __future__ import annotations

import logging
import warnings

import numpy as np

from aocontrol.analysis import residual_psd, robust_margin
from aocontrol.controllers import IIRBank
from aocontrol.synthesis._dd_certify import start_certificate
from aocontrol.synthesis._dd_context import DesignContext, exact_quotient
from aocontrol.synthesis._dd_grids import fine_residual
from aocontrol.synthesis._dd_results import (
    GRID_DISAGREEMENT,
    DataDrivenError,
    DataDrivenResult,
    GridResolutionWarning,
    ModeReport,
)

logger = logging.getLogger(__name__)

#: ``ModeReport.start`` of a mode whose design was worse than its start, which replaced it.
REJECTED_WORSE = "initial (design rejected: worse)"


def _assemble(setup, outcomes: list, threads: int = 1) -> DataDrivenResult:
    """Bank, reports and predicted residuals; raises DataDrivenError if a mode failed.

    A designed mode whose residual is higher than its starting controller's, on the input
    grid or on the fine check, is replaced by the starting controller (reported). The fine
    check runs on ``threads`` threads.
    """
    plant, freqs, fs, ctx = setup.plant, setup.freqs, setup.fs, setup.ctx
    psd2, noise2, init_bank = setup.psd, setup.noise, setup.init_bank
    n_modes = len(outcomes)
    done = [r for r in outcomes if not r["error"]]
    designed = np.zeros(n_modes, bool)
    designed[[r["mode"] for r in done]] = True
    bank = init_bank
    if done:
        rows = IIRBank.from_rows([r["b"] for r in done], [r["a"] for r in done], fs)
        bank = init_bank.with_rows([r["mode"] for r in done], rows)
    var = np.trapezoid(residual_psd(plant, bank, freqs, psd2, noise2, fs=fs), freqs, axis=-1)
    var0 = np.trapezoid(residual_psd(plant, init_bank, freqs, psd2, noise2, fs=fs), freqs, axis=-1)
    peaks = [np.empty(0)] * n_modes  # each mode's |S| peaks [Hz] (none for a failed one)
    for r in outcomes:
        if not r["error"]:
            peaks[r["mode"]] = r.get("peaks_hz", np.empty(0))
    fine, fine0 = fine_residual(
        plant, (bank, init_bank), freqs, psd2, noise2, fs, peaks, threads=threads
    )
    worse = designed & ((var > var0 * (1 + _WORSE_TOL)) | (fine > fine0 * (1 + _WORSE_TOL)))
    if worse.any():
        # Keeping a user's start (a warm redesign: the adaptive loop's running controller) is
        # the promise "never worse than its start", reported per mode and logged as
        # information; a cold design worse than the default integrator is a warning.
        logger.log(
            logging.INFO if setup.user_initial else logging.WARNING,
            "%d mode(s) designed worse than their starting controller on the input grid or the "
            "fine check: the starting controller is kept for them (modes %s)",
            int(worse.sum()),
            np.flatnonzero(worse)[:10].tolist(),
        )
        bank = bank.where(worse, init_bank)
        var[worse], fine[worse] = var0[worse], fine0[worse]
    _warn_disagreement(var, fine, designed, fs)
    reports, failed = [], {}
    for r in outcomes:
        i = r["mode"]
        if r["error"]:
            failed[i] = r["error"]
            empty = (np.empty(0), 0, False, np.nan, False, 0, "")
            bound_error = r.get("bound_error", "")
            reports.append(ModeReport(i, False, r["error"], *empty, bound_start_error=bound_error))
            continue
        margin, method, start = r["margin"], r["certificate"], r["start"]
        robust = r.get("robust_margin", np.nan)
        if worse[i]:
            # Computed by the mode's worker where its design was worse on the input grid
            # (the same call, start_certificate), here otherwise.
            cert = r.get("initial_certificate")
            if cert is None:
                cert = start_certificate(ctx, init_bank.b[i], init_bank.a[i])
            margin, method, start = cert.value, cert.method, REJECTED_WORSE
            if ctx.uncertainty is not None:
                robust = robust_margin(plant, init_bank, ctx.uncertainty, fs=fs, mode=i).value
        reports.append(
            ModeReport(
                i,
                True,
                "",
                r["history"],
                r["solves"],
                r["converged"],
                margin,
                r["stable"],
                r["refinements"],
                start,
                certificate=method,
                pole_radius=_bank_pole_radius(bank, i, r["fixed"]),
                order=int(r.get("order", ctx.free_order + ctx.fixed_factor.size - 1)),
                bound_start_error=r.get("bound_error", ""),
                robust_margin=float(robust),
            )
        )
    no_bound = {r.mode: r.bound_start_error for r in reports if r.bound_start_error}
    if no_bound:
        first = next(iter(no_bound.items()))
        warnings.warn(
            f"bound start not available for {len(no_bound)} mode(s) {list(no_bound)[:10]}: "
            f"{first[1]} (mode {first[0]}); they started from the integrator "
            "(ModeReport.bound_start_error)",
            UserWarning,
            stacklevel=4,
        )
    result = DataDrivenResult(
        bank,
        init_bank,
        tuple(reports),
        var,
        var0,
        ctx.design_freqs,
        residual_variance_fine=fine,
        initial_residual_variance_fine=fine0,
        verification=_verification_text(ctx),
        uncertainty=ctx.uncertainty,
    )
    if failed:
        raise DataDrivenError(failed, result)
    logger.info(
        "data-driven synthesis of %d modes: median %d convex solves per mode",
        n_modes,
        int(np.median(result.solves)),
    )
    return result


def _warn_disagreement(var: np.ndarray, fine: np.ndarray, designed: np.ndarray, fs: float) -> None:
    """Warn when the residual on the input grid and on the fine check disagree by more than
    ``GRID_DISAGREEMENT`` (:class:`GridResolutionWarning`: the grid does not resolve the PSD
    or the loop's ``|S|``, so the design optimised figures that are not the residual)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.maximum(fine / var, var / fine)
    bad = np.flatnonzero(designed & (factor > GRID_DISAGREEMENT))
    if not bad.size:
        return
    i = int(bad[np.argmax(factor[bad])])
    warnings.warn(
        f"the residual on the input grid and on the fine check disagree by more than "
        f"{GRID_DISAGREEMENT:g}x for {bad.size} mode(s) {bad[:10].tolist()} (mode {i}: "
        f"{var[i]:.4g} on the grid, {fine[i]:.4g} on the fine check, PSDs interpolated "
        "linearly): the grid does not resolve the PSD or the loop, and the design optimised "
        "figures that are not the residual; give a denser or log-spaced grid, e.g. "
        f"np.concatenate([[0.0], np.geomspace({fs * 1e-5:.3g}, {fs / 2:g}, 500)])",
        GridResolutionWarning,
        stacklevel=5,
    )


# A design is "worse" than its start beyond this relative tolerance (the solver's accuracy).
_WORSE_TOL = 1e-6


def _bank_pole_radius(bank: IIRBank, i: int, fixed: np.ndarray) -> float:
    """Largest modulus of mode ``i``'s free poles (the fixed factor's divided out if it can)."""
    quot = exact_quotient(bank.a[i], fixed)
    if quot is None:
        quot = np.trim_zeros(bank.a[i], "b")
    return float(np.max(np.abs(np.roots(quot)))) if quot.size > 1 else 0.0


def _verification_text(ctx: DesignContext) -> str:
    exact = ctx.plant_coefficients is not None
    margin = (
        "modulus margin certified exactly over the whole unit circle (stationary points of "
        "|1 + G K| as polynomial roots, and minima on a grid refined around every pole near "
        "the circle)"
        if exact
        else "modulus margin on the measured plant's grid and a dense grid, refined around "
        "the controller's lightly damped poles (plant interpolated between measured points)"
    )
    poles = (
        f"free controller poles inside radius {ctx.max_pole_radius} (roots)"
        if ctx.max_pole_radius is not None
        else "controller poles unconstrained (max_pole_radius=None)"
    )
    robust = (
        ""
        if ctx.uncertainty is None
        else f"; over the uncertainty set {ctx.uncertainty.describe()}: modulus margin and "
        "closed-loop stability certified (aocontrol.analysis.robust_margin)"
    )
    return (
        f"{margin}{robust}; closed-loop stability from the closed-loop poles"
        f"{'' if exact else ' (winding number on the dense grid)'}; {poles}; residual on the "
        "input grid (trapezoid) and on a fine check (20,001 linear + 2,001 log points and "
        "points around every |S| peak, PSDs interpolated linearly)"
    )
