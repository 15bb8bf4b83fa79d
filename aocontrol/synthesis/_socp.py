"""The convexified data-driven problem of one mode: a DPP second-order cone program.

Private module of :mod:`aocontrol.synthesis._datadriven`. Notation (powers of ``w = z^-1``)::

    K = X / Y,   X = sum_{i=0}^{q} x_i w^i,   Y = F (1 + sum_{i=1}^{q} y_i w^i),
    P = Y + G X,  S = Y / P,  T = G X / P.

The decision vector is ``v = [x_0 .. x_q, y_1 .. y_q]``; on a grid of frequencies
``Y = AY v + F`` and ``G X = AX v`` with complex matrices, ``P = A v + F``.

Around the previous controller ``Pc`` every frequency constraint ``|a|^2 <= b |P|^2`` is
replaced by the convex inner approximation ``|a|^2 <= b phi`` with the affine lower bound
``phi = 2 Re(P conj Pc) - |Pc|^2 = M v + c <= |P|^2``: a rotated second-order cone,
``|a|^2 <= b phi  <=>  ||[2a, b - phi]|| <= b + phi``. Per frequency j:

* H2:      ``r1_j^2 |Y_j|^2 + rn_j^2 |G_j X_j|^2 <= g_j phi_j``  (objective ``sum_j h_j g_j``)
* H-inf:   ``sw^2 |G_j X_j|^2 <= gamma phi_j``                  (objective ``+ gamma``)
* margin:  ``mu^2 |Y_j|^2 <= phi_j``                            (``|S_j| <= 1/mu``)

``g_j`` is a convex combination of ``|S_j|^2`` and ``|T_j|^2`` (``r1^2 + rn^2 = 1``); it is
solved as ``g_j = s_j u_j`` with ``s_j`` its value at the previous controller, so that ``u`` is
of order one whatever the dynamic range of the PSD and of ``|S|``: the data only enter the
objective weights ``h_j s_j``, which keeps Clarabel well conditioned.

Every row of every cone is affine in ``v`` with cvxpy ``Parameter`` coefficients (DPP): one
problem per worker and size is compiled once and re-solved for every mode, grid and
iteration. Grid slots beyond the active points are neutral (zero rows, ``phi = 1``), which
leaves room for the points added by the dense checks. Linear constraints on a finer grid,
``Re(P conj Pc) / |Pc| >= max(0.05 |Pc|, min(0.01, |Pc|))``, keep the winding number of ``P``
(closed-loop stability) between grid points and ``|P|`` away from 0.
"""

from __future__ import annotations

import logging
import warnings
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

__all__ = ["GridData", "ConvexifiedProblem", "SolveFailure", "ccp", "true_objective", "get_problem"]

logger = logging.getLogger(__name__)

# Clarabel settings. Moderate tolerances (each step only needs to lower the objective) and
# inaccurate solutions accepted (accept_unknown): every iterate is checked on the true,
# non-convexified objective and constraints before it is used. No equilibration: the problem
# is scaled by construction (Y monic, G normalised, g = s u), and it halves the IPM iterations.
# Gap 1e-4: each convex step is only a surrogate of the true problem; measured on 6 modes it
# saves ~35 % of the solver time and moves the final objectives by < 0.5 % either way.
_SOLVER_OPTS = {
    "tol_gap_abs": 1e-5,
    "tol_gap_rel": 1e-4,
    "tol_feas": 1e-7,
    "max_iter": 100,
    "presolve_enable": False,
    "accept_unknown": True,
    "equilibrate_enable": False,
}
# Winding constraints: Re(P conj Pc) >= _WIND_MIN |Pc|^2 keeps the phase of P within ~87 deg
# of the previous controller's at every point of the winding grid.
_WIND_MIN = 0.05
# ... and |P| >= min(_P_FLOOR, |Pc|): X and Y cannot grow a common factor whose root reaches the
# circle (K unchanged, but a hidden closed-loop mode on the circle). Y is monic: |P| ~ 1.
_P_FLOOR = 1e-2
# Worker-local cache of compiled problems, keyed by (slots, nv, stroke term).
_PROBLEMS: OrderedDict[tuple, ConvexifiedProblem] = OrderedDict()
_MAX_CACHED = 6


class SolveFailure(RuntimeError):
    """The convexified problem has no solution (``status`` says why)."""

    def __init__(self, status: str, iteration: int) -> None:
        super().__init__(f"convexified problem {status} at iteration {iteration}")
        self.status = status
        self.iteration = iteration


