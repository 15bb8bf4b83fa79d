"""The MPC's per-group QP, behind one small interface, with two kinds of solver.

One group of modes (e.g. tip and tilt) is one QP in the condensed variables
``x = (U_0, ..., U_{ng-1})`` (``N`` commands per mode, mode after mode)::

    min_x  0.5 x^T Hq x + f^T x
    s.t.   -limit <= x <= limit                            (simple bounds, per mode)
           u_prev - rate <= U_j[0] <= u_prev + rate        (modes with a rate limit)
           -rate <= U_j[i] - U_j[i-1] <= rate, i = 1..N-1

with ``Hq`` block diagonal (constant) and ``f_j = Gz_j z0_j = Gx_j xi_j`` (this frame's
regulator state ``z0_j = regulator_map_j xi_j``, ``xi_j`` the updated Kalman estimate; the
product ``Gx = Gz regulator_map`` is formed once). The constant matrices are given once; a
frame sets ``xi`` and ``u_prev`` and solves.

* :class:`DaqpQP` -- the real-time path: DAQP (Arnström, Bemporad and Axehill 2022), a dual
  active-set solver for small dense QPs. The workspace (the Cholesky factor of ``Hq``, the
  constraint matrix) is set up once; each frame updates ``f`` and the rate bounds and
  starts from the previous frame's active set (warm start). The solution is exact on its
  active set (rounding), like qpOASES.
* :class:`CasadiQP` -- the reference formulation: a casadi ``qpsol`` (qpOASES or OSQP)
  built symbolically with the parameters ``(xi, u_prev)``, warm-started from the previous
  solution shifted by one frame and the previous multipliers.

Both raise :class:`QPFailure` when the solver does not report an optimal solution, so the
caller applies its fallback. Control layer: imports nothing from ``sim`` or ``study``.
"""

from __future__ import annotations

import contextlib

import casadi
import daqp
import numpy as np

__all__ = ["CasadiQP", "DaqpQP", "QPFailure", "SOLVERS"]

#: Solvers of :class:`MPCBank`: ``"daqp"`` (real time, default) and the casadi plugins.
SOLVERS = ("daqp", "qpoases", "osqp")

# casadi plugin settings. qpOASES (active set, dense, exact on the active set) prints its
# licence banner (discarded, see _Discard). OSQP (ADMM) is approximate to eps and, measured,
# slower on these small dense QPs.
_CASADI_OPTIONS = {
    "qpoases": {
        "printLevel": "none",
        "sparse": False,
        "hessian_type": "posdef",
        "error_on_fail": False,
    },
    "osqp": {
        "osqp": {"verbose": False, "eps_abs": 1e-9, "eps_rel": 1e-9, "polish": False},
        "warm_start_primal": True,
        "warm_start_dual": True,
        "error_on_fail": False,
    },
}

# DAQP's primal feasibility tolerance is absolute (default 1e-6): scaled here by the group's
# smallest finite limit, so that a limit is met to 1e-10 of itself in any unit (commands in
# nm or in radians). Active constraints hold exactly; this bounds the inactive ones.
_DAQP_PRIMAL_TOL = 1e-10
# DAQP exit flags: 1 optimal (2: optimal with soft constraints, not used here).
_DAQP_OPTIMAL = 1


class QPFailure(RuntimeError):
    """The QP solver did not return an optimal solution (status in the message)."""


class _Discard:
    """A text sink: casadi routes qpOASES's C++ output (its licence banner, printed when a
    solver is created and on its first solve) through ``sys.stdout``; library code must not
    print."""

    def write(self, text: str) -> int:
        return len(text)

    def flush(self) -> None:
        pass


_SINK = _Discard()


def _rate_rows(n_modes: int, horizon: int, has_rate: np.ndarray) -> np.ndarray:
    """Constraint matrix of the rate limits, ``(horizon * n_rate, n_modes * horizon)``.

    Per mode with a rate limit: the row ``U_j[0]`` (bounded around ``u_prev``), then the
    rows ``U_j[i] - U_j[i-1]``.
    """
    N = horizon
    blocks = []
    for j in np.flatnonzero(has_rate):
        D = np.zeros((N, n_modes * N))
        D[np.arange(N), j * N + np.arange(N)] = 1.0
        D[np.arange(1, N), j * N + np.arange(N - 1)] = -1.0
        blocks.append(D)
    return np.vstack(blocks) if blocks else np.zeros((0, n_modes * N))


