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

__all__ = [
    "Certifier",
    "Check",
    "ConvexifiedProblem",
    "GridData",
    "SizedProblem",
    "SolveFailure",
    "ccp",
    "get_problem",
    "true_objective",
]

logger = logging.getLogger(__name__)

# Clarabel settings. Moderate tolerances (each step only needs to lower the objective) and
# inaccurate solutions accepted (accept_unknown): every iterate is checked on the true,
# non-convexified objective and constraints before it is used. No equilibration: the problem
# is scaled by construction (Y monic, G normalised, g = s u), and it halves the IPM iterations.
# Gap 1e-4: each convex step is only a surrogate of the true problem; measured on 6 modes it
# saves ~35 % of the solver time and moves the final objectives by < 0.5 % either way.
# Feasibility 1e-6 rather than 1e-7: 8 % fewer IPM iterations (23.8 vs 25.8 on 8 recorded
# problems), objectives within 3e-4; every iterate is certified on the exact constraints.
# Iterative refinement to 1e-9 (1e-13 by default): Clarabel's KKT products and triangular
# solves of the refinement are a third of its time; measured on 52 recorded problems, 10 %
# less solver CPU, objectives within 1e-6 of the default's.
_SOLVER_OPTS = {
    "tol_gap_abs": 1e-5,
    "tol_gap_rel": 1e-4,
    "tol_feas": 1e-6,
    "max_iter": 100,
    "presolve_enable": False,
    "accept_unknown": True,
    "equilibrate_enable": False,
    "iterative_refinement_reltol": 1e-9,
    "iterative_refinement_abstol": 1e-9,
}
# Winding constraints: Re(P conj Pc) >= _WIND_MIN |Pc|^2 keeps the phase of P within ~87 deg
# of the previous controller's at every point of the winding grid.
_WIND_MIN = 0.05
# ... and |P| >= min(_P_FLOOR, |Pc|): X and Y cannot grow a common factor whose root reaches the
# circle (K unchanged, but a hidden closed-loop mode on the circle). Y is monic: |P| ~ 1.
_P_FLOOR = 1e-2
# Floor of the scaled free denominator: a free pole stays about this fraction inside the radius.
POLE_FLOOR = 1e-4
# Worker-local cache of compiled problems, keyed by (slots, nv, stroke term, winding rows).
_PROBLEMS: OrderedDict[tuple, ConvexifiedProblem] = OrderedDict()
_MAX_CACHED = 12
# Compiled problem sizes are multiples of this number of grid slots (SizedProblem).
_SLOT_STEP = 8


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
    mu : float or ndarray of shape (N,)
        Modulus margin enforced on the grid (one per point allowed: a cut point's margin
        never exceeds what the previous controller meets there, so that it stays feasible).
    hinf_weight : float
        Weight of ``||T||_inf^2`` (0 drops the term).
    """

    AY: np.ndarray
    AX: np.ndarray
    F: np.ndarray
    mu: float | np.ndarray
    hinf_weight: float

    def mu_rows(self) -> np.ndarray:
        """The margin of every point, shape (N,)."""
        return np.broadcast_to(np.asarray(self.mu, dtype=float), self.F.shape)

    @property
    def A(self) -> np.ndarray:
        return self.AY + self.AX

    def take(self, idx: np.ndarray) -> GridData:
        """The rows ``idx`` as a new grid."""
        mu = self.mu if np.ndim(self.mu) == 0 else np.asarray(self.mu)[idx]
        return GridData(self.AY[idx], self.AX[idx], self.F[idx], mu, self.hinf_weight)

    def join(self, other: GridData) -> GridData:
        """This grid followed by the rows of ``other``."""
        return GridData(
            np.vstack([self.AY, other.AY]),
            np.vstack([self.AX, other.AX]),
            np.concatenate([self.F, other.F]),
            np.concatenate([self.mu_rows(), other.mu_rows()]),
            self.hinf_weight,
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
        self._pending: list = []  # (parameter, value) of the grid, assigned by solve()
        self.grid_source: object = None  # what set the grid (SizedProblem's record)
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
        self.grid_source = None
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
            "m_yr": 2 * data.mu_rows()[:, None] * AY.real,
            "m_yi": 2 * data.mu_rows()[:, None] * AY.imag,
        }
        if self.stroke:
            sw = 2 * np.sqrt(data.hinf_weight)
            values.update({"s_xr": sw * AX.real, "s_xi": sw * AX.imag})
        off = {
            "o_yr": r1[:, 0] * data.F.real,
            "o_yi": r1[:, 0] * data.F.imag,
            "o_mr": 2 * data.mu_rows() * data.F.real,
            "o_mi": 2 * data.mu_rows() * data.F.imag,
        }
        # Assigned by solve(): a grid set twice before a solve (the seeds) is assigned once.
        self._pending = [(self._params[k], full(x)) for k, x in values.items() if k in self._params]
        self._pending += [(self._offsets[k], full(x)) for k, x in off.items()]

    def set_winding(self, blocks: list[tuple]) -> None:
        """Linear "same winding" constraints, one block per polynomial kept zero-free.

        Each block ``(A, F, Pw, floor)`` is a polynomial ``Q = A v + F`` on a grid of the
        circle, its value ``Pw`` at the previous controller and an absolute floor of ``|Q|``.
        Rows: ``Re(Q conj Pw) / |Pw| >= max(_WIND_MIN |Pw|, min(floor, |Pw|))``: the phase
        of ``Q`` stays
        within ~87 deg of ``Pw`` (same winding number, so the step keeps the zeros of ``Q`` on
        the same side of the circle) and, as ``Re(Q conj Pw) / |Pw| <= |Q|``, ``|Q|`` stays
        above a floor. The previous controller (``Q = Pw``) satisfies both. The blocks are
        ``P = Y + G X`` (closed-loop stability; floor ``_P_FLOOR`` keeps ``|P|`` away from 0,
        no hidden cancellation on the circle) and, with a pole radius, the scaled free
        denominator (controller poles inside the radius; floor ``POLE_FLOOR``, far above the
        solver's feasibility tolerance, so a pole at the radius cannot slip out by it).
        """
        self.set_winding_rows(*winding_rows(blocks))

    def set_winding_rows(self, A_all: np.ndarray, b_all: np.ndarray) -> None:
        """The winding rows ``A_all v + b_all >= 0`` (from :func:`winding_rows`)."""
        if A_all.shape[0] != self.n_wind:  # pragma: no cover - construction bug
            raise AssertionError(f"{A_all.shape[0]} winding rows for {self.n_wind} slots")
        _assign(self.wind_A, A_all)
        _assign(self.wind_b, b_all)

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
        for param, value in self._pending:
            _assign(param, value)
        self._pending = []
        _assign(self._params["M"], M)
        _assign(self._offsets["c"], c)
        _assign(self.s, s)
        _assign(self.h, h)
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


def _assign(param: cp.Parameter, value: np.ndarray) -> None:
    """Set ``param`` to ``value`` (float array of its shape) without cvxpy's validation.

    The ``value`` setter projects every assignment onto the parameter's attributes to
    validate it, a large share of cvxpy's per-solve time on a warm redesign
    (``docs/benchmarks.md``). The values here are built with the parameter's shape; the only
    attribute used is ``nonneg``, checked here.
    """
    value = np.asarray(value, dtype=float)
    if value.shape != param.shape:  # pragma: no cover - construction bug
        raise AssertionError(f"{param.name()}: value of shape {value.shape}, not {param.shape}")
    if param.is_nonneg() and not np.all(value >= 0):  # pragma: no cover - construction bug
        raise AssertionError(f"{param.name()}: negative value for a nonnegative parameter")
    param.save_value(value)


def winding_rows(blocks: list[tuple]) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``(A, b)`` of the linear "same winding" constraints ``A v + b >= 0`` of ``blocks``
    (see :meth:`ConvexifiedProblem.set_winding`)."""
    rows_A, rows_b = [], []
    for A, F, Pw, absolute in blocks:
        scale = 1.0 / np.abs(Pw)  # row scaling: each row has unit size
        rows_A.append((Pw.real[:, None] * A.real + Pw.imag[:, None] * A.imag) * scale[:, None])
        floor = np.maximum(_WIND_MIN * np.abs(Pw), np.minimum(absolute, np.abs(Pw)))
        rows_b.append((Pw.real * F.real + Pw.imag * F.imag) * scale - floor)
    return np.vstack(rows_A), np.concatenate(rows_b)


def _compiled(slots: int, nv: int, stroke: bool, n_wind: int) -> ConvexifiedProblem:
    """The worker's compiled problem of this size and structure (an LRU cache of them)."""
    key = (slots, nv, stroke, n_wind)
    if key in _PROBLEMS:
        _PROBLEMS.move_to_end(key)
        return _PROBLEMS[key]
    prob = _PROBLEMS[key] = ConvexifiedProblem(slots, nv, stroke, n_wind)
    while len(_PROBLEMS) > _MAX_CACHED:
        _PROBLEMS.popitem(last=False)
    return prob


class SizedProblem:
    """The convexified problem of one mode with up to ``slots`` grid points, solved at the
    grid's size.

    Same interface as :class:`ConvexifiedProblem` (``slots``, ``set_grid``, ``set_winding``,
    ``solve``); each solve uses a compiled problem with the grid's number of points rounded
    up to a multiple of ``step`` (at most ``slots``). The neutral slots of a problem compiled
    for the largest grid are cones Clarabel iterates on all the same; a compiled problem
    costs one compilation per worker and size (``docs/benchmarks.md``).

    Parameters
    ----------
    slots : int
        Maximum number of grid points.
    nv, stroke, n_wind
        As :class:`ConvexifiedProblem`.
    step : int, default _SLOT_STEP
        Granularity of the compiled sizes (``slots`` itself is always one of them).
    """

    def __init__(self, slots: int, nv: int, stroke: bool, n_wind: int = 0, step: int = 0):
        self.slots, self.nv, self.stroke, self.n_wind = slots, nv, stroke, n_wind
        self.step = step or _SLOT_STEP
        self._grid: tuple | None = None
        self._wind: tuple | None = None

    def set_grid(self, data: GridData, r1: np.ndarray, rn: np.ndarray, h: np.ndarray) -> None:
        """Set the grid (``N <= slots`` points) and the H2 weights of one mode."""
        if data.F.size > self.slots:
            raise ValueError(f"grid of {data.F.size} points exceeds the {self.slots} slots")
        self._grid = (data, r1, rn, h)

    def set_winding(self, blocks: list[tuple]) -> None:
        """Linear "same winding" constraints (see :meth:`ConvexifiedProblem.set_winding`)."""
        self._wind = winding_rows(blocks) if self.n_wind else None

    def solve(self, Pc: np.ndarray, scale: np.ndarray, iteration: int = 0) -> np.ndarray:
        """Solve around ``Pc`` (see :meth:`ConvexifiedProblem.solve`) at the grid's size."""
        if self._grid is None:  # pragma: no cover - construction bug
            raise AssertionError("solve() before set_grid()")
        n = self._grid[0].F.size
        size = min(self.slots, -(-max(n, 1) // self.step) * self.step)
        prob = _compiled(size, self.nv, self.stroke, self.n_wind)
        if prob.grid_source is not self._grid:  # held, so never a recycled identity
            prob.set_grid(*self._grid)
            prob.grid_source = self._grid
        if self._wind is not None:
            prob.set_winding_rows(*self._wind)
        return prob.solve(Pc, scale, iteration)


def get_problem(
    slots: int, nv: int, stroke: bool, n_wind: int = 0, rows_per_point: int = 1
) -> SizedProblem:
    """The convexified problem of up to ``slots`` grid rows, solved at the grid's size
    (:class:`SizedProblem`; its compiled problems are cached per worker process). With
    ``rows_per_point`` rows per frequency, the compiled sizes step by whole points."""
    return SizedProblem(slots, nv, stroke, n_wind, step=_SLOT_STEP * rows_per_point)


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
        hinf = data.hinf_weight * np.max(np.abs(GX) ** 2 / p2) if data.hinf_weight > 0 else 0.0
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
        problem.set_winding(cert.winding(v))
        if not free and len(history) > patience:
            past = history[-1 - patience]
            if past - J <= tol * abs(past):
                converged = True
                break
    if v_best is None:
        raise SolveFailure("without an iterate that passes the certificates", it)
    return CcpOutcome(
        np.asarray(v_best), np.asarray(history), iterates, converged, solves, added, damped
    )