@dataclass(frozen=True)
class GridData:
    """Data of the convexified problem on a set of frequencies.

    Attributes
    ----------
    AY, AX : ndarray of complex, shape (N, nv)
        ``Y = AY v + F`` and ``G X = AX v`` on the grid.
    F : ndarray of complex, shape (N,)
        Fixed denominator factor on the grid (ones when there is none).
    mu : float
        Modulus margin enforced on the grid.
    stroke_weight : float
        Weight of ``||T||_inf^2`` (0 drops the term).
    """

    AY: np.ndarray
    AX: np.ndarray
    F: np.ndarray
    mu: float
    stroke_weight: float

    @property
    def A(self) -> np.ndarray:
        return self.AY + self.AX

    def take(self, idx: np.ndarray) -> GridData:
        """The rows ``idx`` as a new grid."""
        return GridData(self.AY[idx], self.AX[idx], self.F[idx], self.mu, self.stroke_weight)

    def join(self, other: GridData) -> GridData:
        """This grid followed by the rows of ``other``."""
        return GridData(
            np.vstack([self.AY, other.AY]),
            np.vstack([self.AX, other.AX]),
            np.concatenate([self.F, other.F]),
            self.mu,
            self.stroke_weight,
        )


class ConvexifiedProblem:
    """DPP cvxpy problem with ``slots`` frequency slots and ``nv`` unknowns.

    Parameters
    ----------
    slots : int
        Maximum number of grid points.
    nv : int
        Number of controller coefficients.
    stroke : bool
        Include the ``||T||_inf^2`` term.
    """

    def __init__(self, slots: int, nv: int, stroke: bool, n_wind: int = 0) -> None:
        self.slots, self.nv, self.stroke, self.n_wind = slots, nv, stroke, n_wind
        nx = self.nx = (nv + 1) // 2
        ny = nv - nx
        v = self.v = cp.Variable(nv, name="v")
        vx = v[:nx]
        u = cp.Variable(slots, name="u")
        # Y only depends on the y part of v and G X on the x part: separate parameter blocks
        # keep the cone matrices (and Clarabel's KKT system) as sparse as the structure.
        shapes = {"h_yr": ny, "h_yi": ny, "m_yr": ny, "m_yi": ny, "h_xr": nx, "h_xi": nx}
        if stroke:
            shapes.update({"s_xr": nx, "s_xi": nx})
        P = self._params = {
            name: cp.Parameter((slots, n), name=name) for name, n in shapes.items() if n > 0
        }
        P["M"] = cp.Parameter((slots, nv), name="M")
        off = self._offsets = {
            name: cp.Parameter(slots, name=name) for name in ("o_yr", "o_yi", "o_mr", "o_mi", "c")
        }
        self.s = cp.Parameter(slots, nonneg=True, name="s")
        self.h = cp.Parameter(slots, nonneg=True, name="h")

        def y_row(name: str, offset: str) -> cp.Expression:
            if ny == 0:
                return off[offset] + 0 * vx[0]
            return P[name] @ v[nx:] + off[offset]

        phi = P["M"] @ v + off["c"]
        g = cp.multiply(self.s, u)
        cons = [
            cp.SOC(
                g + phi,
                cp.vstack(
                    [
                        y_row("h_yr", "o_yr"),
                        y_row("h_yi", "o_yi"),
                        P["h_xr"] @ vx,
                        P["h_xi"] @ vx,
                        g - phi,
                    ]
                ),
                axis=0,
            ),
            cp.SOC(
                1 + phi, cp.vstack([y_row("m_yr", "o_mr"), y_row("m_yi", "o_mi"), 1 - phi]), axis=0
            ),
        ]
        objective = self.h @ u
        if stroke:
            gamma = cp.Variable(name="gamma")
            cons.append(
                cp.SOC(
                    gamma + phi, cp.vstack([P["s_xr"] @ vx, P["s_xi"] @ vx, gamma - phi]), axis=0
                )
            )
            objective = objective + gamma
        if n_wind:
            # Same winding number on a fine grid, |P| bounded below (linear, see set_winding).
            self.wind_A = cp.Parameter((n_wind, nv), name="wind_A")
            self.wind_b = cp.Parameter(n_wind, name="wind_b")
            cons.append(self.wind_A @ v + self.wind_b >= 0)
        self.problem = cp.Problem(cp.Minimize(objective), cons)
        if not self.problem.is_dpp():  # pragma: no cover - construction bug
            raise AssertionError("convexified problem is not DPP")

    def set_grid(self, data: GridData, r1: np.ndarray, rn: np.ndarray, h: np.ndarray) -> None:
        """Set the grid (``N <= slots`` points) and the H2 weights of one mode."""
        n = data.F.size
        if n > self.slots:
            raise ValueError(f"grid of {n} points exceeds the {self.slots} slots")
        self.data, self.n = data, n
        self.weights = (np.asarray(r1, float), np.asarray(rn, float), np.asarray(h, float))
        nx = self.nx

        def full(x: np.ndarray) -> np.ndarray:
            out = np.zeros((self.slots,) + x.shape[1:])
            out[:n] = x
            return out

        r1, rn = 2 * self.weights[0][:, None], 2 * self.weights[1][:, None]
        AY, AX = data.AY[:, nx:], data.AX[:, :nx]
        values = {
            "h_yr": r1 * AY.real,
            "h_yi": r1 * AY.imag,
            "h_xr": rn * AX.real,
            "h_xi": rn * AX.imag,
            "m_yr": 2 * data.mu * AY.real,
            "m_yi": 2 * data.mu * AY.imag,
        }
        if self.stroke:
            sw = 2 * np.sqrt(data.stroke_weight)
            values.update({"s_xr": sw * AX.real, "s_xi": sw * AX.imag})
        for name, value in values.items():
            if name in self._params:
                self._params[name].value = full(value)
        off = self._offsets
        off["o_yr"].value = full(r1[:, 0] * data.F.real)
        off["o_yi"].value = full(r1[:, 0] * data.F.imag)
        off["o_mr"].value = full(2 * data.mu * data.F.real)
        off["o_mi"].value = full(2 * data.mu * data.F.imag)

    def set_winding(self, wind: GridData, Pw: np.ndarray) -> None:
        """Winding constraints around ``Pw`` (previous ``P`` on the grid ``wind``).

        ``Re(P conj Pw) / |Pw| >= max(_WIND_MIN |Pw|, min(_P_FLOOR, |Pw|))``: the phase of
        ``P`` stays within ~87 deg of ``Pw`` (same winding number, so the step keeps the
        closed loop stable) and, as ``Re(P conj Pw) / |Pw| <= |P|``, ``|P|`` stays above a floor.
        The previous controller (``P = Pw``) satisfies both.
        """
        scale = 1.0 / np.abs(Pw)  # row scaling: each row has unit size
        self.wind_A.value = (
            Pw.real[:, None] * wind.A.real + Pw.imag[:, None] * wind.A.imag
        ) * scale[:, None]
        floor = np.maximum(_WIND_MIN * np.abs(Pw), np.minimum(_P_FLOOR, np.abs(Pw)))
        self.wind_b.value = (Pw.real * wind.F.real + Pw.imag * wind.F.imag) * scale - floor

    def solve(self, Pc: np.ndarray, scale: np.ndarray, iteration: int = 0) -> np.ndarray:
        """Solve around ``Pc`` (complex, shape (N,)) with ``g = scale * u``; return ``v``.

        Raises
        ------
        SolveFailure
            If Clarabel reports infeasible, unbounded or fails.
        """
        A, F, n = self.data.A, self.data.F, self.n
        M = np.zeros((self.slots, self.nv))
        c = np.ones(self.slots)  # neutral slots: phi = 1
        M[:n] = 2.0 * (Pc.real[:, None] * A.real + Pc.imag[:, None] * A.imag)
        c[:n] = 2.0 * (F.real * Pc.real + F.imag * Pc.imag) - np.abs(Pc) ** 2
        s = np.ones(self.slots)
        h = np.zeros(self.slots)
        s[:n] = scale
        h[:n] = self.weights[2] * scale
        self._params["M"].value, self._offsets["c"].value = M, c
        self.s.value, self.h.value = s, h
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                self.problem.solve(solver=cp.CLARABEL, warm_start=True, **_SOLVER_OPTS)
        except cp.error.SolverError as exc:
            raise SolveFailure("failed in the solver", iteration) from exc
        status = self.problem.status
        if status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or self.v.value is None:
            raise SolveFailure(str(status), iteration)
        return np.array(self.v.value, dtype=float)


