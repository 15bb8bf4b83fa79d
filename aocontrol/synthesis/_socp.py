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

The iterations that re-solve it around each new controller: :func:`aocontrol.synthesis._ccp.ccp`.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

__all__ = [
    "ConvexifiedProblem",
    "GridData",
    "SizedProblem",
    "SolveFailure",
    "get_problem",
    "true_objective",
]

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