class _GroupQP:
    """The data of one group's QP shared by both solvers."""

    def __init__(self, Hq: np.ndarray, Gx: np.ndarray, limit: np.ndarray, rate: np.ndarray) -> None:
        self.n_modes, self.horizon, self.ns = Gx.shape
        self.Hq, self.Gx = Hq, Gx  # (ng, N, N), (ng, N, ns)
        self.limit, self.rate = limit, rate  # (ng,), inf for none
        self.has_rate = np.isfinite(rate)


class DaqpQP(_GroupQP):
    """One group's QP solved by DAQP, workspace set up once, warm-started (see module doc).

    Parameters
    ----------
    Hq : ndarray, shape (ng, N, N)
        Condensed Hessian per mode (positive definite).
    Gx : ndarray, shape (ng, N, ns)
        Linear-term map per mode on the Kalman estimate: ``f_j = Gx[j] xi[j]``.
    limit, rate : ndarray, shape (ng,)
        Limits per mode (``inf`` for none).
    """

    def __init__(self, Hq: np.ndarray, Gx: np.ndarray, limit: np.ndarray, rate: np.ndarray) -> None:
        super().__init__(Hq, Gx, limit, rate)
        ng, N = self.n_modes, self.horizon
        ns = self.ns
        H = np.zeros((ng * N, ng * N))
        F = np.zeros((ng * N, ng * ns))  # f = F xi.ravel(): one matrix-vector product
        for j in range(ng):
            H[j * N : (j + 1) * N, j * N : (j + 1) * N] = Hq[j]
            F[j * N : (j + 1) * N, j * ns : (j + 1) * ns] = Gx[j]
        self._F = F
        self._A = _rate_rows(ng, N, self.has_rate)
        s = np.repeat(limit, N)
        r = np.concatenate([np.full(N, x) for x in rate[self.has_rate]] or [np.zeros(0)])
        # Bounds: the simple bounds first (DAQP's convention), then the rate rows.
        self._upper = np.concatenate([s, r])
        self._lower = -self._upper
        # Index of each rate-limited mode's U_j[0] row in the bound vectors.
        self._first_rows = ng * N + N * np.arange(int(self.has_rate.sum()))
        limits = np.concatenate([limit, rate])
        finite = limits[np.isfinite(limits)]
        primal_tol = _DAQP_PRIMAL_TOL * (float(finite.min()) if finite.size else 1.0)
        self._model = daqp.Model()
        self._model.settings = {"primal_tol": primal_tol}
        flag, _ = self._model.setup(H, np.zeros(ng * N), self._A, self._upper, self._lower)
        if flag < 0:
            raise QPFailure(f"DAQP setup failed (exit flag {flag}); is Hq positive definite?")
        self._cold_sense = np.zeros(self._upper.size, dtype=np.int32)
        self.reset()

    def reset(self) -> None:
        """Forget the warm start: the next solve starts with no active constraint."""
        self._cold = True

    def solve(self, xi: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Optimal ``U``, shape ``(ng, N)``, for the Kalman estimates ``xi`` ``(ng, ns)``.

        Parameters
        ----------
        xi : ndarray, shape (ng, ns)
            Updated Kalman estimate of each mode of the group.
        u_prev : ndarray, shape (ng,)
            Last applied command of each mode (the rate limit's reference).

        Raises
        ------
        QPFailure
            DAQP's exit flag is not "optimal".
        """
        data = {"f": self._F @ xi.ravel()}
        if self._first_rows.size:
            prev = u_prev[self.has_rate]
            rate = self.rate[self.has_rate]
            self._upper[self._first_rows] = prev + rate
            self._lower[self._first_rows] = prev - rate
            data.update(bupper=self._upper, blower=self._lower)
        if self._cold:
            # An explicit sense overrides DAQP's reuse of the previous active set.
            data["sense"] = self._cold_sense
            self._cold = False
        self._model.update(**data)
        x, _, flag, _ = self._model.solve()
        if flag != _DAQP_OPTIMAL:
            self._cold = True
            raise QPFailure(f"DAQP exit flag {flag}")
        return np.asarray(x, dtype=float).reshape(self.n_modes, self.horizon)


class CasadiQP(_GroupQP):
    """One group's QP as a casadi ``qpsol`` (the reference formulation; see module doc).

    Parameters
    ----------
    Hq, Gx, limit, rate
        As :class:`DaqpQP`.
    plugin : {"qpoases", "osqp"}
        casadi QP plugin.
    name : str
        Name of the casadi function.
    """

    def __init__(
        self,
        Hq: np.ndarray,
        Gx: np.ndarray,
        limit: np.ndarray,
        rate: np.ndarray,
        plugin: str,
        name: str,
    ) -> None:
        super().__init__(Hq, Gx, limit, rate)
        ng, N, nz = self.n_modes, self.horizon, self.ns
        U = casadi.SX.sym("U", ng * N)
        p = casadi.SX.sym("p", ng * nz + ng)
        cost = 0
        rate_rows = []
        for j in range(ng):
            u = U[j * N : (j + 1) * N]
            xi = p[j * nz : (j + 1) * nz]
            lin = casadi.mtimes(casadi.DM(Gx[j]), xi)
            cost += 0.5 * casadi.mtimes([u.T, casadi.DM(Hq[j]), u]) + casadi.dot(lin, u)
            if self.has_rate[j]:
                rate_rows.append(u[0] - p[ng * nz + j])
                rate_rows.append(u[1:] - u[:-1])
        g = casadi.vertcat(*rate_rows) if rate_rows else casadi.SX(0, 1)
        with contextlib.redirect_stdout(_SINK):
            self.solver = casadi.qpsol(
                name, plugin, {"x": U, "p": p, "f": cost, "g": g}, _CASADI_OPTIONS[plugin]
            )
        s = np.repeat(limit, N)
        r = np.concatenate([np.full(N, x) for x in rate[self.has_rate]] or [np.zeros(0)])
        self._lbx, self._ubx, self._lbg, self._ubg = -s, s, -r, r
        self.reset()

    def reset(self) -> None:
        """Forget the warm start (zero primal and dual start)."""
        self._x0 = np.zeros(self.n_modes * self.horizon)
        self._lam_x = np.zeros(self._lbx.size)
        self._lam_g = np.zeros(self._lbg.size)

    def solve(self, xi: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Optimal ``U``, shape ``(ng, N)`` (see :meth:`DaqpQP.solve`).

        Raises
        ------
        QPFailure
            The solver raised or did not report success, or returned a non-finite point.
        """
        p = np.concatenate([xi.ravel(), u_prev])
        try:
            with contextlib.redirect_stdout(_SINK):
                sol = self.solver(
                    x0=self._x0,
                    p=p,
                    lbx=self._lbx,
                    ubx=self._ubx,
                    lbg=self._lbg,
                    ubg=self._ubg,
                    lam_x0=self._lam_x,
                    lam_g0=self._lam_g,
                )
        except RuntimeError as exc:
            raise QPFailure(str(exc)) from exc
        stats = self.solver.stats()
        x = np.asarray(sol["x"], dtype=float).ravel()
        if not stats.get("success", False) or not np.all(np.isfinite(x)):
            raise QPFailure(f"solver status {stats.get('return_status', 'unknown')!r}")
        X = x.reshape(self.n_modes, self.horizon)
        # Warm start of the next frame: the solution shifted by one frame.
        self._x0 = np.concatenate([X[:, 1:], X[:, -1:]], axis=1).ravel()
        self._lam_x = np.asarray(sol["lam_x"], dtype=float).ravel()
        self._lam_g = np.asarray(sol["lam_g"], dtype=float).ravel()
        return X