def get_problem(slots: int, nv: int, stroke: bool, n_wind: int = 0) -> ConvexifiedProblem:
    """The compiled problem of this size, built once per process."""
    key = (slots, nv, stroke, n_wind)
    if key in _PROBLEMS:
        _PROBLEMS.move_to_end(key)
        return _PROBLEMS[key]
    prob = _PROBLEMS[key] = ConvexifiedProblem(slots, nv, stroke, n_wind)
    while len(_PROBLEMS) > _MAX_CACHED:
        _PROBLEMS.popitem(last=False)
    return prob


def true_objective(
    data: GridData, v: np.ndarray, r1: np.ndarray, rn: np.ndarray, h: np.ndarray
) -> tuple[float, np.ndarray]:
    """Objective of the controller ``v`` on the grid (not convexified) and its ``P``."""
    Y = data.AY @ v + data.F
    GX = data.AX @ v
    P = Y + GX
    p2 = np.abs(P) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        h2 = np.sum(h * (r1**2 * np.abs(Y) ** 2 + rn**2 * np.abs(GX) ** 2) / p2)
        hinf = data.stroke_weight * np.max(np.abs(GX) ** 2 / p2) if data.stroke_weight > 0 else 0.0
    return float(h2 + hinf), P


def _g_scale(
    data: GridData, Pc: np.ndarray, vc: np.ndarray | None, r1: np.ndarray, rn: np.ndarray
) -> np.ndarray:
    """Per-frequency size of ``g`` at the previous controller (ones if unknown)."""
    if vc is None:
        return np.ones_like(r1)
    Y = data.AY @ vc + data.F
    g = (r1**2 * np.abs(Y) ** 2 + rn**2 * np.abs(data.AX @ vc) ** 2) / np.abs(Pc) ** 2
    # Floor: frequencies where S vanishes (an integrator at 0 Hz) keep a finite scale.
    return np.maximum(g, 1e-8 * max(float(np.max(g)), 1e-300))


