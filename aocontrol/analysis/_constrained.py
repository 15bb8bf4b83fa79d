"""Margin-constrained optimality bound: the best residual of any stabilising linear controller
that also meets a modulus margin.

For a stable plant ``G`` every stabilising controller is ``K = Q / (1 - G Q)`` with ``Q``
stable (Youla), and ``S = 1 - G Q``, ``T = G Q`` are affine in ``Q``. With ``Q`` an FIR filter
of ``n_taps`` coefficients ``q`` (powers of ``z^-1``) the residual variance

    J(q) = int_0^{fs/2} ( |1 - G Q|^2 psd + |G Q|^2 noise_psd ) df        (trapezoid on freqs)

is a convex quadratic in ``q`` and the margin ``|S| <= 1 / mu`` on a grid is a set of
second-order cones: a convex SOCP, given to Clarabel directly (no modelling layer to
compile: :class:`_Problem`). PSDs are one-sided [units^2/Hz].

Write ``a_j = G(f_j) E(f_j)`` (``E`` the FIR basis, ``a`` complex, shape ``(n_freqs,
n_taps)``) and ``P = psd + noise_psd``. Then

    |1 - a q|^2 psd + |a q|^2 noise = P |a q - psd / P|^2 + psd noise / P,

so ``J(q) = ||y - M q||^2 + c`` with the rows ``M = sqrt(w P) [Re a; Im a]``,
``y = sqrt(w P) [psd / P; 0]`` (``w`` the trapezoid weights) and ``c = sum w psd noise / P``.
Any ``R`` with ``R^T R = M^T M`` and ``r`` with ``R^T r = M^T y`` reduce the objective to
``||r - R q||^2`` plus a constant: an ``n_taps``-dimensional least-squares term whatever the
grid size. ``M^T M`` is symmetric Toeplitz, its entry ``(k, l)`` the trapezoid sum
``t_{k-l} = sum_j w_j P_j |G_j|^2 cos(2 pi f_j (k - l) / fs)``, and ``M^T y`` is a sum of the
same kind: products of a ``(n_taps, n_freqs)`` cosine (and sine) matrix, computed once per
call, by the mode's weights. ``R`` is then the Cholesky factor of the Gram matrix and
``r = R^{-T} M^T y``: about ``n_taps^3 / 3 + 6 n_freqs n_taps`` flops per mode, against
``2 n_freqs n_taps^2`` for a QR of ``M``. The Gram matrix squares ``M``'s condition number:
its Cholesky factor is used when its condition number, as LAPACK's ``dtrcon`` estimates it,
is at most ``_GRAM_MAX_COND`` (argued there). Else, or when the Cholesky factorisation fails
(a Gram matrix singular to working precision: fewer rows than taps, PSDs zero over a band),
``R`` and ``r`` come from a thin QR factorisation ``M = U R``, ``r = U^T y``, which does not
square it (one triangular factorisation of ``[M, y]``, ``U`` never formed; ``R`` padded with
zero rows to ``n_taps x n_taps`` when ``M`` has fewer rows). On either path the objective's
value at a solution is computed from ``M``'s rows, ``sum_j w_j P_j |psd_j / P_j - a_j q|^2 +
c``, and every mode's figures are the same arithmetic whichever modes share the call.

The objective's grid must resolve ``S``: the trapezoid on ``N`` equal intervals of [0, fs/2]
sees ``|S|^2`` (a trigonometric polynomial of degree ``L``) only at its points, and an FIR of
``n_taps ~ L`` taps fits a grid of ``N <= L / 2`` intervals exactly, with peaks between its
points that the objective never sees (the bound then comes out far too low, or the solve
fails); short of that the bound is still low by a few per cent at one interval per degree.
So a grid with an interval wider than ``fs / (4 L)`` (two intervals per
degree) has its intervals split into equal parts of at most ``fs / 4096`` (the constraint
grid's resolution), the PSDs interpolated linearly there (as
:func:`aocontrol.synthesis.datadriven`'s fine check): the bound is then the residual for the PSD
interpolated between the input points. A grid fine enough is used as it is.

The margin is imposed on a fine uniform constraint grid (16 points per degree of ``S``) plus
the input grid, by cutting planes: the unconstrained optimum first (often it already meets
the margin: no solve), then a problem with cones at the worst violating local maxima of
``|S|`` on the constraint grid, re-solved with the new violators until none is left (the
objective is a strictly convex quadratic and ``Q = 0`` is feasible: every relaxation has its
optimum, and the first that meets the margin on the whole grid is that grid's optimum).
Clarabel's cost grows with the number of cones times ``n_taps^2``, which the cutting planes
keep small.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import control
import numpy as np
import scipy.linalg as sla
from scipy.fft import next_fast_len

from aocontrol._validation import (
    PerModeError,
    check_frequency_grid,
    check_in_range,
    check_int,
    mode_psds,
)
from aocontrol.controllers import IIRBank
from aocontrol.plant import frequency_response, plant_fs, z_inverse_coefficients

__all__ = ["ConstrainedBound", "ConstrainedBoundError", "constrained_bound"]

logger = logging.getLogger(__name__)

# Clarabel settings: tight gaps (the bound is a yardstick, not a design step; the objective
# is scaled to O(1) per mode, see _scale).
_SOLVER_OPTS = {"tol_gap_abs": 1e-9, "tol_gap_rel": 1e-9, "tol_feas": 1e-9, "max_iter": 200}
# Clarabel's supernodal LDL (faer, Clarabel >= 0.10): the cone rows are dense in q (every
# point's row has all n_taps coefficients), which its dense blocks factor at BLAS speed: 2.2x
# faster than the default QDLDL, measured at 256 taps and 1,200-1,800 rows (one thread);
# QDLDL where this Clarabel lacks it.
_DIRECT_SOLVE_METHODS = ("faer", "qdldl")
# Constraint grid: this many points per degree of S = 1 - G Q (linear in [0, fs/2]), and at
# least _MIN_CONSTRAINT points. A trigonometric polynomial of degree L varies on a scale
# pi / L rad: 16 points per degree keep its peak between grid points within ~0.5 %. The
# number of intervals is then rounded up to an 11-smooth one (scipy.fft.next_fast_len): |S|
# on the grid is an FFT of twice that length, and of 8 times more on the verification grid;
# 16 L - 1 is often a prime (2,063 at 128 taps, 4,111 at 256), where the FFT's chirp-z
# fallback took 2-8 ms per mode, about 80 % of the bound of a mode without cuts.
_CONSTRAINT_PER_DEGREE = 16
_MIN_CONSTRAINT = 2048
# Objective grid: at least this many intervals of [0, fs/2] per degree of S, else refined
# (_objective_grid). Measured on a steep spectrum with a 25-Hz-wide line (1 kHz, 32 taps, uniform
# grids): the bound 2.9 % / 0.8 % / 0.2 % / 0.02 % below its converged value at 1 / 1.5 / 2 / 3
# intervals per degree, 15 % at 0.6 (and at 0.5 the least squares has as many equations as taps:
# S fitted to 0 at the grid points).
_OBJECTIVE_PER_DEGREE = 2
# Verification grid: this many times denser than the constraint grid (plus the input grid).
_VERIFY_FACTOR = 8
# Cutting planes: points added per round, rounds, and the tolerance on mu |S| - 1 below
# which a constraint-grid point counts as satisfied.
_CUTS_PER_ROUND = 64
_MAX_ROUNDS = 60
_CUT_TOL = 1e-7
# Objective scale floor relative to the disturbance-plus-noise variance (a mode whose
# unconstrained FIR optimum is exactly zero keeps a finite scale).
_SCALE_FLOOR = 1e-12
# Least-squares factor from the Gram matrix (module docstring) only when the Cholesky factor's
# condition number (that of M), as LAPACK's dtrcon estimates it in the 1-norm, is at most this;
# else the QR of [M, y]. Forming and factoring M^T M perturbs it by about eps ||M||^2, as the
# QR's backward error does, and the optimal value moves by about that times ||q||^2 on either
# path. The squared condition number enters the solution q: its error is about
# eps cond(M)^2 from the normal equations, against eps (cond(M) + cond(M)^2 rho) from the QR,
# rho = ||y - M q|| / (||M|| ||q||) (Higham, Accuracy and Stability of Numerical Algorithms,
# 2nd ed., 20.1 and 20.4; the bound's residual is not small, so the two differ by less than
# 1 / rho). The estimate was 0.3-3.7 times the 2-norm condition number on the modes below, so
# at 3e4 cond(M) <= 1e5 and eps cond(M)^2 <= 2e-6: the level at which the SOCP's own 1e-9 gap
# moves q (1e-6 relative between two solves of one mode, measured), with the Cholesky far from
# breaking down (cond(M^T M) = 1e10 << 1 / eps). Measured (2-norm): cond(M) 18-193 on the 540
# modes estimated from telemetry at 3 kHz (their noise floor bounds it), 600-66,000 on the
# synthetic resonant modes of bench_design_speed part (b) (turbulence over 10 decades);
# docs/benchmarks.md has the differences between the two paths.
_GRAM_MAX_COND = 3e4


class ConstrainedBoundError(PerModeError):
    """The bound could not be computed for some modes; the others are kept.

    Parameters
    ----------
    failed : dict[int, str]
        Mode index -> reason (kept as ``.failed``).
    result : ConstrainedBound
        Every mode; failed modes have ``ok == False`` and ``variance == nan`` (kept as
        ``.result``).
    """

    def __init__(self, failed: dict[int, str], result: ConstrainedBound) -> None:
        super().__init__(
            failed, result, n_modes=result.variance.size, operation="constrained_bound"
        )


@dataclass(frozen=True)
class ConstrainedBound:
    """Result of :func:`constrained_bound`.

    Attributes
    ----------
    variance : ndarray, shape (n_modes,)
        The bound: lowest residual variance [units^2] over FIR Youla parameters of
        ``n_taps`` taps meeting ``|S| <= 1 / modulus_margin`` on ``constraint_freqs``
        (trapezoid on the input grid; ``nan`` for a failed mode).
    unconstrained : ndarray, shape (n_modes,)
        The same without the margin (FIR Wiener filter, least squares) [units^2]: the
        ``modulus_margin -> 0`` limit, which tends to :func:`wiener_bound` as ``n_taps`` grows.
    q : ndarray, shape (n_modes, n_taps)
        Optimal Youla parameters (FIR coefficients in powers of ``z^-1``).
    verified_margin : ndarray, shape (n_modes,)
        ``min |1 + G K| = 1 / max |S|`` on ``verify_freqs`` (dense grid).
    certified_margin : ndarray, shape (n_modes,)
        A lower bound of ``min |1 + G K|`` over the whole frequency axis for an FIR plant
        (``S`` is then a polynomial of degree ``L`` in ``z^-1``; Bernstein's inequality on the
        uniform part of ``verify_freqs`` with ``M`` intervals gives
        ``max |S| <= max_grid |S| / (1 - pi L / (2 M))``); ``nan`` for an IIR plant.
    ok : ndarray of bool, shape (n_modes,)
        The mode was solved.
    messages : tuple of str
        Failure reason per mode (empty when ``ok``).
    modulus_margin : float
        Required margin ``mu`` (0: no margin).
    n_taps : int
        FIR length of ``Q``.
    fs : float
        Loop rate [Hz].
    constraint_freqs : ndarray, shape (n_constraint,)
        Grid on which the margin is imposed [Hz].
    verify_freqs : ndarray, shape (n_verify,)
        Verification grid [Hz].
    plant_coefficients : tuple of ndarray
        ``(B, A)`` of the plant in powers of ``z^-1`` (for :attr:`controller`).
    solves : ndarray of int, shape (n_modes,)
        SOCP solves per mode (cutting-plane rounds; 0 when the unconstrained FIR optimum
        already meets the margin on the constraint grid).
    objective_freqs : ndarray, shape (n_objective,)
        Grid of the objective's trapezoid [Hz]: the input grid, or the input grid refined
        where it does not resolve ``S`` (the PSDs interpolated linearly; module docstring).
    """

    variance: np.ndarray
    unconstrained: np.ndarray
    q: np.ndarray
    verified_margin: np.ndarray
    certified_margin: np.ndarray
    ok: np.ndarray
    messages: tuple[str, ...]
    modulus_margin: float
    n_taps: int
    fs: float
    constraint_freqs: np.ndarray = field(repr=False)
    verify_freqs: np.ndarray = field(repr=False)
    plant_coefficients: tuple[np.ndarray, np.ndarray] = field(repr=False)
    solves: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, dtype=int))
    objective_freqs: np.ndarray | None = field(repr=False, default=None)

    def __post_init__(self) -> None:
        n = self.variance.shape
        for name in ("unconstrained", "verified_margin", "certified_margin", "ok"):
            if getattr(self, name).shape != n:
                raise ValueError(f"{name} must have shape {n}, got {getattr(self, name).shape}")
        if self.q.shape != n + (self.n_taps,):
            raise ValueError(f"q must have shape {n + (self.n_taps,)}, got {self.q.shape}")
        if len(self.messages) != n[0]:
            raise ValueError(f"messages must have {n[0]} entries, got {len(self.messages)}")

    @property
    def controller(self) -> IIRBank:
        """The controllers ``K = Q / (1 - G Q)`` that reach the bound, one per mode.

        For ``G = B / A`` (powers of ``z^-1``), ``K = Q A / (A - B Q)``. The closed loop is
        stable by construction (``G`` and ``Q`` stable), whether or not ``K`` itself is.
        """
        bg, ag = self.plant_coefficients
        pp = np.polynomial.polynomial
        rows_b = [pp.polymul(q, ag) for q in self.q]
        rows_a = [pp.polysub(ag, pp.polymul(bg, q)) for q in self.q]
        return IIRBank.from_rows(rows_b, rows_a, self.fs)


class _Problem:
    """``min ||R q - r||^2 s.t. mu |1 - a_j q| <= 1`` at the cuts ``a_j``.

    Given to Clarabel directly, in the standard form Clarabel takes (``min x' P x / 2 + c' x``
    s.t. ``b - A x`` in a product of cones), with ``x = (q, t)``:

    * ``t = R q - r`` (a zero cone of ``n_taps`` rows) and ``P = 2 I`` on ``t``: the
      objective ``||t||^2`` (the least-squares term as cvxpy canonicalises ``sum_squares``,
      not ``R' R``, whose condition number is squared);
    * one 3-dimensional second-order cone per point,
      ``(1, mu - mu Re(a_j) q, -mu Im(a_j) q)``: ``|mu (1 - a_j q)| <= 1``.

    With a well-conditioned ``R`` (the Gram path: ``cond(R) <= _GRAM_MAX_COND``) the variable
    is ``t`` alone (``whitened``): ``q = R^{-1} (r + t)``, ``P = 2 I``, no zero cone and no
    ``q``, the cone rows ``mu a_j R^{-1}`` and their offsets at ``q_ls = R^{-1} r``. The same
    problem with ``n_taps`` variables instead of ``2 n_taps`` plus ``n_taps`` equality rows:
    0.65-0.75x the solver time per solve at 128-256 taps (``docs/benchmarks.md``). The QR
    path keeps the zero-cone form (``R`` may be ill-conditioned or singular there).

    The cuts (the worst points of the fine constraint grid) and the least-squares term change
    per solve. Nothing is compiled: cvxpy's DPP compilation of parameter cut rows
    (``slots x n_taps`` parameters times ``q``) took about 30 s and 4.3 GB at 256 taps, once
    per call. The problem is as small as the cuts: no neutral spare slots and no base grid
    (cones that a compiled problem could hold as constants; here they only made every solve
    larger: 264 of them at 256 taps, against about 60 to 350 cuts in all, measured).
    """

    def __init__(self, mu: float, n_taps: int) -> None:
        self.n_taps, self.mu = n_taps, float(mu)
        self.cuts = np.zeros((0, n_taps), complex)
        self.R: np.ndarray | None = None
        self.r: np.ndarray | None = None
        self.whitened = False

    def set_cuts(self, a_cut: np.ndarray, mu: float) -> None:
        """Margin cones at the rows ``a_cut`` (complex, ``(n_cut, n_taps)``)."""
        if float(mu) != self.mu:  # pragma: no cover - one margin per problem
            raise ValueError(f"mu must be the problem's {self.mu!r}, got {mu!r}")
        self.cuts = np.asarray(a_cut, dtype=complex)

    def data(self) -> tuple:
        """``(P, c, A, b, cones)`` of the current cuts and least-squares term."""
        import clarabel
        import scipy.sparse as sp

        n = self.n_taps
        cone_rows, cone_b = _cone_rows(self.cuts, self.mu)
        m = cone_rows.shape[0]
        socs = [clarabel.SecondOrderConeT(3)] * (m // 3)
        if self.whitened:
            q_ls = sla.solve_triangular(self.R, self.r, check_finite=False)
            rows = sla.solve_triangular(self.R, cone_rows.T, trans="T", check_finite=False).T
            P = sp.diags_array(np.full(n, 2.0), format="csc")
            return P, np.zeros(n), sp.csc_array(rows), cone_b - cone_rows @ q_ls, socs
        A = sp.vstack(
            [
                sp.hstack([sp.csc_array(self.R), -sp.identity(n, format="csc")]),
                sp.hstack([sp.csc_array(cone_rows), sp.csc_array((m, n))]),
            ],
            format="csc",
        )
        b = np.concatenate([self.r, cone_b])
        P = sp.block_diag([sp.csc_array((n, n)), 2.0 * sp.identity(n)], format="csc")
        return P, np.zeros(2 * n), A, b, [clarabel.ZeroConeT(n)] + socs

    def solve(self, R: np.ndarray, r: np.ndarray, whitened: bool = False) -> np.ndarray:
        """Solve with the least-squares term ``(R, r)``; raises ``RuntimeError`` on failure."""
        self.R, self.r = np.asarray(R, dtype=float), np.asarray(r, dtype=float)
        self.whitened = bool(whitened)
        x = _solve(self)
        if self.whitened:
            return sla.solve_triangular(self.R, self.r + x, check_finite=False)
        return x[: self.n_taps]


def _cone_rows(a: np.ndarray, mu: float) -> tuple[np.ndarray, np.ndarray]:
    """``A`` rows and ``b`` of the cones ``(1, mu - mu Re(a) q, -mu Im(a) q)`` (``b - A q``),
    three rows per point of ``a`` (complex, ``(n_points, n_taps)``)."""
    rows = np.zeros((a.shape[0], 3, a.shape[1]))
    rows[:, 1], rows[:, 2] = mu * a.real, mu * a.imag
    b = np.tile([1.0, mu, 0.0], a.shape[0])
    return rows.reshape(-1, a.shape[1]), b


def _solve(prob: _Problem) -> np.ndarray:
    """One Clarabel solve; raises ``RuntimeError`` naming the solver status on failure."""
    import clarabel

    data = prob.data()
    for method in _DIRECT_SOLVE_METHODS:
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.max_threads = 1  # one process per core (the synthesis' workers)
        for key, value in _SOLVER_OPTS.items():
            setattr(settings, key, value)
        settings.direct_solve_method = method
        try:
            solution = clarabel.DefaultSolver(*data, settings).solve()
            break
        except Exception as exc:  # noqa: BLE001 - Clarabel raises a bare Exception
            if "direct_solve_method" in str(exc) and method != _DIRECT_SOLVE_METHODS[-1]:
                continue  # an older Clarabel without this method
            raise RuntimeError(f"Clarabel failed ({exc})") from exc
    status = str(solution.status)
    x = np.array(solution.x, dtype=float)
    if status not in ("Solved", "AlmostSolved") or not np.all(np.isfinite(x)):
        raise RuntimeError(f"Clarabel returned status {status!r}")
    return x


class _SGrid:
    """``S = 1 - G Q`` on a uniform grid of ``[0, fs/2]`` (FFT) plus extra points (matrix)."""

    def __init__(
        self,
        plant: object,
        fs: float,
        n_intervals: int,
        extra: np.ndarray,
        n_taps: int,
        a_extra: np.ndarray | None = None,
    ):
        self.n = n_intervals
        self.freqs_uniform = np.linspace(0.0, fs / 2, n_intervals + 1)
        self.g = frequency_response(plant, self.freqs_uniform, fs)
        self.extra = extra
        self.a_extra = _basis(plant, extra, fs, n_taps) if a_extra is None else a_extra
        self.plant, self.fs, self.n_taps = plant, fs, n_taps

    def abs_s(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``|S|`` on the uniform grid and on the extra points."""
        uniform = np.abs(1.0 - self.g * np.fft.rfft(q, 2 * self.n))
        return uniform, np.abs(1.0 - self.a_extra @ q)

    def cut_rows(self, q: np.ndarray, mu: float, n_max: int) -> np.ndarray:
        """Basis rows at the ``n_max`` worst local maxima of ``mu |S|`` above 1 (tolerance)."""
        uniform, extra = self.abs_s(q)
        f_u = self.freqs_uniform
        peaks = np.flatnonzero((uniform >= np.roll(uniform, 1)) & (uniform >= np.roll(uniform, -1)))
        peaks = np.union1d(peaks, [0, uniform.size - 1])
        cand_f = np.concatenate([f_u[peaks], self.extra])
        cand_v = np.concatenate([uniform[peaks], extra])
        bad = mu * cand_v > 1.0 + _CUT_TOL
        if not bad.any():
            return np.zeros((0, self.n_taps), complex)
        order = np.argsort(cand_v[bad])[::-1][:n_max]
        return _basis(self.plant, cand_f[bad][order], self.fs, self.n_taps)

    def peak(self, q: np.ndarray) -> float:
        uniform, extra = self.abs_s(q)
        return float(max(uniform.max(), extra.max() if extra.size else 0.0))


def _margin_solve(
    problem: _Problem,
    sgrid: _SGrid,
    mu: float,
    R: np.ndarray,
    r: np.ndarray,
    n_taps: int,
    q_start: np.ndarray,
    whitened: bool = False,
) -> tuple[np.ndarray, int]:
    """Cutting planes: impose the margin at the worst grid points until it holds everywhere.

    The first problem has the cones at the worst violators of the unconstrained optimum
    ``q_start``; each round adds the local maxima of ``|S|`` on the fine constraint grid that
    violate the margin. Each solve is a relaxation of the problem on the whole constraint
    grid; the first whose solution meets the margin on it (to ``_CUT_TOL``) solves it. Returns
    ``q`` and the number of solves.
    """
    cuts = np.zeros((0, n_taps), complex)
    q = q_start
    for it in range(_MAX_ROUNDS + 1):
        new = sgrid.cut_rows(q, mu, _CUTS_PER_ROUND)
        if new.shape[0] == 0:
            return q, it
        cuts = np.vstack([cuts, new])
        problem.set_cuts(cuts, mu)
        q = problem.solve(R, r, whitened)
    raise RuntimeError(
        f"the margin still fails on the constraint grid after {_MAX_ROUNDS} cutting-plane "
        f"rounds ({cuts.shape[0]} constraint points; max mu |S| = {mu * sgrid.peak(q):.6g})"
    )


def _qr_least_squares(M: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, U^T y)`` of the thin QR factorisation ``M = U R``, without forming ``U``.

    The triangular factor of the augmented matrix ``[M, y]`` is ``[[R, U^T y], [0, rho]]``
    (Householder reflections act on the columns one at a time), so one ``geqrf`` gives both;
    building ``U`` (``orgqr``) and multiplying by it cost twice as much again (2.9x in all,
    measured on 4,400 x 256). ``R`` has ``min(rows, columns)`` rows, as ``mode="reduced"``.
    """
    k = min(M.shape)
    Ra = np.linalg.qr(np.column_stack([M, y]), mode="r")
    return np.ascontiguousarray(Ra[:k, :-1]), np.array(Ra[:k, -1])


def _gram_terms(
    cos: np.ndarray, sin: np.ndarray, g: np.ndarray, wp: np.ndarray, wpt: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """First column ``t`` of the Toeplitz Gram matrix ``M^T M`` and the vector ``M^T y``.

    ``cos`` and ``sin`` are ``cos(k theta_j)`` and ``sin(k theta_j)``, ``theta = 2 pi f / fs``
    on the objective grid, shape ``(n_taps, n_freqs)`` (one pair per call); ``g`` the plant
    there, ``wp = w P`` (trapezoid weight times disturbance plus noise) and ``wpt = w P psd /
    P``, shape ``(n_freqs,)``. Returns ``t_m = sum_j wp_j |g_j|^2 cos(m theta_j)`` and
    ``(M^T y)_k = sum_j wpt_j Re(g_j e^{-i k theta_j})``, each ``(n_taps,)``. One mode at a
    time (three matrix-vector products, about 0.5 ms at 256 taps and 2,061 frequencies): a
    product over the modes of a call would be 7x faster but its rounding would depend on which
    modes share the call, and a mode's bound must not depend on the chunking.
    """
    t = cos @ (wp * (g.real**2 + g.imag**2))
    mty = cos @ (wpt * g.real) + sin @ (wpt * g.imag)
    return t, mty


def _gram_least_squares(t: np.ndarray, mty: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(R, r)`` with ``R^T R = toeplitz(t)`` (Cholesky) and ``R^T r = mty``, or None.

    None when the Gram matrix is not numerically positive definite or its Cholesky factor's
    estimated condition number (``dtrcon``, 1-norm) exceeds ``_GRAM_MAX_COND``: the caller
    then factors ``M`` itself (:func:`_qr_least_squares`).
    """
    try:
        R = sla.cholesky(sla.toeplitz(t), lower=False, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    rcond, info = sla.lapack.dtrcon(R, norm="1", uplo="U", diag="N")
    if info != 0 or not rcond * _GRAM_MAX_COND >= 1.0:  # also a nan rcond
        return None
    return R, sla.solve_triangular(R, mty, trans="T", check_finite=False)


def _powers(f: np.ndarray, fs: float, n_taps: int) -> tuple[np.ndarray, np.ndarray]:
    """``cos(k theta_j)`` and ``sin(k theta_j)``, ``theta = 2 pi f / fs``, ``k < n_taps``:
    shape ``(n_taps, f.size)`` each (``z^-k = cos - i sin`` on the circle; each entry from its
    own phase: 5x faster than complex powers of ``z^-1``, and no error growing with ``k``)."""
    phase = np.outer(np.arange(n_taps), 2.0 * np.pi * f / fs)
    return np.cos(phase), np.sin(phase)


def _basis(plant: object, f: np.ndarray, fs: float, n_taps: int) -> np.ndarray:
    """``a = G(f) [1, z^-1, ..., z^-(n_taps-1)]``, complex, shape ``(f.size, n_taps)``."""
    g = frequency_response(plant, f, fs)
    cos, sin = _powers(f, fs, n_taps)
    return g[:, None] * (cos.T - 1j * sin.T)


def _objective_grid(freqs: np.ndarray, fs: float, degree: int) -> np.ndarray:
    """``freqs`` itself if it has ``_OBJECTIVE_PER_DEGREE`` intervals per degree of ``S``
    (no interval wider than ``fs / (2 _OBJECTIVE_PER_DEGREE degree)``), else ``freqs`` with
    every interval wider than the constraint grid's spacing split into equal parts.

    The refined grid is the same for every ``n_taps`` up to about ``_MIN_CONSTRAINT / 2``
    taps, so refined bounds of different FIR lengths share one quadrature and stay
    non-increasing in ``n_taps``.
    """
    n_needed = _OBJECTIVE_PER_DEGREE * max(degree, 1)
    gaps = np.diff(freqs)
    if gaps.size == 0 or gaps.max() <= fs / (2.0 * n_needed) * (1 + 1e-9):
        return freqs
    h = fs / (2.0 * max(n_needed, _MIN_CONSTRAINT))
    parts = [freqs[:1]]
    for lo, hi, gap in zip(freqs[:-1], freqs[1:], gaps, strict=True):
        n = max(int(np.ceil(gap / h - 1e-9)), 1)
        parts.append(np.linspace(lo, hi, n + 1)[1:])
    return np.concatenate(parts)


def _trapezoid_weights(f: np.ndarray) -> np.ndarray:
    t = np.zeros_like(f)
    df = np.diff(f)
    t[:-1] += df / 2
    t[1:] += df / 2
    return t


def _plant_polynomials(plant: control.TransferFunction) -> tuple[np.ndarray, np.ndarray]:
    """``(B, A)`` of a stable TF plant in powers of ``z^-1``; raises if it is unstable."""
    b, a = z_inverse_coefficients(plant)
    a_trim = np.trim_zeros(a, "b")
    if a_trim.size > 1:
        poles = np.roots(a_trim)
        if np.max(np.abs(poles)) >= 1.0:
            raise ValueError(
                "plant must be stable (Youla parametrisation K = Q / (1 - G Q)), got a pole of "
                f"modulus {np.max(np.abs(poles))!r}"
            )
    return b, a


def constrained_bound(
    plant: control.TransferFunction,
    freqs: object,
    psd: object,
    noise_psd: object = 0.0,
    modulus_margin: float = 0.5,
    *,
    n_taps: int = 128,
    n_constraint: int | None = None,
    raise_on_failure: bool = True,
    fs: float | None = None,
) -> ConstrainedBound:
    r"""Lowest residual variance of a stabilising linear controller with a modulus margin.

    Per mode, over FIR Youla parameters ``Q`` of ``n_taps`` taps (``K = Q / (1 - G Q)``,
    ``S = 1 - G Q``, ``T = G Q``), solves the convex SOCP

    .. math::

        \min_Q \int_0^{f_s/2} \left(|S|^2 \Phi_d + |T|^2 \Phi_n\right) df
        \quad \text{s.t.} \quad |S(f_j)| \le 1/\mu \ \text{on the constraint grid}

    (Clarabel, given the problem directly; cutting planes: module docstring). The integral is
    the trapezoid on ``freqs``, exactly the residual of
    :func:`aocontrol.analysis.residual_variance` for the returned controllers, when ``freqs``
    resolves ``S`` (no interval wider than ``fs / (4 L)``, ``L`` about ``n_taps``); otherwise
    on ``freqs`` refined to ``fs / 4096``, the PSDs interpolated linearly
    (:attr:`ConstrainedBound.objective_freqs`; module docstring: a coarse grid let a long FIR
    fit between its points). The closed loop is stable by construction. ``modulus_margin = 0``
    drops the constraint (FIR Wiener filter; the limit :func:`wiener_bound` is reached as
    ``n_taps`` grows).

    What it bounds, and how well:

    * The FIR class grows with ``n_taps`` (nested), so on one objective grid the value is
      non-increasing in ``n_taps`` and converges to the infimum over all stable ``Q``: check
      convergence by doubling ``n_taps`` (a resonance of damping ``z`` at ``f0`` needs
      ``n_taps >> fs / (2 pi z f0)``).
    * The margin is imposed on a grid only (a relaxation: the value is a lower bound for the
      FIR class with the margin on the whole axis). The result reports the margin verified
      on an 8x denser grid and, for an FIR plant such as :func:`aocontrol.loop_plant`, a
      margin certified on the whole axis (Bernstein's inequality).
    * A controller verified to meet the margin (e.g. :func:`aocontrol.synthesis.datadriven`)
      cannot do better on the same grid, up to the FIR truncation and the grid relaxation.

    Parameters
    ----------
    plant : control.TransferFunction
        Stable discrete SISO plant (command to measurement), e.g. :func:`aocontrol.loop_plant`.
        A measured plant (``control.FRD``) is refused: the controller ``K`` is built from the
        plant's polynomials.
    freqs : array_like, shape (n_freqs,)
        Strictly increasing grid in [0, fs/2] [Hz] that resolves the PSDs (log-spaced at low
        frequency for turbulent modes); refined where it does not resolve ``S`` (above).
    psd : array_like, shape (n_freqs,) or (n_modes, n_freqs)
        Disturbance PSD, one-sided [units^2/Hz].
    noise_psd : float or array_like, default 0.0
        Measurement-noise PSD, one-sided [units^2/Hz]: scalar (white), like ``psd``, or one
        white level per mode ``(n_modes,)``.
    modulus_margin : float, default 0.5
        Required ``min |1 + G K|`` in [0, 1] (``||S||_inf <= 1 / modulus_margin``; 0: none).
        Every ``mu <= 1`` is feasible (``Q = 0``, ``S = 1``).
    n_taps : int, default 128
        FIR length of ``Q`` (>= 1).
    n_constraint : int, optional
        Points of the (linear) constraint grid over [0, fs/2]; default ``max(2048, 16 L)``
        with ``L`` the degree of ``S`` for an FIR plant, a few more when that makes the number
        of intervals a fast FFT length (11-smooth).
    raise_on_failure : bool, default True
        Raise :class:`ConstrainedBoundError` (holding every mode) if a mode fails; if False,
        return the result with ``ok == False`` and ``nan`` for the failed modes.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.

    Returns
    -------
    ConstrainedBound
        ``.variance`` (shape ``(n_modes,)``, units^2) is the bound; ``.q``, ``.controller``,
        ``.verified_margin``, ``.certified_margin`` and ``.unconstrained`` describe it.

    Raises
    ------
    TypeError
        An FRD or non-LTI plant.
    ValueError
        Bad grid, PSDs, margin or ``n_taps`` (named in the message), or an unstable plant.
    ConstrainedBoundError
        Some modes failed in the solver (``error.result`` keeps the others).

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> fs, a = 1000.0, 0.9
    >>> f = np.linspace(0.0, fs / 2, 2001)
    >>> ar1 = 2 / fs / np.abs(1 - a * np.exp(-2j * np.pi * f / fs)) ** 2  # s_w^2 = 1
    >>> # Two-frame delay: the Wiener predictor Q = a^2 gives |S| <= 1 + a^2 = 1.81 < 2, so
    >>> # with a margin of 0.5 the bound is the prediction error 1 + a^2.
    >>> res = constrained_bound(loop_plant(fs, 1.0), f, ar1, modulus_margin=0.5, n_taps=4)
    >>> round(float(res.variance[0]), 3)
    1.81
    """
    if isinstance(plant, control.FRD):
        raise TypeError(
            "plant must be a control.TransferFunction: constrained_bound builds the controller "
            "K = Q / (1 - G Q) from the plant's polynomials; a measured plant (FRD) is not "
            "supported (fit a transfer function, e.g. loop_plant, first)"
        )
    fs_ = plant_fs(plant, fs)
    freqs = check_frequency_grid("freqs", freqs, fs_)
    if freqs.size < 2:
        raise ValueError(f"freqs must have at least 2 points to integrate a PSD, got {freqs.size}")
    psd2, noise2, _ = mode_psds(psd, noise_psd, freqs.size)
    mu = check_in_range("modulus_margin", modulus_margin, 0.0, 1.0, high_inclusive=True)
    n_taps = check_int("n_taps", n_taps, minimum=1)
    bg, ag = _plant_polynomials(plant)
    fir_plant = np.trim_zeros(ag, "b").size == 1
    degree = n_taps - 1 + np.trim_zeros(bg, "b").size - 1 if fir_plant else None
    if n_constraint is None:
        n_con = max(_MIN_CONSTRAINT, _CONSTRAINT_PER_DEGREE * (degree or (n_taps + 8)))
        n_con = next_fast_len(n_con - 1) + 1
    else:
        n_con = check_int("n_constraint", n_constraint, minimum=2)
    con = _SGrid(plant, fs_, n_con - 1, freqs, n_taps)
    n_uniform = _VERIFY_FACTOR * (n_con - 1)
    ver = _SGrid(plant, fs_, n_uniform, freqs, n_taps, a_extra=con.a_extra)
    problem = _Problem(mu, n_taps)
    f_obj = _objective_grid(freqs, fs_, degree or (n_taps + 8))
    g_obj = frequency_response(plant, f_obj, fs_)
    cos, sin = _powers(f_obj, fs_, n_taps)  # (n_taps, n_freqs): the basis and the Gram sums
    a_obj = con.a_extra if f_obj is freqs else g_obj[:, None] * (cos.T - 1j * sin.T)
    if f_obj is not freqs:
        psd2 = np.array([np.interp(f_obj, freqs, row) for row in psd2])
        noise2 = np.array([np.interp(f_obj, freqs, row) for row in noise2])
        logger.info(
            "constrained_bound: the grid of %d points does not resolve S (degree %d); the "
            "objective uses %d points, the PSDs interpolated linearly",
            freqs.size,
            degree or (n_taps + 8),
            f_obj.size,
        )
    w = _trapezoid_weights(f_obj)
    m_rows = np.vstack([a_obj.real, a_obj.imag])

    n_modes = psd2.shape[0]
    variance = np.full(n_modes, np.nan)
    unconstrained = np.full(n_modes, np.nan)
    q_all = np.zeros((n_modes, n_taps))
    verified = np.full(n_modes, np.nan)
    certified = np.full(n_modes, np.nan)
    ok = np.zeros(n_modes, dtype=bool)
    messages = [""] * n_modes
    solves = np.zeros(n_modes, dtype=int)
    for i in range(n_modes):
        sd, sn = psd2[i], noise2[i]
        total = sd + sn
        with np.errstate(divide="ignore", invalid="ignore"):
            target = np.where(total > 0, sd / total, 0.0)
            floor_term = float(np.sum(w * np.where(total > 0, sd * sn / total, 0.0)))
        wp = w * total

        def value(
            q: np.ndarray, wp: np.ndarray = wp, t: np.ndarray = target, c: float = floor_term
        ):
            # ||y - M q||^2 + c from M's rows: sum_j w_j P_j |psd_j / P_j - a_j q|^2 + c.
            aq = m_rows @ q
            return float(np.sum(wp * ((t - aq[: t.size]) ** 2 + aq[t.size :] ** 2)) + c)

        try:
            factors = _gram_least_squares(*_gram_terms(cos, sin, g_obj, wp, wp * target))
            if factors is not None:
                R, r = factors
                q_unc = sla.solve_triangular(R, r, check_finite=False)
            else:
                sw = np.sqrt(wp)
                M = np.concatenate([sw, sw])[:, None] * m_rows
                R, r = _qr_least_squares(M, np.concatenate([sw * target, np.zeros_like(sw)]))
                if R.shape[0] < n_taps:  # fewer rows than taps: the same objective, square R
                    R = np.vstack([R, np.zeros((n_taps - R.shape[0], n_taps))])
                    r = np.concatenate([r, np.zeros(n_taps - r.size)])
                q_unc = np.linalg.lstsq(R, r, rcond=None)[0]  # R may be singular here
            unconstrained[i] = value(q_unc)
            if mu == 0:
                q = q_unc
            else:
                scale = np.sqrt(
                    max(unconstrained[i], _SCALE_FLOOR * float(np.sum(w * total)), 1e-300)
                )
                q, solves[i] = _margin_solve(
                    problem, con, mu, R / scale, r / scale, n_taps, q_unc, factors is not None
                )
        except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:
            messages[i] = f"{exc}"
            logger.warning("constrained_bound: mode %d failed: %s", i, exc)
            continue
        q_all[i] = q
        variance[i] = value(q)
        peak = ver.peak(q)
        verified[i] = 1.0 / peak
        if fir_plant:
            slack = 1.0 - np.pi * degree / (2 * n_uniform)
            certified[i] = slack / peak if slack > 0 else 0.0
        ok[i] = True
    result = ConstrainedBound(
        variance=variance,
        unconstrained=unconstrained,
        q=q_all,
        verified_margin=verified,
        certified_margin=certified,
        ok=ok,
        messages=tuple(messages),
        modulus_margin=mu,
        n_taps=n_taps,
        fs=fs_,
        constraint_freqs=np.union1d(con.freqs_uniform, freqs),
        verify_freqs=np.union1d(ver.freqs_uniform, freqs),
        solves=solves,
        plant_coefficients=(bg, ag),
        objective_freqs=f_obj,
    )
    if raise_on_failure and not ok.all():
        raise ConstrainedBoundError({i: messages[i] for i in np.flatnonzero(~ok).tolist()}, result)
    return result
