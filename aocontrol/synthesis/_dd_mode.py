"""The per-mode engine of the data-driven synthesis: one mode's design, its orders, a chunk.

:func:`aocontrol.synthesis.datadriven` (``_datadriven``) validates the input and prepares the
shared context (:class:`~aocontrol.synthesis._dd_certify.DesignContext`); this module designs the
modes: each from its best certified start (``_design_mode``), at one order or each order of
``order="auto"`` (``_design_orders``), in chunks of neighbouring modes (``chunks``,
``_design_chunk``) run serially, on a process pool or on a Dask cluster (``_run``; the Dask
side in :mod:`._dd_dask`). A failure in one mode is returned for it, the others kept.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from typing import Any

import numpy as np

from aocontrol._validation import is_programming_error
from aocontrol.plant import frequency_response
from aocontrol.synthesis._ccp import PATIENCE, ccp
from aocontrol.synthesis._dd_certify import _ModeCertifier, _p_of, start_certificate
from aocontrol.synthesis._dd_context import DesignContext
from aocontrol.synthesis._dd_grids import _interp_matrix
from aocontrol.synthesis._dd_starts import bound_candidate, bound_targets, start_certified
from aocontrol.synthesis._socp import GridData, SolveFailure, get_problem, true_objective

logger = logging.getLogger(__name__)
# Modes per work item; within a chunk each mode may start from the previous mode's design.
# The first mode of a chunk starts cold (15 to 30 solves, against 1 to 3 for a warm start):
# measured on 32 contiguous turbulence modes (3 kHz, order 5), 32 instead of 8 cut the CPU by
# 17 % at the same median residual / Wiener bound (1.0089 vs 1.0087).
_CHUNK = 32
# Free grid slots for the constraint-only points added by the dense checks.
_SPARE_SLOTS = 24
# A mode started from the previous mode's design (a neighbour, already converged) stops when
# one iteration lowers the objective by less than ``tol`` (others: PATIENCE iterations).
# Measured on 32 contiguous turbulence modes (3 kHz, order 5): 25 % less CPU, the same median
# residual / Wiener bound (1.016); on the 20 lowest modes 1.139 vs 1.130.
_WARM_PATIENCE = 1
# The default start's pole lies this fraction inside max_pole_radius (strictly inside: the
# convexified radius constraint needs the scaled denominator nonzero on the circle).
_START_LEAK_MARGIN = 1e-3
# Gains of the reduced-bound start candidates (1: the fit itself).
_BOUND_GAINS = (1.0, 0.9, 0.8)


# The dense grid's rows of the last contexts (the same for every mode of a call and order):
# (dense frequencies, their rows), keyed by the arrays' identity (held, so never reused) and
# the structure. Measured: 1.3 ms per mode on 6,177 dense points.
_DENSE_ROWS: OrderedDict = OrderedDict()
_MAX_DENSE = 4


def _dense_data(ctx: DesignContext) -> GridData:
    """The rows of the dense grid at the asked modulus margin (cached)."""
    key = (
        id(ctx.dense_freqs),
        id(ctx.dense_response),
        ctx.free_order,
        ctx.fixed_factor.tobytes(),
        ctx.modulus_margin,
        ctx.fs,
    )
    key += (ctx.hinf_weight, ctx.response_scale)
    hit = _DENSE_ROWS.get(key)
    if hit is not None and hit[0] is ctx.dense_freqs and hit[1] is ctx.dense_response:
        _DENSE_ROWS.move_to_end(key)
        return hit[2]
    data = ctx.grid_data(ctx.dense_freqs, ctx.dense_response, ctx.modulus_margin)
    _DENSE_ROWS[key] = (ctx.dense_freqs, ctx.dense_response, data)
    while len(_DENSE_ROWS) > _MAX_DENSE:
        _DENSE_ROWS.popitem(last=False)
    return data


def _design_mode(
    ctx: DesignContext,
    psd: np.ndarray,
    noise: np.ndarray,
    b0: np.ndarray,
    a0: np.ndarray,
    starts: list | tuple = (),
) -> dict:
    """Design one mode; returns the coefficients and diagnostics (raises on failure).

    ``starts`` are other start candidates, ``(label, (b, a))``: the previous mode's design,
    the reduced margin-constrained bound (:mod:`aocontrol.synthesis._dd_starts`). The best
    one replaces the initial controller as the starting point if it passes every certificate
    (``start_certified``) and has a lower objective for this mode; the iterations never
    raise the objective, so the result is never worse than the best certified start.
    """
    mu_d = ctx.design_margin
    f, g = ctx.design_freqs, ctx.design_response
    H = _interp_matrix(ctx.h2_freqs, ctx.input_freqs)
    pos = np.searchsorted(f, ctx.h2_freqs)
    q1 = np.zeros(f.size)
    qn = np.zeros(f.size)
    q1[pos] = (psd * ctx.input_weights) @ H.T
    qn[pos] = (noise * ctx.input_weights) @ H.T
    Y0, P0 = _p_of(ctx, f, g, b0, a0)
    v_ref = float(np.sum((q1 * np.abs(Y0) ** 2 + qn * np.abs(P0 - Y0) ** 2) / np.abs(P0) ** 2))
    if not v_ref > 1e-12 * np.sum(q1 + qn):
        v_ref = float(np.sum(q1 + qn))
    dense = _dense_data(ctx)
    cert = _ModeCertifier(ctx, psd, noise, v_ref, b0, a0, dense, mu_d)
    k = ctx.rows_per_point  # rows per point: the nominal plant and a robust design's variants
    r1, rn, h = cert.weights(f)
    grid = cert.rows(f)
    n_wind = ctx.winding_index.size * k
    n_wind += cert.n_pole_rows if ctx.max_pole_radius is not None else 0
    # Up to _SPARE_SLOTS points added by the checks; each solve at the grid's size.
    problem = get_problem(
        (f.size + _SPARE_SLOTS) * k, 2 * ctx.free_order + 1, ctx.hinf_weight > 0, n_wind, k
    )
    v0 = ctx.to_v(b0, a0)
    P_rows = cert.p_start(f)  # the start's P on the grid's rows (every plant's)
    start = "initial"
    J_best = true_objective(grid, v0, r1, rn, h)[0] if v0 is not None else np.inf
    leak = 1.0 - ctx.max_pole_radius * (1.0 - _START_LEAK_MARGIN) if ctx.max_pole_radius else 0.0
    for label, (bc, ac) in starts:
        # The previous mode's design enters a free structure with the default start's leak
        # in place of its integrator (_warm_v); the other candidates as they are.
        vc = ctx.warm_v(bc, ac, leak) if label == "previous mode" else ctx.to_v(bc, ac)
        if vc is None:
            continue
        Jc, Pc_grid = true_objective(grid, vc, r1, rn, h)
        # 0/0 where a candidate's P and Y both vanish on the grid gives nan: "not met" below
        # (nan >= need is False), so such a start is skipped, silently.
        with np.errstate(divide="ignore", invalid="ignore"):
            met = float(np.min(np.abs(Pc_grid) / np.abs(grid.AY @ vc + grid.F)))
        # The previous mode's design meets the design grid's margin mu_d (to the solver's
        # accuracy); a reduced bound, fitted, may meet only the certified mu there: the design
        # grid's margin is then lowered to what it meets (at least mu, which the final
        # certificate enforces exactly), so that the start is feasible for the convex steps.
        need = ctx.modulus_margin if label == "bound reduction" else mu_d
        if Jc < J_best and met >= need * (1 - 1e-4) and start_certified(ctx, cert, dense, vc):
            (b0, a0), v0, P_rows, start, J_best = ctx.from_v(vc), vc, Pc_grid, label, Jc
            Y0, P0 = _p_of(ctx, f, g, b0, a0)
            cert.b0, cert.a0 = b0, a0
            cert.mu_d = max(ctx.modulus_margin, min(mu_d, met * (1 - 1e-4)))
    # The objective of the start (nominal rows: the variants' carry no H2 weight).
    r1n, rnn, hn = r1[::k], rn[::k], h[::k]
    J_start = float(
        np.sum(hn * (r1n**2 * np.abs(Y0) ** 2 + rnn**2 * np.abs(P0 - Y0) ** 2) / np.abs(P0) ** 2)
    )
    if start == "initial" and ctx.hinf_weight > 0:
        J_start += ctx.hinf_weight * float(np.max(np.abs(P0 - Y0) ** 2 / np.abs(P0) ** 2))
    out = ccp(
        problem,
        f,
        cert,
        v0,
        P_rows,
        cert.p_start,
        max_iter=ctx.max_iter,
        tol=ctx.tol,
        extrapolate=ctx.extrapolate,
        J_start=J_start,
        patience=_WARM_PATIENCE if start == "previous mode" else PATIENCE,
    )
    # Final verification by the certificates (margin over the whole circle, closed-loop
    # stability, pole radius). The checks in the iterations make a failure unlikely; if it
    # happens, the newest accepted iterate that passes is returned, and the start otherwise.
    for v in reversed(out.iterates):
        if v is None:
            continue
        chk = cert.check_final(v)
        if chk is not None:
            margin, method = chk
            if v is not out.iterates[-1]:
                logger.warning(
                    "final iterate failed its certificate; an earlier certified iterate is returned"
                )
            break
    else:
        raise RuntimeError("no iterate passed the certificates (margin, stability, pole radius)")
    b, a = ctx.from_v(v)
    poles = ctx.free_poles(v)
    cert_v = cert.margin(v)
    rm = cert.robust(v)
    return {
        "robust_margin": np.nan if rm is None else rm.value,
        "peaks_hz": cert_v.minima_hz,
        "b": b,
        "a": a,
        "history": out.history,
        "solves": out.solves,
        "converged": out.converged,
        "margin": margin,
        "certificate": method,
        "stable": True,
        "refinements": out.added,
        "start": start,
        "pole_radius": float(np.max(np.abs(poles))) if poles.size else 0.0,
    }


def _mode_residual(ctx: DesignContext, g: np.ndarray, psd, noise, b, a) -> float:
    """Residual variance of ``K = b/a`` on the input grid (trapezoid), plant response ``g``."""
    Y, P = _p_of(ctx, ctx.input_freqs, g, b, a)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (np.abs(Y) ** 2 * psd + np.abs(P - Y) ** 2 * noise) / np.abs(P) ** 2
    return float(np.sum(r * ctx.input_weights))


def _design_orders(
    ctx: DesignContext, g: np.ndarray, psd, noise, b0, a0, warm, target=None
) -> dict:
    """Design one mode at one order, or at each order of ``ctx.auto_orders`` (``order="auto"``).

    With several orders each design starts from the previous order's (a lower-order
    controller lies in the higher order's parameter set), and the lowest order whose residual
    on the input grid is within ``auto_tol`` of the best one is kept. The sequence stops early
    once two consecutive orders gain less than ``auto_tol / 2`` each. Orders below the
    initial controller's own are skipped (it is not in their parameter set). ``warm`` (the
    previous mode's design) is a start candidate of the first order; ``target`` (the bound's
    sensitivity on the input grid, or None) gives a reduced-bound start candidate at each
    order (:func:`aocontrol.synthesis._dd_starts.bound_candidate`).
    """

    def starts(ctx_k: DesignContext, first: bool) -> list:
        out = [("previous mode", warm)] if first and warm is not None else []
        cand = bound_candidate(ctx_k, g, psd, noise, target)
        if cand is None:
            return out
        # The fit may miss the margin where the bound meets it with equality: the same
        # controller with a lower gain (towards open loop) is tried too.
        return out + [("bound reduction", (c * cand[0], cand[1])) for c in _BOUND_GAINS]

    if not ctx.auto_orders:
        return _design_mode(ctx, psd, noise, b0, a0, starts(ctx, True))
    tried, gains = [], []
    start = (b0, a0)
    start_order = max(np.trim_zeros(b0, "b").size - 1, np.trim_zeros(a0, "b").size - 1)
    orders = [o for o in ctx.auto_orders if o >= start_order] or [ctx.auto_orders[-1]]
    for order in orders:
        ctx_k = ctx.with_structure(ctx.fixed_factor, order)
        res = _design_mode(ctx_k, psd, noise, *start, starts(ctx_k, not tried))
        res["order"] = order
        res["residual"] = _mode_residual(ctx, g, psd, noise, res["b"], res["a"])
        if tried:
            gains.append(1.0 - res["residual"] / max(tried[-1]["residual"], 1e-300))
        tried.append(res)
        start = (res["b"], res["a"])
        if len(gains) >= 2 and max(gains[-2:]) < ctx.auto_tol / 2:
            break
    best = min(r["residual"] for r in tried)
    chosen = next(r for r in tried if r["residual"] <= best * (1 + ctx.auto_tol))
    chosen["solves"] = sum(r["solves"] for r in tried)
    chosen["orders_tried"] = tuple(r["order"] for r in tried)
    return chosen


def _design_chunk(ctx: DesignContext, items: list) -> list:
    """Design a chunk of modes in one worker; failures are returned, not raised.

    BLAS runs on one thread here (as in joblib's workers): the products are of a few thousand
    rows by ~11 columns, where a second thread only waits (``docs/benchmarks.md``).
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _design_items(ctx, items)


def _design_items(ctx: DesignContext, items: list) -> list:
    """The body of :func:`_design_chunk`."""
    out = []
    warm = None
    g = frequency_response(ctx.plant, ctx.input_freqs, ctx.fs)
    targets, why = bound_targets(ctx, items, ctx.design_margin)
    for (mode, psd, noise, b0, a0, fixed, _), target, bound_error in zip(
        items, targets, why, strict=True
    ):  # ModeItem fields
        try:
            ctx_m = ctx
            if not np.array_equal(fixed, ctx.fixed_factor):
                order = ctx.free_order + ctx.fixed_factor.size - 1
                ctx_m = ctx.with_structure(fixed, order)
            res = _design_orders(ctx_m, g, psd, noise, b0, a0, warm, target)
            if _mode_residual(ctx, g, psd, noise, res["b"], res["a"]) > _mode_residual(
                ctx, g, psd, noise, b0, a0
            ):
                # The assembly will most likely keep the start (worse on the input grid) and
                # report its certificate: computed here, on the workers, by the very call the
                # assembly makes (it computes those it is not given, and any that fails here).
                try:
                    res["initial_certificate"] = start_certificate(ctx, b0, a0)
                except Exception as exc:
                    if is_programming_error(exc):
                        raise
            res["fixed"] = fixed
            res["mode"], res["error"] = mode, ""
            res["bound_error"] = bound_error
            warm = (res["b"], res["a"])
        except Exception as exc:
            # A numerical failure of this mode (solver, linear algebra, floating point, a
            # ValueError from numerics...) is reported for it and the others are kept; a
            # programming error (TypeError, AttributeError, ...) is a bug and propagates.
            if is_programming_error(exc):
                raise
            msg = str(exc) if isinstance(exc, (SolveFailure, RuntimeError)) else ""
            msg = msg or f"{type(exc).__name__}: {exc}"
            if isinstance(exc, SolveFailure) and "infeasible" in exc.status.lower():
                msg += (
                    " (no controller of this structure meets the modulus margin around "
                    "the initial controller; lower modulus_margin or give another initial)"
                )
            logger.debug("mode %d failed", mode, exc_info=True)
            res = {"mode": mode, "error": msg, "bound_error": bound_error}
        out.append(res)
    return out


class _Bar:
    """No progress bar: the two methods of a tqdm bar that :func:`_run` calls."""

    def update(self, n: int) -> None:  # noqa: D102 - a bar's method
        pass

    def close(self) -> None:  # noqa: D102 - a bar's method
        pass


def chunks(items: list) -> list:
    """The fixed chunks of :data:`_CHUNK` neighbouring modes every path designs (serial, joblib,
    Dask): within a chunk a mode may start from the previous mode's design, so the chunks,
    not the workers, decide each mode's start and the bank does not depend on the path."""
    return [items[i : i + _CHUNK] for i in range(0, len(items), _CHUNK)]


#: Extra cost of a mode's bound start in units of a mode's other work: the order in which
#: the chunks are handed to the workers only (the bank does not depend on it). Measured on
#: 60 of bench_design_speed (a)'s 540 telemetry modes (5 Dec, one process): 65 ms of bound
#: start per mode that has one (24 of 60), about 70 ms of other work per mode.
_BOUND_START_COST = 0.9


def _longest_first(parts: list) -> list:
    """``parts`` by expected cost, the costliest first (the first mode's cold start, the
    others warm, and the bound starts)."""
    cost = [len(p) + _BOUND_START_COST * sum(bool(i.bound_start) for i in p) for p in parts]
    return [parts[k] for k in np.argsort(cost, kind="stable")[::-1]]


def local_workers(n_jobs: int | None) -> int:
    """Workers of ``n_jobs`` on this machine (None: every core; negative: joblib's convention)."""
    from joblib import cpu_count

    cores = cpu_count()  # affinity, cgroups and LOKY_MAX_CPU_COUNT (a sweep worker's share)
    n_workers = cores if n_jobs is None else n_jobs
    return max(1, cores + 1 + n_workers) if n_workers < 0 else n_workers


def _run(
    ctx: DesignContext, items: list, n_jobs: int | None, progress: bool, client: Any = None
) -> list:
    """Design every mode: on ``client`` (Dask, :mod:`._dd_dask`) if given, else in this
    process or on a joblib process pool when it pays."""
    n_workers = min(local_workers(n_jobs), len(items))
    bar = _Bar()
    if progress:  # tqdm.auto imported only for a bar asked for (in Jupyter without ipywidgets
        # its import warns, a warning a call without a bar should not print)
        from tqdm.auto import tqdm

        bar = tqdm(total=len(items), desc="data-driven synthesis", unit="mode")
    results = []
    try:
        parts = chunks(items)
        if client is not None:
            from aocontrol.synthesis._dd_dask import run_on_client

            results = run_on_client(client, _design_chunk, ctx, parts, bar)
        elif n_workers <= 1:
            for chunk in parts:
                results.extend(_design_chunk(ctx, chunk))
                bar.update(len(chunk))
        else:
            from joblib import Parallel, delayed

            # Longest first (the chunks and so the bank are unchanged, the results sorted
            # by mode below): the last chunk to finish is a short one, less idle time
            gen = Parallel(n_jobs=n_workers, return_as="generator_unordered")(
                delayed(_design_chunk)(ctx, chunk) for chunk in _longest_first(parts)
            )
            for part in gen:
                results.extend(part)
                bar.update(len(part))
    finally:
        bar.close()
    return sorted(results, key=lambda r: r["mode"])