@dataclass
class CcpOutcome:
    """Result of the convex-concave iterations of one mode."""

    v: np.ndarray
    history: np.ndarray
    iterates: list
    converged: bool
    solves: int
    added: int


# Extrapolation steps tried beyond each convex step (multiples of the step, doubling).
_EXTRAPOLATION = 2.0 ** np.arange(1, 11) - 1.0
# Number of iterations over which the relative decrease is compared with ``tol``.
_PATIENCE = 3
# Points added to the grid per failed dense check.
_ADD_PER_CHECK = 4


def ccp(
    problem: ConvexifiedProblem,
    grid: GridData,
    weights: tuple,
    dense: GridData,
    v0: np.ndarray | None,
    P0: np.ndarray,
    Pd0: np.ndarray,
    stable: Callable[[np.ndarray], bool],
    wind: tuple | None = None,
    *,
    max_iter: int,
    tol: float,
    extrapolate: bool = True,
    J_start: float = np.inf,
) -> CcpOutcome:
    """Iterate the convexified problem from ``P0`` until the objective stops decreasing.

    Each convex solve gives ``v_new`` with a lower objective than the previous controller
    (which is feasible). Every candidate is checked on the ``dense`` grid (modulus margin
    ``mu |Y| <= |P|``) and for closed-loop stability (``stable``). If a check fails, the worst
    dense points (or, for instability, those where ``P`` turned most from the previous ``P``)
    join the design grid as constraint-only points and the step is solved again: the grid
    could otherwise hide a sharp resonance between its points. The iterations then move along
    long, flat valleys; to cross them ``v_new + t (v_new - v_old)`` is tried for
    ``t = 1, 3, 7, ...`` while it passes the same checks and lowers the objective. The
    objective history is non-increasing.

    Parameters
    ----------
    problem : ConvexifiedProblem
        Compiled problem with enough slots.
    grid : GridData
        Design grid (H2 points first).
    weights : tuple of ndarray
        ``(r1, rn, h)`` on ``grid`` (zeros on constraint-only points).
    dense : GridData
        Verification grid (same ``mu`` as the required modulus margin).
    v0 : ndarray or None
        Coefficients of the initial controller if it lies in the parameter set.
    P0, Pd0 : ndarray of complex, shapes (N,) and (n_dense,)
        ``Y0 + G X0`` of the initial controller on ``grid`` and on ``dense``.
    stable : callable
        ``stable(v)`` is True if the controller ``v`` stabilises the plant.
    wind : tuple (GridData, ndarray), optional
        Fine grid for the linear winding constraints and the initial ``P`` on it (the
        problem must have been built with as many winding rows).
    max_iter : int
        Maximum number of convex solves.
    tol : float
        Stop when the last ``_PATIENCE`` iterations lowered the objective by less than
        ``tol`` (relative) in total.
    extrapolate : bool, default True
        Try extrapolated steps (False: the plain convex-concave iteration).
    J_start : float, optional
        Objective of an initial controller outside the parameter set (``v0`` None), for the
        history only: the first iterate is then accepted whatever its value.

    Returns
    -------
    CcpOutcome
        Best coefficients, objective history (initial first) and the accepted iterates.
    """
    r1, rn, h = weights
    n_h2 = r1.size
    J0 = true_objective(grid, v0, r1, rn, h)[0] if v0 is not None else J_start
    history, iterates = [J0], [v0]
    v_best, J_best, Pc = v0, J0, P0
    converged, solves, added = False, 0, 0

    def weights_on(g: GridData) -> tuple:
        pad = np.zeros(g.F.size - n_h2)
        return tuple(np.concatenate([w, pad]) for w in (r1, rn, h))

    def dense_fail(v: np.ndarray, log: bool = True) -> np.ndarray:
        Y = dense.AY @ v + dense.F
        P = Y + dense.AX @ v
        with np.errstate(divide="ignore", invalid="ignore"):
            excess = np.nan_to_num(dense.mu * np.abs(Y) / np.abs(P) - 1.0, nan=1.0)
        bad = np.flatnonzero(excess > 0)
        if bad.size and log:
            logger.debug(
                "dense margin check failed at %d points (max excess %.3g)",
                bad.size,
                float(excess.max()),
            )
            return bad[np.argsort(excess[bad])[::-1]]
        if not stable(v):
            # A closed-loop pole crossed the circle between grid points: there P turned by
            # more than 90 degrees from the previous (stabilising) controller's.
            Pb = dense.A @ v_best + dense.F if v_best is not None else Pd0
            cos = (P * np.conj(Pb)).real / (np.abs(P) * np.abs(Pb) + 1e-300)
            if log:
                logger.debug(
                    "stability check failed; min cos(P, P_prev) on the dense grid %.3g",
                    float(cos.min()),
                )
            return np.argsort(cos)[:_ADD_PER_CHECK]
        return bad

    problem.set_grid(grid, *weights_on(grid))
    if wind is not None:
        problem.set_winding(wind[0], wind[1])
    it = 0
    while it < max_iter:
        it += 1
        free = v_best is None
        try:
            v = problem.solve(Pc, _g_scale(grid, Pc, v_best, *weights_on(grid)[:2]), it)
        except SolveFailure as exc:
            if free or "infeasible" in exc.status:
                raise
            logger.debug(
                "solver failed at iteration %d (%s); keeping the last iterate", it, exc.status
            )
            converged = True
            break
        solves += 1
        bad = dense_fail(v)
        if bad.size:
            room = problem.slots - grid.F.size
            if room <= 0:
                logger.debug("no free grid slot left; keeping the last iterate")
                converged = True
                break
            # The worst point and its neighbours' worst: a few points per failed check.
            pick = np.unique(bad[: min(_ADD_PER_CHECK, room)])
            grid = grid.join(dense.take(pick))
            Pc = np.concatenate(
                [Pc, dense.A[pick] @ v_best + dense.F[pick]]
                if v_best is not None
                else [Pc, Pd0[pick]]
            )
            added += pick.size
            problem.set_grid(grid, *weights_on(grid))
            continue
        w_grid = weights_on(grid)
        J, P = true_objective(grid, v, *w_grid)
        if not np.isfinite(J):
            if free:
                raise SolveFailure("non-finite objective (Y + G X vanishes)", it)
            converged = True
            break
        if not free and J > J_best * (1 + 1e-9) + 1e-12:
            # The previous controller is feasible: a higher value means the iteration has
            # stalled at the solver's accuracy.
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
                # then starts from a feasible point) and the dense checks.
                if (
                    not Je < J
                    or np.any(grid.mu * np.abs(grid.AY @ ve + grid.F) > np.abs(Pe))
                    or dense_fail(ve, log=False).size
                ):
                    break
                v, J, P = ve, Je, Pe
        history.append(J)
        iterates.append(v)
        v_best, J_best, Pc = v, J, P
        if wind is not None:
            problem.set_winding(wind[0], wind[0].A @ v + wind[0].F)
        if not free and len(history) > _PATIENCE:
            past = history[-1 - _PATIENCE]
            if past - J <= tol * abs(past):
                converged = True
                break
    if v_best is None:
        raise SolveFailure("without an iterate that passes the dense check", it)
    return CcpOutcome(np.asarray(v_best), np.asarray(history), iterates, converged, solves, added)
