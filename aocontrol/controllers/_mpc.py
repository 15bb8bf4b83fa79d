"""Model predictive control bank (a QP per group of modes) with LQG's model and Kalman predictor.

Per mode the estimator is the steady-state Kalman predictor of an
:class:`~aocontrol.controllers.LQGStateSpace` (the same ``A``, ``B``, ``C`` and gain as
:class:`~aocontrol.controllers.LQGBank`). Each frame, with ``xi+`` the updated estimate and
``z0 = regulator_map xi+`` the regulator state ``(x_d[j+k], u[j-1])``, the command minimises
the predicted residual over a horizon of ``N`` frames::

    min_U  sum_{i<N} (H z_i + D u_i)^2 + rho u_i^2 + z_N^T P z_N,  z_{i+1} = A_z z_i + B_z u_i
    s.t.   |u_i| <= command_limit,   |u_i - u_{i-1}| <= rate_limit   (u_{-1}: the last command)

(``e = H z + D u`` is the residual the command first acts on; ``P`` the regulator Riccati
solution, so that with no active constraint the first command is exactly LQG's). The
prediction is condensed (variables ``U`` only): ``0.5 U^T Hq U + (Gz z0)^T U`` with constant
``Hq``, ``Gz``. One QP per group of modes, solved each frame from a warm start: by default
DAQP (a dual active-set solver for small dense QPs, workspace set up once, previous active
set reused; the real-time path), or the casadi formulation (qpOASES or OSQP ``qpsol`` with the
parameters ``(xi+, u_prev)``), kept as the reference (:mod:`aocontrol.controllers._qp`).
Only ``u_0`` is applied; the predictor is advanced with the applied command.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import control
import numpy as np

from aocontrol._deprecation import DeprecatedAttribute, renamed_keyword
from aocontrol._validation import check_int
from aocontrol.controllers._base import (
    _LIMIT_NOTE,
    ControllerBank,
    _all_finite,
    _command_limit_in,
)
from aocontrol.controllers._lqg import (
    LQGBank,
    LQGStateSpace,
    state_space_arrays,
    state_space_from_arrays,
)
from aocontrol.controllers._qp import SOLVERS, CasadiQP, DaqpQP, QPFailure

__all__ = ["MPCBank"]

logger = logging.getLogger(__name__)

# The shortcut (unconstrained optimum applied without a QP) requires every constraint to
# hold with this relative slack: a solution on the boundary goes to the QP.
_SLACK = 1e-9


# A failure is logged on its first occurrence and then every this many failures.
_LOG_EVERY = 1000


def _condensed(ss: LQGStateSpace, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Per mode, ``Hq`` (n, N, N) and ``Gz`` (n, N, nz) of ``0.5 U^T Hq U + (Gz z0)^T U``."""
    Az, Bz, Hz, Dz, P = (
        ss.regulator_A,
        ss.regulator_B,
        ss.regulator_H,
        ss.regulator_D,
        ss.regulator_P,
    )
    n, nz = Bz.shape
    N = horizon
    # powers[i] = Az^i, i = 0..N
    powers = np.empty((N + 1, n, nz, nz))
    powers[0] = np.eye(nz)
    for i in range(1, N + 1):
        powers[i] = powers[i - 1] @ Az
    Phi = np.einsum("mk,imkl->mil", Hz, powers[:N])  # (n, N, nz): H Az^i
    HAB = np.einsum("mk,imkl,ml->mi", Hz, powers[:N], Bz)  # (n, N): H Az^i Bz
    Gamma = np.zeros((n, N, N))
    for i in range(N):
        Gamma[:, i, i] = Dz
        for l in range(i):
            Gamma[:, i, l] = HAB[:, i - 1 - l]
    Psi = np.stack([np.einsum("mkl,ml->mk", powers[N - 1 - l], Bz) for l in range(N)], axis=2)
    AzN = powers[N]
    rho = ss.control_weight
    GtG = np.einsum("mik,mil->mkl", Gamma, Gamma)
    PsiP = np.einsum("mkl,mki->mli", Psi, P)  # Psi^T P: (n, N, nz)
    Hq = 2 * (GtG + rho * np.eye(N) + PsiP @ Psi)
    Gz = 2 * (np.einsum("mik,mil->mkl", Gamma, Phi) + PsiP @ AzN)
    Hq = (Hq + np.swapaxes(Hq, 1, 2)) / 2
    return Hq, Gz


