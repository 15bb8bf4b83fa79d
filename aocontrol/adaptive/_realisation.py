"""Well-conditioned realisations of high-order controllers in the adaptive loop.

A controller is one transfer function, but the loop runs a *realisation* of it, and the
realisation decides how a mismatch of its state (a switch's initial state, round-off) reaches
the command. The Direct-Form I recursion of an LQG's exact transfer function (order up to 8,
poles crowding near ``z = 1`` with nearly cancelling zeros) turns a unit mismatch into a
command of ``1e7`` to ``1e12`` (:func:`~aocontrol.adaptive._redesign.recursion_gain`); the
same LQG run in its own observer form (the Kalman predictor of the loop state, as
:class:`~aocontrol.controllers.LQGBank` runs it) has a gain of tens to hundreds. So the
adaptive loop runs such modes as a batched state-space bank:

    x[k+1] = F x[k] + G m[k] + E (u_applied[k] - u[k]),      u[k] = H x[k] + J m[k]

vectorised over modes (one batched product per frame, the state padded to the largest
order), with ``E`` the input of the applied command (back-calculation: for an observer form,
the delay line's input ``B``, so that the predictor stays consistent with a clipped command).
The other modes (integrators, data-driven filters of order 5, whose recursion gains are
small) stay in Direct-Form I, which is cheaper.

* :class:`StateSpaceRows` holds the per-mode realisations (and which modes use one);
* :func:`state_space_gain` is the certificate of a state-space mode, the counterpart of
  ``recursion_gain``;
* :func:`bumpless_state` initialises a new state-space mode from the recent telemetry;
* :class:`RealisedBank` runs a bank: Direct-Form I rows and state-space rows together.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import control
import numpy as np

from aocontrol._validation import check_int
from aocontrol.controllers import ControllerBank, IIRBank
from aocontrol.plant import z_inverse_coefficients

#: Weights of the bumpless fits (:func:`bumpless_outputs`, :func:`bumpless_state`): e-folding
#: age [frames] of the weights, and the weight of the last frame (the first new command
#: continues the last applied one).
BUMPLESS_MEMORY = 20.0
BUMPLESS_LAST_WEIGHT = 100.0


@dataclass(frozen=True)
class StateSpaceRows:
    """Per-mode state-space realisations of a bank's controllers (some modes, or none).

    ``x[k+1] = F x[k] + G m[k] + E (u_applied[k] - u[k])``, ``u[k] = H x[k] + J m[k]``, the
    state of every mode padded with zeros to ``ns``.

    Attributes
    ----------
    used : ndarray of bool, shape (n_modes,)
        Modes run in state space (the others: Direct-Form I; their rows are zero).
    F : ndarray, shape (n_modes, ns, ns)
    G, H, E : ndarray, shape (n_modes, ns)
    J : ndarray, shape (n_modes,)
    """

    used: np.ndarray
    F: np.ndarray
    G: np.ndarray
    H: np.ndarray
    J: np.ndarray
    E: np.ndarray

    def __post_init__(self) -> None:
        n = self.used.shape[0]
        ns = self.F.shape[-1]
        shapes = {
            "F": (n, ns, ns),
            "G": (n, ns),
            "H": (n, ns),
            "J": (n,),
            "E": (n, ns),
        }
        for name, shape in shapes.items():
            got = np.shape(getattr(self, name))
            if got != shape:
                raise ValueError(f"{name} must have shape {shape}, got {got}")
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f"{name} must be finite")

    @property
    def n_modes(self) -> int:
        return int(self.used.shape[0])

    @property
    def ns(self) -> int:
        """States per mode (padded)."""
        return int(self.F.shape[-1])

    @classmethod
    def none(cls, n_modes: int) -> StateSpaceRows:
        """No mode in state space."""
        z = np.zeros((n_modes, 0))
        return cls(np.zeros(n_modes, bool), np.zeros((n_modes, 0, 0)), z, z, np.zeros(n_modes), z)

    def padded(self, ns: int) -> StateSpaceRows:
        """The same realisations with ``ns`` states (zero states appended)."""
        k = ns - self.ns
        if k < 0:
            raise ValueError(f"ns must be >= {self.ns}, got {ns}")
        if k == 0:
            return self
        vec = {n: np.pad(getattr(self, n), ((0, 0), (0, k))) for n in ("G", "H", "E")}
        return dataclasses.replace(self, F=np.pad(self.F, ((0, 0), (0, k), (0, k))), **vec)

    def rows(self, modes: np.ndarray) -> StateSpaceRows:
        """The rows ``modes``."""
        return StateSpaceRows(*(getattr(self, f.name)[modes] for f in dataclasses.fields(self)))

    def merge(self, other: StateSpaceRows, take: np.ndarray) -> StateSpaceRows:
        """Rows of ``other`` where ``take``, of ``self`` elsewhere (states padded)."""
        ns = max(self.ns, other.ns)
        a, b = self.padded(ns), other.padded(ns)
        parts = {}
        for f in dataclasses.fields(self):
            x, y = getattr(a, f.name), getattr(b, f.name)
            parts[f.name] = np.where(take.reshape((-1,) + (1,) * (x.ndim - 1)), y, x)
        return StateSpaceRows(**parts)

    def expand(self, modes: np.ndarray, n_modes: int) -> StateSpaceRows:
        """These rows placed at ``modes`` of an ``n_modes`` bank (no state space elsewhere)."""
        out = StateSpaceRows.none(n_modes).padded(self.ns)
        parts = {}
        for f in dataclasses.fields(self):
            x = getattr(out, f.name).copy()
            x[modes] = getattr(self, f.name)
            parts[f.name] = x
        return StateSpaceRows(**parts)

    def transfer_function(self, mode: int, fs: float) -> control.TransferFunction:
        """The exact transfer function ``J + H (zI - F)^-1 G`` of a state-space ``mode``."""
        sys = control.ss(
            self.F[mode], self.G[mode][:, None], self.H[mode][None, :], [[self.J[mode]]], 1 / fs
        )
        return control.ss2tf(sys)


#: Doubling steps of the batched Lyapunov solve: converged once ``||A^(2^k)||`` is below
#: round-off, i.e. for closed-loop poles up to radius ``1 - 2^-50`` (the gain is ``inf``
#: beyond: such a loop does not forget a mismatch).
_DOUBLINGS = 50


def _plant_state_space(plant: control.TransferFunction):
    """``(Ap, Bp, Cp, Dp)`` of the loop plant in transposed direct form II (the plant is a
    short delay line: well conditioned)."""
    gb, ga = z_inverse_coefficients(plant, "plant")
    n = max(gb.size, ga.size)
    gb, ga = np.pad(gb, (0, n - gb.size)) / ga[0], np.pad(ga, (0, n - ga.size)) / ga[0]
    Ap = np.zeros((n - 1, n - 1))
    Ap[:, 0] = -ga[1:]
    Ap[np.arange(n - 2), np.arange(1, n - 1)] = 1.0
    Bp = gb[1:] - ga[1:] * gb[0]
    Cp = np.zeros(n - 1)
    if n > 1:
        Cp[0] = 1.0
    return Ap, Bp, Cp, float(gb[0])


def state_space_gains(plant: control.TransferFunction, rows: StateSpaceRows) -> np.ndarray:
    """Closed-loop gain from a mismatch of each state-space controller's state to its command.

    The counterpart of ``recursion_gain`` (the Direct-Form I recursion's) for a controller
    run as ``x[k+1] = F x[k] + G m[k]``, ``u[k] = H x[k] + J m[k]`` on the plant
    (``u = K m``, ``m = -G_p u``): a mismatch ``delta`` of its state (a switch's initial
    state, round-off), in the units of the state (the loop's, for an observer form whose
    state predicts the disturbance and holds past commands, as Direct-Form I's holds past
    measurements and commands), makes a command transient ``u``; returned is the largest
    ``||u||_2 / ||delta||_2`` over all mismatches, ``sqrt(lambda_max(W))`` with ``W`` the
    controller block of the closed loop's observability Gramian of the command (the discrete
    Lyapunov equation ``W = A^T W A + c^T c``, solved by doubling, batched over modes: exact
    to rounding, no frequency grid). It bounds the transient's peak ``max_k |u[k]|`` too. A
    realisation that keeps the controller's poles near ``z = 1`` nearly unobservable in the
    command (an observer form: the LQG's disturbance-model states reach the command only
    through the estimate) has a gain of tens to thousands; the Direct-Form I recursion of
    the same transfer function (as a state space: past measurements and commands) has
    ``1e10`` and more (``tests/test_adaptive_realisation.py`` checks both).

    Parameters
    ----------
    plant : control.TransferFunction
        Loop plant.
    rows : StateSpaceRows
        Realisations; only the modes in ``rows.used`` are computed.

    Returns
    -------
    ndarray, shape (n_modes,)
        The gain per mode (``nan`` for modes not in state space; ``inf`` where the closed
        loop is not stable, or has a pole within ``2^-50`` of the unit circle).
    """
    out = np.full(rows.n_modes, np.nan)
    idx = np.flatnonzero(rows.used)
    if idx.size == 0:
        return out
    block = _command_gramians(plant, rows, idx)
    gain = np.full(idx.size, np.inf)
    done = np.all(np.isfinite(block), axis=(1, 2))
    if done.any() and rows.ns:
        gain[done] = np.sqrt(np.maximum(np.linalg.eigvalsh(block[done])[:, -1], 0.0))
    elif rows.ns == 0:
        gain[:] = 0.0
    out[idx] = gain
    return out


def _command_gramians(
    plant: control.TransferFunction, rows: StateSpaceRows, idx: np.ndarray
) -> np.ndarray:
    """Controller block ``W`` (shape (len(idx), ns, ns)) of the closed loop's observability
    Gramian of the command, per mode ``idx``: a state mismatch ``delta`` makes a command
    transient of energy ``delta^T W delta``. ``inf`` where the loop is not stable."""
    ns = rows.ns
    F, G, H, J = (getattr(rows, k)[idx] for k in ("F", "G", "H", "J"))
    Ap, Bp, Cp, Dp = _plant_state_space(plant)
    n, npl = idx.size, Cp.size
    out = np.full((n, ns, ns), np.inf)
    if ns == 0:
        return out
    # m = -(Cp xp + Dp u), u = H x + J m  =>  u = (H x - J Cp xp) / (1 + J Dp).
    s = 1.0 + J * Dp
    bad = s == 0
    s = np.where(bad, 1.0, s)
    cu = np.concatenate([H, -J[:, None] * Cp[None, :]], axis=1) / s[:, None]  # u = cu [x; xp]
    cm = -np.concatenate([np.zeros((n, ns)), np.broadcast_to(Cp, (n, npl))], axis=1)
    cm = cm - Dp * cu  # m = cm [x; xp]
    acl = np.zeros((n, ns + npl, ns + npl))
    acl[:, :ns, :ns] = F
    acl[:, ns:, ns:] = Ap
    acl[:, :ns] += G[:, :, None] * cm[:, None, :]
    acl[:, ns:] += Bp[None, :, None] * cu[:, None, :]
    radius = np.max(np.abs(np.linalg.eigvals(acl)), axis=1)
    stable = ~bad & (radius < 1.0)
    if stable.any():
        # Doubling: W_2k = W_k + (A^k)^T W_k A^k, A^2k = A^k A^k.
        c = cu[stable]
        w = c[:, :, None] * c[:, None, :]
        a = acl[stable]
        with np.errstate(over="ignore", invalid="ignore"):
            for _ in range(_DOUBLINGS):
                w = w + np.swapaxes(a, 1, 2) @ w @ a
                a = a @ a
                if not np.max(np.abs(a)) >= 1e-18:  # converged (or not finite)
                    break
            block = w[:, :ns, :ns]
            block = (block + np.swapaxes(block, 1, 2)) / 2
            converged = np.max(np.abs(a), axis=(1, 2)) < 1e-12
        block[~converged] = np.inf
        out[stable] = block
    return out


def state_space_gain(
    plant: control.TransferFunction, F: np.ndarray, G: np.ndarray, H: np.ndarray, J: float
) -> float:
    """:func:`state_space_gains` of one controller.

    Parameters
    ----------
    plant : control.TransferFunction
        Loop plant.
    F : ndarray, shape (ns, ns)
        State transition.
    G : ndarray, shape (ns,)
        Measurement input.
    H : ndarray, shape (ns,)
        Command output.
    J : float
        Direct term.

    Returns
    -------
    float
        The gain (``inf`` if the closed loop is not stable).
    """
    F = np.atleast_2d(np.asarray(F, float))
    ns = F.shape[0] if F.size else 0
    g, h = (np.asarray(x, float).reshape(1, ns) for x in (G, H))
    rows = StateSpaceRows(
        np.ones(1, bool), F.reshape(1, ns, ns), g, h, np.array([float(J)]), np.zeros((1, ns))
    )
    return float(state_space_gains(plant, rows)[0])


def bumpless_outputs(
    bank: IIRBank, measurements: np.ndarray, commands: np.ndarray, *, fit_frames: int
) -> np.ndarray:
    """Past outputs for a new filter entering a running loop: the bumpless initial state.

    Setting a new filter's Direct-Form I history to the commands another controller applied
    makes its next command an extrapolation of a trajectory that is not its own: with poles
    near ``z = 1`` (an LQG's turbulence model, a high-order data-driven filter) that
    extrapolation of the old filter's shape is a transient of many times the disturbance.
    Instead, per mode, the new filter is run over the last ``fit_frames`` frames on the
    measurements actually received, from the initial past outputs ``c`` (``na - 1`` values)
    that bring its outputs closest to the commands actually applied (least squares,
    ``min ||u - (zero-state response + F c)||``, ``F`` its free responses). Its virtual
    outputs then track the applied commands over the fit (exactly when the new filter is the
    old one), and its state is its own: the first command continues the loop without a jump
    and without the extrapolation transient.

    Parameters
    ----------
    bank : IIRBank
        The new filters.
    measurements, commands : ndarray, shape (n_frames, n_modes)
        Recent measurements and applied commands, oldest first.
    fit_frames : int
        Frames at the end of the history over which the outputs are fitted (the frames
        before them give the measurements' initial state).

    Returns
    -------
    ndarray, shape (fit_frames, n_modes)
        The new filters' outputs over the fit, for :meth:`IIRBank.set_history`.
    """
    from scipy import signal

    m = np.asarray(measurements, dtype=float)
    u = np.asarray(commands, dtype=float)
    n_total = m.shape[0]
    fit = check_int("fit_frames", fit_frames, minimum=0, maximum=n_total)
    if fit == 0 or bank.a.shape[1] == 1:
        return u[n_total - fit :]
    pre = n_total - fit
    # Recent frames count more (e-folding BUMPLESS_MEMORY frames); the last one most: the
    # first new command continues the last applied one.
    age = np.arange(fit)[::-1]
    weight = np.exp(-age / BUMPLESS_MEMORY)
    weight[-1] = BUMPLESS_LAST_WEIGHT
    out = np.empty((fit, bank.n_modes))
    nb, na = bank.b.shape[1], bank.a.shape[1]
    for i in range(bank.n_modes):  # at a switch only: a short loop of short filters
        b, a = bank.b[i], bank.a[i]
        x_past = m[max(pre - nb + 1, 0) : pre, i][::-1]
        zi = signal.lfiltic(b, a, np.zeros(na - 1), x_past)
        zero_state = signal.lfilter(b, a, m[pre:, i], zi=zi)[0]
        free = np.empty((fit, na - 1))
        for j in range(na - 1):
            y0 = np.zeros(na - 1)
            y0[j] = 1.0
            free[:, j] = signal.lfilter(b, a, np.zeros(fit), zi=signal.lfiltic(b, a, y0))[0]
        c, *_ = np.linalg.lstsq(
            free * weight[:, None], (u[pre:, i] - zero_state) * weight, rcond=None
        )
        out[:, i] = zero_state + free @ c
    return out


def bumpless_state(
    rows: StateSpaceRows, measurements: np.ndarray, commands: np.ndarray, *, fit_frames: int
) -> np.ndarray:
    """Initial state of new state-space controllers entering a running loop (bumpless).

    Each new controller is run over the whole recorded history as it will run in the loop,
    from the zero state, with the commands actually applied entering through ``E``
    (``x <- (F - E H) x + (G - E J) m + E u_applied``, the tracking form). For an observer
    form (``E = B``) this is the Kalman predictor of the loop state driven by the true
    measurements and commands, stable whatever controller applied them: the state is the
    new controller's own estimate of the loop (converged at the estimator's rate from the
    prior mean), and its first command is the command it would give on that loop: it differs
    from the last applied command by what the two controllers disagree on
    (``tests/test_adaptive_realisation.py`` checks that it jumps by a fraction of the
    command where a cold start jumps by all of it). Returned: the state after the last frame,
    ready for the next one. For the controller that produced the commands, started at zero at
    the same frame, it is exactly its own state.

    A least-squares fit of the initial state to the applied commands over the last frames
    (what :func:`~aocontrol.adaptive.bumpless_outputs` does for Direct-Form I) is used only
    for a mode whose tracking form is not stable (spectral radius of ``F - E H`` at least 1):
    for an observer form such a fit puts a large error along the estimator's slow, weakly
    observable directions (nearly cancelled poles near ``z = 1``), a command offset that
    lasts the whole period.

    Parameters
    ----------
    rows : StateSpaceRows
        The new realisations (only the rows in ``rows.used``; others get zeros).
    measurements, commands : ndarray, shape (n_frames, n_modes)
        Recent measurements and applied commands, oldest first (all of them are run).
    fit_frames : int
        Frames at the end of the history fitted by least squares for a mode whose tracking
        form is not stable (``0``: its zero state).

    Returns
    -------
    ndarray, shape (n_modes, ns)
    """
    m = np.asarray(measurements, float)
    u = np.asarray(commands, float)
    fit = check_int("fit_frames", fit_frames, minimum=0, maximum=m.shape[0])
    n, ns = rows.n_modes, rows.ns
    x_end = np.zeros((n, ns))
    idx = np.flatnonzero(rows.used)
    if ns == 0 or idx.size == 0 or m.shape[0] == 0:
        return x_end
    F, G, H, J, E = (getattr(rows, k)[idx] for k in ("F", "G", "H", "J", "E"))
    Ft = F - E[:, :, None] * H[:, None, :]
    Gt = G - E * J[:, None]
    stable = np.max(np.abs(np.linalg.eigvals(Ft)), axis=1) < 1.0
    m, u = m[:, idx], u[:, idx]
    n_run = m.shape[0]
    start = np.where(stable, 0, n_run - fit)  # fitted modes: zero state at the fit's start
    xs = np.zeros((idx.size, ns))  # zero-state response
    phi = np.broadcast_to(np.eye(ns), (idx.size, ns, ns)).copy()  # Ft^k from the fit's start
    own = np.zeros((fit, idx.size))
    free = np.zeros((fit, idx.size, ns))
    fitted = ~stable
    for k in range(n_run):  # at a switch only, vectorised over modes
        active = k >= start
        j = k - (n_run - fit)
        if j >= 0 and fitted.any():
            own[j] = np.einsum("mi,mi->m", H, xs) + J * m[k]
            free[j] = np.einsum("mi,mij->mj", H, phi)
            phi[fitted] = Ft[fitted] @ phi[fitted]
        step = np.einsum("mij,mj->mi", Ft, xs) + Gt * m[k][:, None] + E * u[k][:, None]
        xs = np.where(active[:, None], step, 0.0)
    x = xs
    if fitted.any() and fit:
        age = np.arange(fit)[::-1]
        w = np.exp(-age / BUMPLESS_MEMORY)
        w[-1] = BUMPLESS_LAST_WEIGHT
        lhs = np.transpose(free[:, fitted], (1, 0, 2)) * w[None, :, None]  # (modes, fit, ns)
        rhs = ((u[-fit:, fitted] - own[:, fitted]) * w[:, None]).T  # (modes, fit)
        x0 = np.einsum("mij,mj->mi", np.linalg.pinv(lhs, rcond=1e-12), rhs)
        x = x.copy()
        x[fitted] = xs[fitted] + np.einsum("mij,mj->mi", phi[fitted], x0)
    x_end[idx] = x
    return x_end


class RealisedBank(ControllerBank):
    """A bank whose modes run in Direct-Form I or in state space (:class:`StateSpaceRows`).

    ``bank`` describes every mode's controller (its transfer function); the modes in
    ``rows.used`` run the state-space realisation instead of ``bank``'s Direct-Form I
    recursion. Vectorised over modes: a frame is one :class:`~aocontrol.controllers.IIRBank`
    step on the Direct-Form I modes and one batched product over the state-space modes. The
    bank's ``command_limit`` clips both; a clipped command enters the state (the Direct-Form I
    history, or the state-space state through ``E``: anti-windup).

    Parameters
    ----------
    bank : IIRBank
        Transfer functions of every mode (the Direct-Form I rows run for the other modes).
    rows : StateSpaceRows
        State-space realisations (``rows.used``: the modes that run them).
    """

    def __init__(self, bank: IIRBank, rows: StateSpaceRows) -> None:
        if not isinstance(bank, IIRBank):
            raise TypeError(f"bank must be an IIRBank, got {type(bank).__name__}")
        if rows.n_modes != bank.n_modes:
            raise ValueError(f"rows must have {bank.n_modes} modes, got {rows.n_modes}")
        self.bank = bank
        self.rows = rows
        used = rows.used
        self._idx = np.flatnonzero(used)
        self._df_idx = np.flatnonzero(~used)
        self._df = None
        if self._df_idx.size:
            self._df = bank.rows(self._df_idx).trim_orders()
        idx = self._idx
        # Mode-last layout, (ns, ns, n) and (ns, n): a frame is one pass over contiguous rows
        # of modes (a batched product of small matrices costs twice as much in numpy).
        self._F, self._G, self._H, self._E = (
            np.ascontiguousarray(np.moveaxis(getattr(rows, k)[idx], 0, -1))
            for k in ("F", "G", "H", "E")
        )
        self._J = rows.J[idx].copy()
        lim = bank.command_limit
        self._limit = None if lim is None else lim[idx]
        self.reset()

    @property
    def n_modes(self) -> int:
        return self.bank.n_modes

    @property
    def fs(self) -> float:
        return self.bank.fs

    @property
    def state(self) -> np.ndarray:
        """State of the state-space modes, shape ``(n_state_space_modes, ns)`` (a copy)."""
        return self._x.T.copy()

    def reset(self) -> None:
        if self._df is not None:
            self._df.reset()
        self._x = np.zeros((self.rows.ns, self._idx.size))

    def set_history(self, measurements: np.ndarray, commands: np.ndarray, fit_frames: int) -> None:
        """Bumpless start from recent telemetry: Direct-Form I rows by
        :func:`~aocontrol.adaptive.bumpless_outputs` (fitted over the last ``fit_frames``
        frames), state-space rows by :func:`bumpless_state` (run over all of them)."""
        if self._df is not None:
            m = np.asarray(measurements, float)[:, self._df_idx]
            u = np.asarray(commands, float)[:, self._df_idx]
            self._df.set_history(m, bumpless_outputs(self._df, m, u, fit_frames=fit_frames))
        x = bumpless_state(self.rows, measurements, commands, fit_frames=fit_frames)
        self._x = np.ascontiguousarray(x[self._idx].T)

    def _step(self, m: np.ndarray) -> np.ndarray:
        if self._df is None:
            u = np.empty(self.n_modes)
        elif self._idx.size == 0:
            u = self._df.step(m)
        else:
            u = np.empty(self.n_modes)
            u[self._df_idx] = self._df.step(m[self._df_idx])
        if self._idx.size:
            x, mi = self._x, m[self._idx]
            v = np.einsum("in,in->n", self._H, x) + self._J * mi
            x_next = np.einsum("ijn,jn->in", self._F, x)
            x_next += self._G * mi
            if self._limit is not None:
                vc = np.clip(v, -self._limit, self._limit)
                x_next += self._E * (vc - v)
                v = vc
            if not np.isfinite(v).all():
                bad = self._idx[~np.isfinite(v)][:10].tolist()
                raise FloatingPointError(f"controller command is not finite for modes {bad}")
            self._x = x_next
            u[self._idx] = v
        return u

    def transfer_function(self, mode: int = 0) -> control.TransferFunction:
        mode = self._check_mode(mode)
        if self.rows.used[mode]:
            return self.rows.transfer_function(mode, self.fs)
        return self.bank.transfer_function(mode)

    def __repr__(self) -> str:
        return (
            f"RealisedBank(n_modes={self.n_modes}, fs={self.fs:g}, state_space_modes="
            f"{self._idx.size}, ns={self.rows.ns})"
        )
