"""The convex-concave iterations of one mode: the convexified problem re-solved until the
objective stops decreasing, every candidate certified.

Private module of :mod:`aocontrol.synthesis._datadriven`. Each step solves the convexified
second-order cone program of :mod:`aocontrol.synthesis._socp` around the previous controller,
which is always feasible, so the objective never increases. The design supplies the
certificates and the grid rows through a :class:`Certifier`; a failed margin or stability adds
cutting planes to the grid, a pole outside the radius damps the step, and flat valleys are
crossed by extrapolated steps (:func:`ccp`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from aocontrol.synthesis._socp import (
    ConvexifiedProblem,
    GridData,
    SizedProblem,
    SolveFailure,
    _g_scale,
    true_objective,
)

__all__ = ["CcpOutcome", "Certifier", "Check", "PATIENCE", "ccp"]

logger = logging.getLogger(__name__)


@dataclass
class CcpOutcome:
    """Result of the convex-concave iterations of one mode."""

    v: np.ndarray
    history: np.ndarray
    iterates: list
    converged: bool
    solves: int
    added: int
    damped: int


@dataclass(frozen=True)
class Check:
    """Verdict of the certificates on one candidate controller.

    Attributes
    ----------
    ok : bool
        Every certificate passed.
    cut : numpy.ndarray
        Frequencies [Hz] to add to the design grid (cutting planes: the certified minima of
        ``|1 + G K|`` below the margin, the points where ``P`` turned most for a lost
        stability, or ``|S|`` peaks the design grid misrepresents).
    reason : str
        What failed (``""`` when ``ok``): ``"margin"``, ``"stability"``, ``"poles"`` (a
        controller pole outside the radius; no cut, the step is damped) or ``"peaks"``.
    """

    ok: bool
    cut: np.ndarray
    reason: str = ""


class Certifier:
    """What :func:`ccp` needs from the design (implemented by the data-driven synthesis).

    ``rows(f)`` gives ``rows_per_point`` rows per frequency, point after point (a robust
    design constrains several plants at each frequency); ``weights(f)`` and the start's
    ``P`` follow the same order.
    """

    #: Grid rows per frequency point.
    rows_per_point = 1

    def check(self, v: np.ndarray) -> Check:  # pragma: no cover - interface
        raise NotImplementedError

    def rows(self, f: np.ndarray) -> GridData:  # pragma: no cover - interface
        raise NotImplementedError

    def weights(self, f: np.ndarray) -> tuple:  # pragma: no cover - interface
        raise NotImplementedError

    def winding(self, v: np.ndarray | None) -> list:  # pragma: no cover - interface
        raise NotImplementedError

    def seeds(self, v: np.ndarray) -> np.ndarray:
        """Frequencies [Hz] to add to the grid before the first step (none by default)."""
        return np.empty(0)


# Extrapolation steps tried beyond each convex step (multiples of the step, doubling).
_EXTRAPOLATION = 2.0 ** np.arange(1, 11) - 1.0
# Damped steps tried when a full step leaves the pole radius or loses closed-loop stability
# through a near pole-zero cancellation that the margin does not see (fractions of the step).
_DAMPING = 0.5 ** np.arange(1, 9)
_DAMPED = ("poles", "stability")
#: Number of iterations over which the relative decrease is compared with ``tol`` (default).
PATIENCE = 3
# Points added to the grid per failed check.
_ADD_PER_CHECK = 4


def _last_damped(
    cert: Certifier,
    grid: GridData,
    v: np.ndarray,
    v_best: np.ndarray,
    w_grid: tuple,
    J_best: float,
) -> np.ndarray | None:
    """The longest damped step ``v_best + t (v - v_best)`` (``t`` in ``_DAMPING``) that
    lowers the objective on ``grid``, meets its margin rows and passes every certificate."""
    for t in _DAMPING:
        vt = v_best + t * (v - v_best)
        Jt, Pt = true_objective(grid, vt, *w_grid)
        if not Jt < J_best * (1 - 1e-9):
            continue
        if np.any(grid.mu_rows() * np.abs(grid.AY @ vt + grid.F) > np.abs(Pt)):
            continue
        if cert.check(vt, v_best).ok:
            return vt
    return None


def ccp(
    problem: SizedProblem | ConvexifiedProblem,
    grid_f: np.ndarray,
    cert: Certifier,
    v0: np.ndarray | None,
    P0: np.ndarray,
    p_start: Callable[[np.ndarray], np.ndarray],
    *,
    max_iter: int,
    tol: float,
    extrapolate: bool = True,
    J_start: float = np.inf,
    patience: int = PATIENCE,
) -> CcpOutcome:
    """Iterate the convexified problem from ``P0`` until the objective stops decreasing.

    Each convex solve gives ``v_new`` whose convexified objective (an upper bound of the true
    one, equal at the previous controller, which is feasible) is no higher than the previous
    objective. Every candidate goes through the certificates (``cert.check``): the modulus
    margin over the whole circle, closed-loop stability, the controller pole radius, and the
    ``|S|`` peaks that fall between design points. A failed margin or stability adds the
    failing frequencies to the design grid (cutting planes) and the step is solved again; a
    pole outside the radius damps the step (``v_old + t (v_new - v_old)``, ``t = 1/2, 1/4,
    ...``: the convexified objective and constraints hold along the segment). Long, flat
    valleys are crossed by trying ``v_new + t (v_new - v_old)`` for ``t = 1, 3, 7, ...`` while
    it passes the same checks and lowers the objective. When the last solve allowed
    (``max_iter``) gives a step refused for a margin or peak cut, the cut points join the
    grid and the step is damped instead of lost (the longest of ``t = 1/2, 1/4, ...`` that
    lowers the objective on the refined grid and passes every certificate), so a one-solve
    warm redesign still improves its mode (``docs/benchmarks.md``). The objective history is
    non-increasing on a fixed grid; when the grid grows, the current objective is re-evaluated
    on it first.

    Parameters
    ----------
    problem : SizedProblem or ConvexifiedProblem
        Problem with enough slots and winding rows.
    grid_f : ndarray, shape (N,)
        Design-grid frequencies [Hz].
    cert : Certifier
        Certificates, grid rows, objective weights and winding blocks of this mode.
    v0 : ndarray or None
        Coefficients of the initial controller if it lies in the parameter set.
    P0 : ndarray of complex, shape (N,)
        ``Y0 + G X0`` of the initial controller on the grid.
    p_start : callable
        ``p_start(f)``: ``Y0 + G X0`` of the initial controller at frequencies ``f`` [Hz].
    max_iter : int
        Maximum number of convex solves.
    tol : float
        Stop when the last ``PATIENCE`` iterations lowered the objective by less than
        ``tol`` (relative) in total.
    extrapolate : bool, default True
        Try extrapolated steps (False: the plain convex-concave iteration).
    J_start : float, optional
        Objective of an initial controller outside the parameter set (``v0`` None), for the
        history only: the first iterate is then accepted whatever its value.
    patience : int, default PATIENCE
        Number of iterations over which the decrease is compared with ``tol``.

    Returns
    -------
    CcpOutcome
        Best coefficients, objective history (initial first) and the accepted iterates.
    """
    grid_f = np.asarray(grid_f, dtype=float)
    grid = cert.rows(grid_f)
    w_grid = cert.weights(grid_f)
    J0 = true_objective(grid, v0, *w_grid)[0] if v0 is not None else J_start
    history, iterates = [J0], [v0]
    v_best, J_best, Pc = v0, J0, P0
    converged, solves, added, damped = False, 0, 0, 0

    def p_prev(f: np.ndarray, rows: GridData) -> np.ndarray:
        return rows.A @ v_best + rows.F if v_best is not None else p_start(f)

    def join(new: np.ndarray) -> None:
        """Add the points ``new`` [Hz] to the design grid (margin rows; H2 if the certifier
        says so), the previous controller kept feasible, the objective re-evaluated."""
        nonlocal grid_f, grid, Pc, added, w_grid, J_best
        rows = cert.rows(new)
        Pb = p_prev(new, rows)
        if v_best is not None:
            # The previous controller stays feasible: a cut point's margin is at most
            # what it meets there (it passed the certificate, so at least mu).
            Yb = rows.AY @ v_best + rows.F
            with np.errstate(divide="ignore", invalid="ignore"):
                met = np.where(np.abs(Yb) > 0, np.abs(Pb) / np.abs(Yb), np.inf)
            rows = GridData(
                rows.AY,
                rows.AX,
                rows.F,
                np.minimum(rows.mu_rows(), met * (1 - 1e-9)),
                rows.hinf_weight,
            )
        grid_f = np.concatenate([grid_f, new])
        grid = grid.join(rows)
        Pc = np.concatenate([Pc, Pb])
        added += new.size
        w_grid = cert.weights(grid_f)
        problem.set_grid(grid, *w_grid)
        if v_best is not None:
            # The objective on the refined grid (the H2 weights may have moved).
            J_best = true_objective(grid, v_best, *w_grid)[0]

    if v0 is not None:
        # Seed the grid with the start's |S| peaks (the local minima of |1 + G K| where
        # |S| > 1): the steps tend to deepen them between design points, which the
        # certificates would otherwise add one cut (one solve) at a time.
        seeds = cert.seeds(v0)
        free_points = max(problem.slots - grid.F.size, 0) // cert.rows_per_point
        seeds = seeds[~np.isin(seeds, grid_f)][: free_points // 2]
        if seeds.size:
            join(seeds)
            history[0] = J_best
    problem.set_grid(grid, *w_grid)
    problem.set_winding(cert.winding(v0))
    it = 0
    while it < max_iter:
        it += 1
        free = v_best is None
        try:
            v = problem.solve(Pc, _g_scale(grid, Pc, v_best, *w_grid[:2]), it)
        except SolveFailure as exc:
            if free or "infeasible" in exc.status:
                raise
            logger.debug(
                "solver failed at iteration %d (%s); keeping the last iterate", it, exc.status
            )
            converged = True
            break
        solves += 1
        chk = cert.check(v, v_best)
        if not chk.ok and chk.reason in _DAMPED and not free:
            # Damp the step: the segment from the previous controller stays feasible for the
            # convexified problem, and short enough steps keep the poles inside the radius
            # and the closed loop stable (its poles move continuously from stable ones).
            for t in _DAMPING:
                vt = v_best + t * (v - v_best)
                ct = cert.check(vt, v_best)
                if ct.ok or ct.reason not in _DAMPED:
                    v, chk = vt, ct
                    damped += 1
                    break
            else:
                logger.debug("no damped step passes the %s check; stopping", chk.reason)
                converged = True
                break
        if not chk.ok:
            new = chk.cut[~np.isin(chk.cut, grid_f)][:_ADD_PER_CHECK]
            room = (problem.slots - grid.F.size) // cert.rows_per_point
            if new.size == 0 or room <= 0:
                logger.debug("check failed (%s) and no grid slot or point left", chk.reason)
                if free:
                    raise SolveFailure(f"without an iterate that passes the {chk.reason} check", it)
                converged = True
                break
            new = new[:room]
            logger.debug(
                "%s check failed at iteration %d: %s Hz join the grid", chk.reason, it, new
            )
            join(new)
            if free or it < max_iter:
                continue
            # No solve left: the step damped towards the certified previous iterate (the
            # convexified objective decreases along it), on the grid with the new points.
            vt = _last_damped(cert, grid, v, v_best, w_grid, J_best)
            if vt is None:
                continue
            v, chk = vt, Check(True, np.empty(0))
            damped += 1
        J, P = true_objective(grid, v, *w_grid)
        if not np.isfinite(J):
            if free:
                raise SolveFailure("non-finite objective (Y + G X vanishes)", it)
            converged = True
            break
        if not free and J > J_best * (1 + 1e-9) + 1e-12:
            # The convex step is a descent direction of the convexified model, tangent to the
            # true objective at the previous controller; where the solver's feasibility
            # tolerance spoils the full step (rows near a dip of |P| after a cut), a shorter
            # one may still descend (measured: low-order turbulence modes keep descending by
            # 0.1-0.5 % per step this way, 1.14 -> 1.89 of the Wiener bound without it);
            # otherwise the iteration has stalled at the solver's accuracy.
            for t in _DAMPING:
                vt = v_best + t * (v - v_best)
                Jt, Pt = true_objective(grid, vt, *w_grid)
                if Jt < J_best * (1 - 1e-9) and cert.check(vt, v_best).ok:
                    v, J, P = vt, Jt, Pt
                    damped += 1
                    break
            else:
                logger.debug(
                    "objective rose from %.8g to %.8g at iteration %d; stopping", J_best, J, it
                )
                converged = True
                break
        if extrapolate and not free:
            step = v - v_best
            for t in _EXTRAPOLATION:
                ve = v + t * step
                Je, Pe = true_objective(grid, ve, *w_grid)
                # Same constraints as the convex steps: the grid's margin (the next problem
                # then starts from a feasible point) and the certificates.
                if (
                    not Je < J
                    or np.any(grid.mu_rows() * np.abs(grid.AY @ ve + grid.F) > np.abs(Pe))
                    or not cert.check(ve, v_best).ok
                ):
                    break
                v, J, P = ve, Je, Pe
        history.append(J)
        iterates.append(v)
        v_best, J_best, Pc = v, J, P
        if not free and len(history) > patience:
            past = history[-1 - patience]
            if past - J <= tol * abs(past):
                converged = True
                break
        if it < max_iter:  # the next solve's winding rows (none after the last one)
            problem.set_winding(cert.winding(v))
    if v_best is None:
        raise SolveFailure("without an iterate that passes the certificates", it)
    return CcpOutcome(
        np.asarray(v_best), np.asarray(history), iterates, converged, solves, added, damped
    )