def _per_mode(name: str, value: object, n: int) -> np.ndarray:
    """A limit per mode (> 0, ``inf`` for none), naming the first bad mode."""
    if value is None:
        return np.full(n, np.inf)
    arr = np.asarray(value, dtype=float)
    if arr.ndim > 1 or (arr.ndim == 1 and arr.size != n):
        raise ValueError(f"{name} must be a scalar or have shape ({n},), got shape {arr.shape}")
    arr = np.broadcast_to(arr, (n,)).astype(float)
    bad = np.flatnonzero(~(arr > 0))  # NaN too
    if bad.size:
        raise ValueError(
            f"{name} must be > 0 for every mode (a limit that no command can meet makes the "
            f"constraints infeasible), got {float(arr[bad[0]])!r} for mode {int(bad[0])}"
        )
    return arr


class MPCBank(ControllerBank):
    """MPC bank: LQG's Kalman predictor and a constrained predicted-residual QP per group.

    See the module docstring for the problem. Groups of modes (e.g. tip and tilt) are solved
    as one QP each (block-diagonal: the limits are per mode); the Kalman update, the
    prediction and the unconstrained optimum are vectorised over all modes. With
    ``skip_inactive`` the unconstrained optimum over the horizon is applied without calling
    the solver whenever it meets every limit (it is then the QP's solution); only groups
    with an active limit are solved, one solver call each.

    When a solve fails (solver status or exception) the group's command is the unconstrained
    LQG command clipped to the limits (command limit, and the rate around the last command), the
    failure is counted in ``n_solver_failures`` and logged (first, then every 1000th).

    Parameters
    ----------
    state_space : LQGStateSpace
        The LQG design (:func:`aocontrol.synthesis.lqg_state_space`): disturbance model,
        delays, Kalman gain and the regulator (cost, terminal cost).
    horizon : int, default 10
        Prediction horizon ``N`` [frames], >= 1.
    command_limit : float or array_like of shape (n_modes,), optional
        Hard limit ``|u| <= command_limit`` on the modal command [units of the command], > 0
        (``inf`` for a mode without one); ``None``: none. A controller setting: in the
        simulator, the bound the stage's DM implies per mode
        (:attr:`aocontrol.sim.dm.ModalDM.command_bound`, from ``m2c`` and the actuator stroke
        by :func:`aocontrol.sim.dm.modal_stroke`); ``stroke`` is its deprecated name.
    rate_limit : float or array_like of shape (n_modes,), optional
        Hard limit ``|u[j] - u[j-1]| <= rate_limit`` [units per frame]; ``None``: none.
    groups : sequence of sequences of int, optional
        Modes solved together, e.g. ``[[0, 1]]`` (tip and tilt); modes not listed get a group
        of their own. Default: one group per mode.
    solver : {"daqp", "qpoases", "osqp"}, default "daqp"
        QP solver. ``"daqp"``: DAQP, dual active set, exact on its active set, workspace
        set up once and warm-started from the previous active set (the real-time path);
        ``"qpoases"``, ``"osqp"``: the casadi formulation with that plugin (qpOASES: active
        set, exact; OSQP: ADMM to ``1e-9``), the reference. DAQP and qpOASES agree to
        rounding (tested), both with the cvxpy + Clarabel QP.
    skip_inactive : bool, default True
        Apply the unconstrained optimum without a solve when it meets every limit.
    model : object, optional
        The disturbance model the design came from (kept as ``.model`` for reports).

    Attributes
    ----------
    n_solver_failures : ndarray of int, shape (n_modes,)
        Frames whose command came from the clipped-LQG fallback since the last reset.
    n_solves : ndarray of int, shape (n_modes,)
        Frames whose command came from the QP solver.

    Raises
    ------
    ValueError
        ``horizon < 1``, a limit that is not > 0 (naming the mode), bad groups.

    Examples
    --------
    >>> from aocontrol.synthesis import DisturbanceModel, lqg_state_space
    >>> d = DisturbanceModel([[0.9, 0.0]], [1.0], np.zeros((1, 0)), np.zeros((1, 0)),
    ...                      np.zeros((1, 0)), fs=1000.0)
    >>> ss = lqg_state_space(d, latency_frames=0.0, noise_variance=0.0)
    >>> mpc = MPCBank(ss, horizon=5, command_limit=0.5)
    >>> float(np.round(mpc.step(np.array([1.0]))[0], 6))   # LQG would command 0.9
    0.5
    """

    #: Deprecated name of :attr:`command_limit`.
    stroke = DeprecatedAttribute("command_limit", _LIMIT_NOTE)

    @renamed_keyword("stroke", "command_limit", _LIMIT_NOTE)
    def __init__(
        self,
        state_space: LQGStateSpace,
        horizon: int = 10,
        *,
        command_limit: object = None,
        rate_limit: object = None,
        groups: Sequence[Sequence[int]] | None = None,
        solver: str = "daqp",
        skip_inactive: bool = True,
        model: object = None,
    ) -> None:
        if not isinstance(state_space, LQGStateSpace):
            raise TypeError(
                f"state_space must be an LQGStateSpace, got {type(state_space).__name__}"
            )
        self._ss = state_space
        self.model = model
        n = state_space.n_modes
        self._horizon = check_int("horizon", horizon, minimum=1)
        self._limit = _per_mode("command_limit", command_limit, n)
        self._rate = _per_mode("rate_limit", rate_limit, n)
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {list(SOLVERS)}, got {solver!r}")
        self._solver_name = solver
        self._skip = bool(skip_inactive)
        self._group_modes = self._partition(groups, n)
        Hq, Gz = _condensed(state_space, self._horizon)
        self._Hq, self._Gz = Hq, Gz
        # The QP's linear term on the Kalman estimate: f = Gz z0 = (Gz regulator_map) xi+.
        self._Gx = Gz @ state_space.regulator_map
        # Unconstrained optimum U* = Kfull z0 (n, N, nz); Kfull[:, 0] is LQG's law on z.
        self._Kfull = -np.linalg.solve(Hq, Gz)
        self._KT = self._Kfull @ state_space.regulator_map  # (n, N, ns)
        self._lqg_law = self._KT[:, 0]  # = LQG's control_gain (tested)
        self._limit_tol = self._limit * (1 - _SLACK)
        self._rate_tol = self._rate * (1 - _SLACK)
        self._has_rate = bool(np.isfinite(self._rate).any())
        self._groups = [self._build_group(idx) for idx in self._group_modes]
        self._group_of = np.empty(n, dtype=int)
        for g, idx in enumerate(self._group_modes):
            self._group_of[idx] = g
        self.reset()

    # -- construction ---------------------------------------------------------------------
    @staticmethod
    def _partition(groups: object, n: int) -> list[np.ndarray]:
        seen = np.zeros(n, dtype=bool)
        out: list[np.ndarray] = []
        for gi, group in enumerate(groups or []):
            idx = np.asarray(group)
            if idx.ndim != 1 or idx.size == 0 or not np.issubdtype(idx.dtype, np.integer):
                raise ValueError(f"groups[{gi}] must be a non-empty list of mode indices")
            if np.any((idx < 0) | (idx >= n)):
                raise ValueError(f"groups[{gi}] has modes outside [0, {n - 1}]: {idx.tolist()}")
            if np.any(seen[idx]) or np.unique(idx).size != idx.size:
                raise ValueError(f"groups[{gi}] repeats a mode already in a group: {idx.tolist()}")
            seen[idx] = True
            out.append(np.sort(idx))
        out.extend(np.array([m]) for m in np.flatnonzero(~seen))
        return sorted(out, key=lambda a: int(a[0]))

    def _build_group(self, modes: np.ndarray) -> DaqpQP | CasadiQP:
        """The QP of one group of modes with the chosen solver."""
        data = (self._Hq[modes], self._Gx[modes], self._limit[modes], self._rate[modes])
        if self._solver_name == "daqp":
            return DaqpQP(*data)
        return CasadiQP(*data, plugin=self._solver_name, name=f"mpc_{int(modes[0])}")

    # -- controller files (aocontrol.controllers.save_controller) -------------------------
    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, object]]:
        """The bank as arrays and scalars for :func:`aocontrol.controllers.save_controller`.

        The LQG state space, the limits per mode (``inf`` for none), the group of each mode,
        horizon, solver and ``skip_inactive``; the disturbance model is not saved.
        """
        arrays, attrs = state_space_arrays(self._ss)
        arrays["command_limit"] = np.asarray(self._limit)
        arrays["rate_limit"] = np.asarray(self._rate)
        arrays["group"] = self._group_of.copy()
        attrs.update(horizon=self._horizon, solver=self._solver_name, skip_inactive=self._skip)
        return arrays, attrs

    @classmethod
    def from_arrays(cls, arrays: dict, attrs: dict) -> MPCBank:
        """Inverse of :meth:`to_arrays` (``attrs`` also holds ``fs`` and ``n_modes``).

        Parameters
        ----------
        arrays : dict of str to ndarray
            State-space arrays, ``command_limit`` (``stroke`` in files written before its
            rename), ``rate_limit`` and ``group`` per mode.
        attrs : dict
            State-space scalars, ``horizon``, ``solver``, ``skip_inactive``, ``fs``.
        """
        group = np.asarray(arrays["group"], dtype=int)
        groups = [np.flatnonzero(group == g).tolist() for g in np.unique(group)]
        finite = {
            "command_limit": np.asarray(_command_limit_in(arrays)),
            "rate_limit": np.asarray(arrays["rate_limit"]),
        }
        return cls(
            state_space_from_arrays(arrays, attrs),
            int(attrs["horizon"]),
            command_limit=(
                finite["command_limit"] if np.isfinite(finite["command_limit"]).any() else None
            ),
            rate_limit=finite["rate_limit"] if np.isfinite(finite["rate_limit"]).any() else None,
            groups=groups,
            solver=str(attrs["solver"]),
            skip_inactive=bool(attrs["skip_inactive"]),
        )

    # -- interface ------------------------------------------------------------------------
    @property
    def n_modes(self) -> int:
        return self._ss.n_modes

    @property
    def fs(self) -> float:
        return self._ss.fs

    @property
    def horizon(self) -> int:
        """Prediction horizon [frames]."""
        return self._horizon

    @property
    def command_limit(self) -> np.ndarray | None:
        """The hard limit on the command per mode, shape (n_modes,) (``inf``: none for that
        mode), or ``None`` when no mode has one."""
        if not np.isfinite(self._limit).any():
            return None
        return self._limit.copy()

    @property
    def state_space(self) -> LQGStateSpace:
        """The LQG design whose estimator and regulator the MPC uses."""
        return self._ss

    @property
    def groups(self) -> list[np.ndarray]:
        """Mode indices of each QP."""
        return [g.copy() for g in self._group_modes]

    def reset(self) -> None:
        n = self._ss.n_modes
        self._xi = np.zeros((n, self._ss.ns))
        self._u_prev = np.zeros(n)
        self.n_solver_failures = np.zeros(n, dtype=np.int64)
        self.n_solves = np.zeros(n, dtype=np.int64)
        self._failures_logged = 0
        for g in getattr(self, "_groups", []):
            g.reset()

    def _step(self, m: np.ndarray) -> np.ndarray:
        ss = self._ss
        xi = self._xi
        innov = m - np.add.reduce(ss.C * xi, axis=1)
        xi_post = xi + ss.kalman_gain * innov[:, None]
        # Unconstrained optimum over the horizon, U = Kfull z0 = (Kfull Tz) xi+, (n, N).
        U = np.matmul(self._KT, xi_post[:, :, None])[:, :, 0]
        u = U[:, 0].copy()
        if self._skip:
            lim = self._limit_tol
            ok = np.abs(U).max(axis=1) <= lim
            if self._has_rate:
                dU = np.empty_like(U)
                dU[:, 0] = U[:, 0] - self._u_prev
                np.subtract(U[:, 1:], U[:, :-1], out=dU[:, 1:])
                ok &= np.abs(dU).max(axis=1) <= self._rate_tol
            active = () if ok.all() else np.unique(self._group_of[~ok])
        else:
            active = range(len(self._groups))
        for gi in active:
            self._solve_group(int(gi), xi_post, U, u)
        if not _all_finite(u):
            bad = np.flatnonzero(~np.isfinite(u))[:10].tolist()
            raise FloatingPointError(f"MPC command is not finite for modes {bad}")
        self._xi = np.matmul(ss.A, xi_post[:, :, None])[:, :, 0] + ss.B * u[:, None]
        self._u_prev = u
        return u.copy()

    def _solve_group(self, gi: int, xi: np.ndarray, U: np.ndarray, u: np.ndarray) -> None:
        """Solve group ``gi``'s QP and write its first commands into ``u`` (fallback on failure)."""
        modes = self._group_modes[gi]
        group = self._groups[gi]
        try:
            X = group.solve(xi[modes], self._u_prev[modes])
            if not _all_finite(X.ravel()):
                raise QPFailure("solution not finite")
        except QPFailure as exc:
            self._fallback(gi, U, u, exc)
            return
        # Keep the solution within the limits exactly (solver tolerance).
        u[modes] = np.clip(X[:, 0], -self._limit[modes], self._limit[modes])
        self.n_solves[modes] += 1

    def _fallback(self, gi: int, U: np.ndarray, u: np.ndarray, exc: Exception) -> None:
        """The unconstrained LQG command clipped to the command and rate limits."""
        modes = self._group_modes[gi]
        prev, rate, limit = self._u_prev[modes], self._rate[modes], self._limit[modes]
        lo = np.maximum(-limit, prev - rate)
        hi = np.minimum(limit, prev + rate)
        u[modes] = np.clip(U[modes, 0], lo, hi)
        self.n_solver_failures[modes] += 1
        self._groups[gi].reset()
        self._failures_logged += 1
        if self._failures_logged == 1 or self._failures_logged % _LOG_EVERY == 0:
            logger.warning(
                "MPC: QP of modes %s failed (%s); clipped LQG command applied (%d failure(s) "
                "since reset)",
                modes.tolist(),
                exc,
                self._failures_logged,
            )

    def transfer_function(self, mode: int = 0) -> control.TransferFunction:
        """The unconstrained linear equivalent of ``mode``: LQG's controller, ``dt = 1/fs``.

        With no active limit the MPC command is the LQG command (terminal cost = the
        regulator's Riccati solution), so this is
        :meth:`aocontrol.controllers.LQGBank.transfer_function`.

        Parameters
        ----------
        mode : int, default 0
            Mode index.
        """
        return LQGBank(self._ss).transfer_function(self._check_mode(mode))

    def __repr__(self) -> str:
        return (
            f"MPCBank(n_modes={self.n_modes}, fs={self.fs}, horizon={self._horizon}, "
            f"groups={len(self._groups)}, solver={self._solver_name!r})"
        )
