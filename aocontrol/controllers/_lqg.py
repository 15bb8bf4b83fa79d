"""LQG controller bank: a steady-state Kalman predictor per mode, vectorised over modes.

The state space (built by :func:`aocontrol.synthesis.lqg_state_space`) is, per mode, with
the loop plant ``G = z^-1 ((1-f) z^-k + f z^-(k+1))`` (see :mod:`aocontrol.plant`)::

    xi[j] = (x_d[j-1], u[j-1], u[j-2], ..., u[j-n_u])         ns = nx + n_u
    xi[j+1] = A xi[j] + B u[j] + w[j]                          (disturbance model + delay line)
    m[j]    = C xi[j] + n[j] = d[j-1] - (1-f) u[j-1-k] - f u[j-2-k] + n[j]

``x_d`` is the disturbance model's state (:class:`aocontrol.synthesis.DisturbanceModel`),
``n_u = k + 1`` (``f = 0``) or ``k + 2`` command taps. Per frame the real-time path is

    xi+ = xi- + K (m - C xi-)          (Kalman update, steady-state gain K)
    u   = L xi+                        (control law)
    xi- = A xi+ + B u                  (prediction of the next frame's state)

which :class:`LQGBank` runs vectorised over all modes (elementwise operations on a state
array ``(ns, n_modes)``; a batched matrix product as a fallback). The LQG controller itself
may be unstable (e.g. the minimum-variance controller of a near-integrating AR(2) behind a
two-frame delay has a pole near ``-a1``); the closed loop is stable.
Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import control
import numpy as np

from aocontrol._deprecation import DeprecatedAttribute, renamed_keyword
from aocontrol._validation import check_finite_array, check_positive
from aocontrol.controllers._base import (
    _LIMIT_NOTE,
    ControllerBank,
    _check_command_limit,
    _command_limit_in,
)

__all__ = ["FilterpyLQG", "LQGBank", "LQGStateSpace"]


@dataclass(frozen=True)
class LQGStateSpace:
    """Steady-state LQG of a bank: estimator, predictor and control law, per mode.

    Built by :func:`aocontrol.synthesis.lqg_state_space`; see the module docstring for the
    state layout. Every array's first axis is the mode.

    Parameters
    ----------
    A : ndarray, shape (n_modes, ns, ns)
        Loop-state transition (disturbance model and command delay line).
    B : ndarray, shape (n_modes, ns)
        Command input: ``u[j]`` enters the delay line's first tap.
    C : ndarray, shape (n_modes, ns)
        Measurement ``m[j] = C xi[j] + n[j]``.
    Q : ndarray, shape (n_modes, ns, ns)
        Process-noise covariance per frame [units^2] (zero on the delay line).
    R : ndarray, shape (n_modes,)
        Measurement-noise variance per frame used by the filter [units^2] (floored above 0).
    P : ndarray, shape (n_modes, ns, ns)
        Steady-state prior covariance ``cov(xi[j] - xi-[j])`` (the filter DARE's solution).
    kalman_gain : ndarray, shape (n_modes, ns)
        ``K = P C^T / (C P C^T + R)``.
    control_gain : ndarray, shape (n_modes, ns)
        ``L``: the command ``u[j] = L xi+[j]``.
    regulator_A : ndarray, shape (n_modes, nz, nz)
        Regulator state ``z[j] = (x_d[j+k], u[j-1])``, ``nz = nx + 1``:
        ``z[j+1] = regulator_A z[j] + regulator_B u[j]`` (plus disturbance noise).
    regulator_B : ndarray, shape (n_modes, nz)
        Regulator input.
    regulator_H : ndarray, shape (n_modes, nz)
        The residual the command ``u[j]`` first acts on:
        ``e[j+k] = regulator_H z[j] + regulator_D u[j] = d[j+k] - f u[j-1] - (1-f) u[j]``.
    regulator_D : ndarray, shape (n_modes,)
        ``-(1 - f)``.
    regulator_map : ndarray, shape (n_modes, nz, ns)
        ``E[z[j] | m[..j]] = regulator_map xi+[j]``: ``x_d[j+k] = A_d^(k+1) x_d[j-1]``.
    regulator_P : ndarray, shape (n_modes, nz, nz)
        Regulator DARE solution (cost-to-go ``z^T P z``; an MPC's terminal cost). Its
        disturbance block (a constant for the optimisation) comes from a Stein equation and
        is ill-conditioned for poles near ``z = 1``; the blocks involving ``u`` are exact.
    control_weight : float
        Weight ``rho`` of ``u^2`` in the stage cost ``e^2 + rho u^2``.
    nx : int
        Disturbance-model states per mode.
    latency_frames : float
        Plant latency beyond the WFS frame [frames].
    fs : float
        Loop rate [Hz].

    Notes
    -----
    The regulator minimises ``sum_j (e[j+k]^2 + rho u[j]^2)`` with the standard DARE law
    ``u = -(R_z + B^T P B)^-1 (B^T P A + S^T) z``; ``control_gain = -that gain @ regulator_map``.
    An MPC reuses the estimator (``A``, ``B``, ``C``, ``kalman_gain``), maps ``xi+`` to
    ``z`` with ``regulator_map`` and predicts with ``regulator_A``/``regulator_B``; with the
    terminal cost ``regulator_P`` and no active constraint it reproduces ``control_gain``.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    P: np.ndarray
    kalman_gain: np.ndarray
    control_gain: np.ndarray
    regulator_A: np.ndarray
    regulator_B: np.ndarray
    regulator_H: np.ndarray
    regulator_D: np.ndarray
    regulator_map: np.ndarray
    regulator_P: np.ndarray
    control_weight: float
    nx: int
    latency_frames: float
    fs: float

    def __post_init__(self) -> None:
        check_positive("fs", self.fs)
        n, ns = np.shape(self.A)[0], np.shape(self.A)[-1]
        shapes = {
            "A": (n, ns, ns),
            "B": (n, ns),
            "C": (n, ns),
            "Q": (n, ns, ns),
            "R": (n,),
            "P": (n, ns, ns),
            "kalman_gain": (n, ns),
            "control_gain": (n, ns),
        }
        nz = np.shape(self.regulator_A)[-1]
        shapes.update(
            regulator_A=(n, nz, nz),
            regulator_B=(n, nz),
            regulator_H=(n, nz),
            regulator_D=(n,),
            regulator_map=(n, nz, ns),
            regulator_P=(n, nz, nz),
        )
        for name, shape in shapes.items():
            arr = check_finite_array(name, getattr(self, name))
            if arr.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
            arr = np.array(arr, dtype=float)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def n_modes(self) -> int:
        """Number of modes."""
        return self.A.shape[0]

    @property
    def ns(self) -> int:
        """Loop-state dimension per mode."""
        return self.A.shape[-1]

    @cached_property
    def controller_matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The linear controller ``m -> u`` in state space on ``xi-``, batched over modes.

        ``xi-[j+1] = F xi-[j] + G m[j]``, ``u[j] = H xi-[j] + J m[j]`` with
        ``F = (A + B L)(I - K C)``, ``G = (A + B L) K``, ``H = L (I - K C)``, ``J = L K``.

        Returns
        -------
        F : ndarray, shape (n_modes, ns, ns)
        G : ndarray, shape (n_modes, ns)
        H : ndarray, shape (n_modes, ns)
        J : ndarray, shape (n_modes,)
        """
        K, L = self.kalman_gain, self.control_gain
        eye = np.eye(self.ns)
        ikc = eye[None] - K[:, :, None] * self.C[:, None, :]
        abl = self.A + self.B[:, :, None] * L[:, None, :]
        F = abl @ ikc
        G = np.einsum("mij,mj->mi", abl, K)
        H = np.einsum("mi,mij->mj", L, ikc)
        J = np.einsum("mi,mi->m", L, K)
        for x in (F, G, H, J):
            x.setflags(write=False)
        return F, G, H, J


_STATE_SPACE_ARRAYS = (
    "A", "B", "C", "Q", "R", "P", "kalman_gain", "control_gain", "regulator_A",
    "regulator_B", "regulator_H", "regulator_D", "regulator_map", "regulator_P",
)  # fmt: skip


def state_space_arrays(ss: LQGStateSpace) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """An :class:`LQGStateSpace` as arrays and scalars (controller files of LQG and MPC)."""
    arrays = {name: np.asarray(getattr(ss, name)) for name in _STATE_SPACE_ARRAYS}
    attrs = {
        "control_weight": float(ss.control_weight),
        "nx": int(ss.nx),
        "latency_frames": float(ss.latency_frames),
    }
    return arrays, attrs


def state_space_from_arrays(arrays: dict, attrs: dict) -> LQGStateSpace:
    """Inverse of :func:`state_space_arrays` (``attrs`` also holds ``fs``)."""
    return LQGStateSpace(
        **{name: np.asarray(arrays[name]) for name in _STATE_SPACE_ARRAYS},
        control_weight=float(attrs["control_weight"]),
        nx=int(attrs["nx"]),
        latency_frames=float(attrs["latency_frames"]),
        fs=float(attrs["fs"]),
    )


def _is_structured(ss: LQGStateSpace) -> bool:
    """True if ``ss`` has the layout of ``lqg_state_space``: 2x2 companion disturbance
    blocks, a command shift register fed by ``B``, no gain on the register."""
    n, ns, nx = ss.n_modes, ss.ns, ss.nx
    if nx % 2 or nx < 2 or ns <= nx:
        return False
    expect = np.zeros((n, ns, ns))
    for c in range(0, nx, 2):
        expect[:, c, c] = ss.A[:, c, c]
        expect[:, c, c + 1] = ss.A[:, c, c + 1]
        expect[:, c + 1, c] = 1.0
    for i in range(nx + 1, ns):
        expect[:, i, i - 1] = 1.0
    b = np.zeros((n, ns))
    b[:, nx] = 1.0
    return bool(
        np.array_equal(ss.A, expect)
        and np.array_equal(ss.B, b)
        and not np.any(ss.kalman_gain[:, nx:])
    )


class LQGBank(ControllerBank):
    """Steady-state LQG bank: per-mode Kalman predictor and minimum-variance control law.

    Real-time path, vectorised over modes (no loop over modes). A frame is the innovation
    ``m - C xi-``, the update ``xi+ = xi- + K innov``, the command ``u = L xi+`` and the
    prediction ``xi- = A xi+ + B u``. When ``A`` has the structure
    :func:`aocontrol.synthesis.lqg_state_space` builds (2x2 companion blocks of the
    disturbance model, a shift register of commands), the state of all modes is one array
    ``(ns, n_modes)`` and a frame is about a dozen elementwise numpy operations on rows of
    ``n_modes`` values; otherwise the bank falls back to one batched product
    ``[xi-; u] = M [xi-; m]`` with ``M`` of shape ``(n_modes, ns + 1, ns + 1)`` (about twice
    slower). Both are the same linear recursion as :meth:`transfer_function`.

    Parameters
    ----------
    state_space : LQGStateSpace
        The design (:func:`aocontrol.synthesis.lqg_state_space`).
    model : object, optional
        The disturbance model it was designed from (kept for reports; not used).
    dense : bool, default False
        Always use the batched dense product (a check of the structured path).
    command_limit : float or array of shape (n_modes,), optional
        The controller's own limit on its modal command (same unit as the command, > 0);
        ``None`` for no limit. The command is clipped to ``[-command_limit, command_limit]``
        and the *applied* command enters the delay line of the state, so the estimator stays
        consistent with what the DM did (anti-windup). A controller setting, not the DM's
        stroke; ``stroke`` is its deprecated name.

    Attributes
    ----------
    n_saturated : numpy.ndarray of int, shape (n_modes,)
        Number of frames each mode's command was clipped since the last reset.

    Examples
    --------
    >>> from aocontrol.synthesis import DisturbanceModel, lqg_state_space
    >>> d = DisturbanceModel([[0.9, 0.0]], [1.0], np.zeros((1, 0)), np.zeros((1, 0)),
    ...                      np.zeros((1, 0)), fs=1000.0)
    >>> bank = LQGBank(lqg_state_space(d, latency_frames=0.0, noise_variance=0.0))
    >>> float(np.round(bank.step(np.array([1.0]))[0], 6))   # AR(1), no noise: u = a m
    0.9
    """

    #: Deprecated name of :attr:`command_limit`.
    stroke = DeprecatedAttribute("command_limit", _LIMIT_NOTE)

    @renamed_keyword("stroke", "command_limit", _LIMIT_NOTE)
    def __init__(
        self,
        state_space: LQGStateSpace,
        *,
        model: object = None,
        dense: bool = False,
        command_limit: float | np.ndarray | None = None,
    ) -> None:
        if not isinstance(state_space, LQGStateSpace):
            raise TypeError(
                f"state_space must be an LQGStateSpace, got {type(state_space).__name__}"
            )
        self._ss = state_space
        self.model = model
        self._limit = _check_command_limit(command_limit, state_space.n_modes)
        F, G, H, J = state_space.controller_matrices
        n, ns = state_space.n_modes, state_space.ns
        M = np.zeros((n, ns + 1, ns + 1))
        M[:, :ns, :ns] = F
        M[:, :ns, ns] = G
        M[:, ns, :ns] = H
        M[:, ns, ns] = J
        self._M = M
        self._structured = not dense and _is_structured(state_space)
        self.reset()

    # -- controller files (aocontrol.controllers.save_controller) -------------------------
    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, object]]:
        """The bank as arrays and scalars for :func:`aocontrol.controllers.save_controller`.

        The disturbance model (``model``, kept for reports only) is not saved.
        """
        arrays, attrs = state_space_arrays(self._ss)
        if self._limit is not None:
            arrays["command_limit"] = np.asarray(self._limit)
        attrs["dense"] = not self._structured and _is_structured(self._ss)
        return arrays, attrs

    @classmethod
    def from_arrays(cls, arrays: dict, attrs: dict) -> LQGBank:
        """Inverse of :meth:`to_arrays` (``attrs`` also holds ``fs`` and ``n_modes``).

        Parameters
        ----------
        arrays : dict of str to ndarray
            The state-space arrays (and ``command_limit`` when the bank had one; ``stroke``
            in files written before its rename).
        attrs : dict
            ``control_weight``, ``nx``, ``latency_frames``, ``dense``, ``fs``.
        """
        ss = state_space_from_arrays(arrays, attrs)
        return cls(ss, dense=bool(attrs["dense"]), command_limit=_command_limit_in(arrays))

    @property
    def n_modes(self) -> int:
        return self._ss.n_modes

    @property
    def fs(self) -> float:
        return self._ss.fs

    @property
    def state_space(self) -> LQGStateSpace:
        """The design this bank runs."""
        return self._ss

    def reset(self) -> None:
        ss = self._ss
        n, ns, nx = ss.n_modes, ss.ns, ss.nx
        self.n_saturated = np.zeros(n, dtype=np.int64)
        if self._structured:
            # State transposed, (ns, n_modes), in the component-major order [x0 of each
            # component, x1 of each component, commands]: every operation then runs over
            # contiguous rows of n_modes values (numpy is slow on short inner loops).
            # perm[new] = old index.
            nc = nx // 2
            perm = np.concatenate([np.arange(0, nx, 2), np.arange(1, nx, 2), np.arange(nx, ns)])
            self._perm = perm
            self._s = np.zeros((ns, n))
            self._buf = np.empty((ns, n))
            self._x0, self._x1 = self._s[:nc], self._s[nc:nx]
            diag = np.arange(nc)
            self._a1 = np.ascontiguousarray(ss.A[:, 2 * diag, 2 * diag].T)
            self._a2 = np.ascontiguousarray(ss.A[:, 2 * diag, 2 * diag + 1].T)
            self._tmp = np.empty((nc, n))
            self._c = np.ascontiguousarray(ss.C[:, perm].T)
            self._k = np.ascontiguousarray(ss.kalman_gain[:, perm].T)
            self._l = np.ascontiguousarray(ss.control_gain[:, perm].T)
        else:
            # [xi-; m] per mode, shape (n_modes, ns + 1, 1) for the batched product.
            self._v = np.zeros((n, ns + 1, 1))
            self._out = np.empty_like(self._v)

    def _step(self, m: np.ndarray) -> np.ndarray:
        ss = self._ss
        ns, nx = ss.ns, ss.nx
        if self._structured:
            s, buf = self._s, self._buf
            np.multiply(self._c, s, out=buf)
            innov = m - buf.sum(axis=0)
            np.multiply(self._k, innov, out=buf)
            s += buf
            np.multiply(self._l, s, out=buf)
            u = buf.sum(axis=0)
            if self._limit is not None:
                u = self._clip(u)
            # Prediction: companion blocks (x0, x1) <- (a1 x0 + a2 x1, x0); command shift.
            np.multiply(self._a2, self._x1, out=self._tmp)
            self._x1[...] = self._x0
            self._x0 *= self._a1
            self._x0 += self._tmp
            if ns - nx > 1:
                s[nx + 1 :] = s[nx : ns - 1]
            s[nx] = u
        else:
            self._v[:, ns, 0] = m
            np.matmul(self._M, self._v, out=self._out)
            self._v, self._out = self._out, self._v
            u = self._v[:, ns, 0].copy()
            if self._limit is not None:
                uc = self._clip(u)
                # The delay line holds the applied command: xi- += B (u_applied - u).
                self._v[:, :ns, 0] += ss.B * (uc - u)[:, None]
                u = uc
        if not np.isfinite(u).all():
            bad = np.flatnonzero(~np.isfinite(u))[:10].tolist()
            raise FloatingPointError(f"LQG command is not finite for modes {bad}")
        return u

    def _clip(self, u: np.ndarray) -> np.ndarray:
        clipped = np.abs(u) > self._limit
        if clipped.any():
            self.n_saturated += clipped
            u = np.clip(u, -self._limit, self._limit)
        return u

    @property
    def command_limit(self) -> np.ndarray | None:
        """The controller's limit on its command per mode, shape (n_modes,), or ``None``."""
        return self._limit

    @property
    def predicted_state(self) -> np.ndarray:
        """Current Kalman prediction ``xi-`` of the loop state, shape ``(n_modes, ns)``."""
        if self._structured:
            out = np.empty((self._ss.n_modes, self._ss.ns))
            out[:, self._perm] = self._s.T
            return out
        return self._v[:, : self._ss.ns, 0].copy()

    def transfer_function(self, mode: int = 0) -> control.TransferFunction:
        """Exact linear equivalent ``m -> u`` of ``mode`` (``J + H (zI - F)^-1 G``), ``dt=1/fs``.

        Parameters
        ----------
        mode : int, default 0
            Mode index.
        """
        mode = self._check_mode(mode)
        F, G, H, J = self._ss.controller_matrices
        sys = control.ss(F[mode], G[mode][:, None], H[mode][None, :], [[J[mode]]], 1.0 / self.fs)
        return control.ss2tf(sys)

    def __repr__(self) -> str:
        s = self._ss
        return (
            f"LQGBank(n_modes={s.n_modes}, fs={s.fs}, latency_frames={s.latency_frames}, ns={s.ns})"
        )


class FilterpyLQG(ControllerBank):
    """Reference implementation of :class:`LQGBank` with filterpy's ``KalmanFilter``.

    One ``filterpy.kalman.KalmanFilter`` per mode (slow: Python loops over modes, for tests
    and checks only). Each frame runs ``update(m)``, the command ``u = L x`` and
    ``predict(u)`` with filterpy's own covariance recursion (Joseph form). Started at
    ``x = 0`` with the covariance at the steady-state prior ``state_space.P`` (default), the
    gain is the steady-state one from the first frame and the commands are those of
    :class:`LQGBank`; started elsewhere, they converge to them.

    Parameters
    ----------
    state_space : LQGStateSpace
        The design (:func:`aocontrol.synthesis.lqg_state_space`).
    initial_covariance : array_like, shape (n_modes, ns, ns), optional
        Prior covariance of the first frame (default ``state_space.P``).
    """

    def __init__(self, state_space: LQGStateSpace, *, initial_covariance: object = None) -> None:
        if not isinstance(state_space, LQGStateSpace):
            raise TypeError(
                f"state_space must be an LQGStateSpace, got {type(state_space).__name__}"
            )
        self._ss = state_space
        if initial_covariance is None:
            p0 = state_space.P
        else:
            p0 = check_finite_array("initial_covariance", initial_covariance)
            if p0.shape != state_space.P.shape:
                raise ValueError(
                    f"initial_covariance must have shape {state_space.P.shape}, got {p0.shape}"
                )
        self._p0 = np.array(p0, dtype=float)
        self.reset()

    @property
    def n_modes(self) -> int:
        return self._ss.n_modes

    @property
    def fs(self) -> float:
        return self._ss.fs

    def reset(self) -> None:
        from filterpy.kalman import KalmanFilter

        ss = self._ss
        self._filters = []
        for mode in range(ss.n_modes):
            kf = KalmanFilter(dim_x=ss.ns, dim_z=1, dim_u=1)
            kf.F = ss.A[mode].copy()
            kf.B = ss.B[mode][:, None].copy()
            kf.H = ss.C[mode][None, :].copy()
            kf.Q = ss.Q[mode].copy()
            kf.R = np.array([[ss.R[mode]]])
            kf.P = self._p0[mode].copy()
            kf.x = np.zeros((ss.ns, 1))
            self._filters.append(kf)

    def _step(self, m: np.ndarray) -> np.ndarray:
        u = np.empty(self.n_modes)
        for mode, kf in enumerate(self._filters):
            kf.update(np.array([[m[mode]]]))
            u[mode] = float(self._ss.control_gain[mode] @ kf.x[:, 0])
            kf.predict(u=np.array([[u[mode]]]))
        return u

    @property
    def gains(self) -> np.ndarray:
        """Current Kalman gains of the filters, shape ``(n_modes, ns)``."""
        return np.array([kf.K[:, 0] for kf in self._filters])

    def transfer_function(self, mode: int = 0) -> control.TransferFunction:
        """The steady-state linear equivalent (that of :class:`LQGBank`), ``dt = 1/fs``.

        Parameters
        ----------
        mode : int, default 0
            Mode index.
        """
        return LQGBank(self._ss).transfer_function(self._check_mode(mode))
