"""Multi-mode linear prediction from telemetry (EOF / LMMSE), certified before use.

A modal controller predicts each mode from its own past. Frozen-flow turbulence moves the
phase across the pupil, so the past of one mode predicts another: a multi-mode predictor
(Guyon & Males 2017, "empirical orthogonal functions") uses the last ``h`` pseudo-open-loop
(POL) frames of every mode for every command. This module trains one from telemetry and
returns it as a :class:`~aocontrol.controllers.MultiModeBank` with its certificate.

Loop (conventions of :mod:`aocontrol.plant`): ``G = z^-1 ((1 - f) z^-k + f z^-(k+1))``,
residual ``e[t] = d[t] - (1 - f) u[t-k] - f u[t-k-1]``, POL ``p[t] = m[t] + (G u)[t] =
d[t-1] + n[t]``. The controller commands ``u[s] = sum_{j < h} A_j p[s-j]``, so

    e[t] = d[t] - sum_j A_j q[t-k-j],       q[s] = (1 - f) p[s] + f p[s-1],

linear in the ``A_j``: the fractional latency is handled exactly as the plant applies it.
Training minimises, over the frames ``t`` of the record,

    sum_t || p[t+1] - sum_j A_j q[t-k-j] ||^2  +  lam e ||A||_F^2,   A = [A_0 | ... | A_{h-1}]

with ``e = trace(G) / (n h)`` the regressors' mean energy over the data (``G`` their Gram
matrix): ``lam`` is dimensionless, and the penalty is what white noise of variance
``lam x`` (the mean POL variance per mode) added to every regressor would cost, in the
common unit of the modal coefficients. It bounds the predictor's gain in every direction
alike, which is what the multivariable margin needs (a penalty scaled per regressor, ridge
on standardised regressors, was measured much worse: ``docs/benchmarks.md``).

Integral action (``integral_action=True``, the default): the minimum is taken subject to

    F(1) = sum_j A_j = I,

so ``S(1) = I - G(1) F(1) = 0`` for every weight: the loop rejects a constant disturbance
exactly (``S`` has a zero at ``z = 1``), and the prediction is unbiased whatever the
disturbance's mean (the condition of "ordinary kriging": the weights of an unbiased linear
predictor under an unknown constant mean sum to one). Without it (``False``) least squares
gives the best predictor of the record as if it were zero-mean and stationary; its DC gain
``F(1)`` falls below ``I`` where the record has little power at low frequency or much
noise, and the loop keeps a static error ``(I - F(1)) d`` on any offset, drift or slow
transient the record did not hold (a loop converging upstream, seeing changing over
minutes). A record of ``T`` frames holds a few independent samples of its frequencies
below a few ``fs / T``, where turbulence has most of its power: integral action is the
default, ``False`` the plain LMMSE predictor for a disturbance known to be zero-mean and
stationary (it reaches a VAR or AR process's prediction error, which the constraint
misses by its price: ``docs/benchmarks.md``).

The constraint is solved exactly by a change of variables: ``A = A_mean + X (U x I_n)^T``
with ``A_mean = [I | ... | I] / h`` (the mean of the last ``h`` frames, the smallest
``||A||_F`` with ``F(1) = I``), ``U`` of shape ``(h, h - 1)`` an orthonormal basis of the
zero-sum vectors and ``X`` of shape ``(n, n (h - 1))`` free. ``A_mean`` is orthogonal to
every admissible ``A - A_mean``, so ``||A||_F^2 = ||A_mean||_F^2 + ||X||_F^2``: the problem
is a ridge regression in ``X`` (same weight ``lam e``) of the target ``p[t+1] - A_mean
z[t]`` on the regressors ``(U x I_n)^T z[t]``, ``z[t] = [q[t-k]; ...; q[t-k-h+1]]`` (the
zero-sum combinations of the last ``h`` frames, blind to a constant); its Gram matrix and
cross terms follow from those of ``z`` by the same small transformation. ``lam -> inf``
gives ``A -> A_mean``. With ``history=1`` nothing is free: ``A_0 = I``, persistence.

Noise, honestly. The target ``p[t+1] = d[t] + n[t+1]`` and the regressors carry the
measurement noise, as on an instrument. The noise ``n[t+1]`` is white and later than every
regressor (``q[t-k-j]`` uses ``p`` up to frame ``t``), so it is uncorrelated with them: the
least-squares solution is the best linear predictor of ``d[t]`` itself (the target's noise
adds a constant to the cost), and the noise in the regressors is what the controller will
see in the loop, so the fit weighs it exactly as it will act (the LMMSE predictor under
noisy inputs). No noise model is needed. The oracle trained on the true disturbance (pass
``p = z^-1 d`` to :func:`eof_from_pseudo_open_loop`) is a diagnostic, not an instrument's
design.

Choice of ``lam`` (when not given): the last ``validation_fraction`` (default 20 %) of the
frames is held back; the predictor is fitted on the first part for every ``lam`` of
:data:`REGULARISATION_GRID` and ``lam`` is the one with the smallest residual on the held-back
part (the future of the training data, so a drift counts against overfitting). Every
weight comes from one eigendecomposition of the scaled Gram matrix ``G / e = V diag(s) V^T``
(with integral action, that of the free variables ``X``): ``A(lam) = (B / e) V diag(1 / (s +
lam)) V^T`` (``B`` the cross terms) and the held-back residual is a quadratic form in ``1 /
(s + lam)``. The predictor is then refitted on all frames with that ``lam`` (a Cholesky
solve): 25 % more data for the final taps; the weight chosen on 80 % is then, if anything,
slightly too large (a safe bias).

Certificate, never skipped: the controller's loop is certified by
:func:`aocontrol.analysis.multimode_certificate` (stability structural and checked on the
real-time path, multivariable margin ``min sigma_min(I + G K)`` bounded over the whole
circle). Below the required margin, ``lam`` is multiplied by 4 and the predictor refitted
until it is met, then the last step is bisected to a factor ~1.19; the result says which
weight and margin were certified. This ends when the limit ``lam -> inf`` meets the
requirement, so the limit is certified first whenever the weight chosen on data fails:

* without integral action the limit is ``F = 0``, ``S = I``, margin 1 (an open loop);
* with it the limit is the mean of the last ``h`` frames, ``F = I M_h``,
  ``M_h(z) = (1 + z^-1 + ... + z^-(h-1)) / h``: ``S = (1 - G M_h) I``. For ``h >= 2``,
  ``|M_h| < 1`` off ``z = 1`` and ``|G| <= 1``, so ``max |S| < 2`` and the margin is above
  1/2 at every latency (at latency 0.83, ``h = 2, 5, 20``: 0.579, 0.654, 0.746; at an
  integer latency it falls as the latency grows, latency 3 and ``h = 2``: 0.515). With
  ``h = 1`` (persistence, ``S = 1 - G``) it is exactly 1/2 at an integer latency: a
  requirement of 1/2 cannot be certified there.

A limit below the requirement ends the search at once with
:class:`EOFNotCertifiedError` (a longer history, a lower margin or ``integral_action=False``
are the ways out). The margin costs residual: ``S = I - G F`` with a short FIR ``F`` cannot
shape ``|S|`` as an IIR controller can, so a margin of 0.5 behind a two-frame delay costs
far more here than it costs the data-driven modal design; and a short FIR with ``F(1) = I``
cannot average the noise over as many frames as a low-gain integrator does (its white-noise
gain is at least ``1 / h``): in a noise-limited loop the history must be long
(measurements: ``benchmarks/bench_eof.py``, ``docs/benchmarks.md``).

Cost (``n`` modes, history ``h``, ``T`` frames, ``N = n h``): the Gram matrix from ``h``
products ``n x T x n`` (its block Toeplitz structure: the other blocks by rank-one
updates) and ``h`` for the cross terms; with integral action their transformation to the
free variables, ``O(h^3 n^2)``; one ``N x N`` eigendecomposition and two ``N^3``
products for the validation scan; one Cholesky per refit; the certificate's ``O(n^3)``
per frequency. Memory ``O(N^2)``; the ``T x N`` regressor matrix is never formed.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from aocontrol._validation import (
    check_finite_array,
    check_in_range,
    check_instance,
    check_int,
    check_nonnegative,
    check_positive,
)
from aocontrol.analysis import MultiModeCertificate, multimode_certificate
from aocontrol.controllers import MultiModeBank
from aocontrol.plant import loop_plant, split_latency
from aocontrol.synthesis._telemetry import LoopTelemetry, pseudo_open_loop

__all__ = [
    "EOFNotCertifiedError",
    "EOFResult",
    "REGULARISATION_GRID",
    "eof_from_pseudo_open_loop",
    "eof_min_frames",
    "eof_predictor",
]

logger = logging.getLogger(__name__)

#: Tikhonov weights scanned on the held-back telemetry: 10^-10 to 10^2, four per decade
#: (relative to the regressors' mean energy; 0 is left out, singular for noise-free
#: telemetry).
REGULARISATION_GRID = np.logspace(-10.0, 2.0, 49)
REGULARISATION_GRID.setflags(write=False)
# Below the required margin the weight is multiplied by this, at most this many times
# (1e-10 * 4^40 ~ 1e14: F is then ~0 and the margin ~1), then the last factor is bisected
# this many times in log(lam) (see _Certifier).
_RAISE_FACTOR, _MAX_RAISES, _BISECTIONS = 4.0, 40, 3


class EOFNotCertifiedError(RuntimeError):
    """No regularisation weight gave a predictor whose loop is certified (never run)."""


@dataclass(frozen=True, eq=False)
class EOFResult:
    """A trained multi-mode predictor, its certificate and how its weight was chosen.

    Attributes
    ----------
    controller : MultiModeBank
        The certified controller (taps ``A_j``, latency model, rate).
    certificate : MultiModeCertificate
        Its loop's certificate (stability, margin bound, required margin).
    regularisation : float
        Tikhonov weight of ``controller`` (relative to the regressors' mean energy); 0 when
        nothing was free (``history=1`` with integral action).
    validation_regularisation : float or None
        The weight the held-back telemetry chose (``None`` when it was given or nothing
        was free); ``regularisation`` is larger when the margin required more.
    regularisation_grid : numpy.ndarray, shape (n_grid,)
        Weights scanned (empty when the weight was given).
    validation_residual : numpy.ndarray, shape (n_grid,)
        Mean-square error on the held-back frames per weight, summed over modes
        [units^2]: ``E||p[t+1] - prediction||^2``, the disturbance's prediction error plus
        the noise variance of the target once.
    history : int
        POL frames per command, ``h``.
    latency_frames : float
        Latency beyond the WFS frame of the loop it was trained for [frames].
    n_training_frames : int
        Training equations (frames ``t``) of the final fit (all usable frames).
    n_validation_frames : int
        Equations held back for the choice of the weight (0 when it was given).
    fit_seconds : float
        Wall-clock time of the training (Gram matrices, scan, refits) [s], certificates
        excluded.
    certify_seconds : float
        Wall-clock time of the certificates [s].
    integral_action : bool
        Whether the DC gain was constrained, ``sum_j A_j = I`` (``S(1) = 0``).
    """

    controller: MultiModeBank
    certificate: MultiModeCertificate
    regularisation: float
    validation_regularisation: float | None
    regularisation_grid: np.ndarray
    validation_residual: np.ndarray
    history: int
    latency_frames: float
    n_training_frames: int
    n_validation_frames: int
    fit_seconds: float
    certify_seconds: float
    integral_action: bool


# -- least squares with the Gram matrix's block structure ----------------------------------
@dataclass
class _Normal:
    """Normal equations of the rows ``s`` in ``[s0, s1]``: ``G = Z^T Z``, ``B = Y^T Z``,
    ``yy = sum ||y||^2`` (``Z`` rows ``[q[s], q[s-1], ..., q[s-h+1]]``, ``y = p[s+k+1]``)."""

    gram: np.ndarray  # (N, N)
    cross: np.ndarray  # (n, N)
    yy: float
    rows: int

    def __add__(self, other: _Normal) -> _Normal:
        return _Normal(self.gram + other.gram, self.cross + other.cross, self.yy + other.yy,
                       self.rows + other.rows)  # fmt: skip


def _normal_equations(p: np.ndarray, q: np.ndarray, h: int, k0: int, s0: int, s1: int):
    """:class:`_Normal` of rows ``s0..s1`` (inclusive; ``s0 >= h``, ``s1 + k0 + 1 < T``).

    Block ``(i, j)`` of ``G`` is ``sum_s q[s-i] q[s-j]^T``; the first block row takes ``h``
    products, and ``G_{i+1, j+1} = G_{ij} + q[s0-1-i] q[s0-1-j]^T - q[s1-i] q[s1-j]^T``
    (the same sum over a window one frame earlier) gives the rest.
    """
    n = p.shape[1]
    N = n * h
    rows = s1 - s0 + 1
    y = p[s0 + k0 + 1 : s1 + k0 + 2]
    gram = np.empty((N, N))
    cross = np.empty((n, N))
    q0 = q[s0 : s1 + 1]
    for j in range(h):
        qj = q[s0 - j : s1 + 1 - j]
        gram[:n, j * n : (j + 1) * n] = q0.T @ qj
        cross[:, j * n : (j + 1) * n] = y.T @ qj
    for i in range(h - 1):
        for j in range(i, h - 1):
            blk = gram[i * n : (i + 1) * n, j * n : (j + 1) * n]
            upd = np.outer(q[s0 - 1 - i], q[s0 - 1 - j]) - np.outer(q[s1 - i], q[s1 - j])
            gram[(i + 1) * n : (i + 2) * n, (j + 1) * n : (j + 2) * n] = blk + upd
    for i in range(1, h):  # lower blocks by symmetry
        for j in range(i):
            gram[i * n : (i + 1) * n, j * n : (j + 1) * n] = gram[
                j * n : (j + 1) * n, i * n : (i + 1) * n
            ].T
    return _Normal(gram, cross, float(np.einsum("ij,ij->", y, y)), rows)


def _energy(gram: np.ndarray) -> float:
    """Mean regressor energy ``trace(G) / N`` (1 for an all-zero record)."""
    e = float(np.trace(gram)) / gram.shape[0]
    return e if e > 0 else 1.0


@dataclass(frozen=True)
class _Reduced:
    """Normal equations in the free variables: ``gram`` (M, M), ``cross`` (n, M), ``yy``,
    ``rows``, and ``scale`` the mean energy ``e`` of the original regressors ``z``."""

    gram: np.ndarray
    cross: np.ndarray
    yy: float
    rows: int
    scale: float


class _Parametrisation:
    """The taps as ``A = A_fixed + X T^T`` with ``X`` free (module docstring).

    Free taps: ``A_fixed = 0``, ``T = I``. Integral action: ``A_fixed = A_mean``,
    ``T = U x I_n`` with ``U`` (h, h - 1) orthonormal, its columns orthogonal to ones.
    """

    def __init__(self, n: int, h: int, integral_action: bool) -> None:
        self.n, self.h, self.integral_action = n, h, integral_action
        if integral_action:
            # Orthonormal basis of the zero-sum vectors of length h (an empty one for h = 1).
            self.basis = scipy.linalg.null_space(np.ones((1, h))) if h > 1 else np.zeros((1, 0))
        else:
            self.basis = None

    @property
    def n_free(self) -> int:
        """Free unknowns per mode, ``M``."""
        return self.n * (self.h if self.basis is None else self.h - 1)

    def reduce(self, normal: _Normal) -> _Reduced:
        """The normal equations of ``X``: ``T^T G T``, ``(B - A_fixed G) T`` and
        ``sum ||y - A_fixed z||^2``."""
        scale = _energy(normal.gram)
        if self.basis is None:
            return _Reduced(normal.gram, normal.cross, normal.yy, normal.rows, scale)
        n, h, U = self.n, self.h, self.basis
        g4 = normal.gram.reshape(h, n, h, n)
        c3 = normal.cross.reshape(n, h, n)
        # A_mean G = (1/h) sum_j G[j, :], a row of blocks; A_mean B^T's trace and
        # A_mean G A_mean^T's trace for the target's energy.
        mean_g = g4.sum(axis=0).reshape(n, h * n) / h
        yy = (normal.yy - 2.0 * float(np.trace(c3.sum(axis=1))) / h
              + float(np.einsum("jxlx->", g4)) / h**2)  # fmt: skip
        gram = np.tensordot(np.tensordot(U, g4, axes=(0, 0)), U, axes=(2, 0))  # (a, x, z, b)
        gram = gram.transpose(0, 1, 3, 2).reshape(self.n_free, self.n_free)
        cross = np.tensordot((normal.cross - mean_g).reshape(n, h, n), U, axes=(1, 0))
        cross = cross.transpose(0, 2, 1).reshape(n, self.n_free)
        return _Reduced(gram, cross, yy, normal.rows, scale)

    def taps(self, X: np.ndarray | None) -> np.ndarray:
        """Taps ``A_j``, shape ``(h, n, n)``, of the free variables ``X`` (n, M); ``None``
        for the limit ``lam -> inf`` (``X = 0``)."""
        n, h = self.n, self.h
        if self.basis is None:
            A = np.zeros((n, h, n)) if X is None else X.reshape(n, h, n)
        else:
            A = np.broadcast_to(np.eye(n)[:, None, :] / h, (n, h, n)).copy()
            if X is not None and X.size:
                A += np.tensordot(X.reshape(n, h - 1, n), self.basis, axes=(1, 1)).transpose(
                    0, 2, 1
                )
        return np.ascontiguousarray(A.transpose(1, 0, 2))


def _solve(reduced: _Reduced, lam: float) -> np.ndarray:
    """``X`` minimising the regularised cost (module docstring), shape ``(n, M)``."""
    if reduced.gram.shape[0] == 0:
        return reduced.cross
    g = reduced.gram / reduced.scale
    g[np.diag_indices_from(g)] += lam
    try:
        factor = scipy.linalg.cho_factor(g, lower=False, check_finite=False)
    except np.linalg.LinAlgError as exc:
        raise ValueError(
            f"regularisation={lam!r} leaves the regressors' Gram matrix singular (telemetry "
            "without enough independent frames, e.g. noise-free and smooth): give "
            "regularisation > 0 or None (chosen on held-back telemetry)"
        ) from exc
    return scipy.linalg.cho_solve(factor, (reduced.cross / reduced.scale).T, check_finite=False).T


def _scan(train: _Reduced, valid: _Reduced, grid: np.ndarray) -> np.ndarray:
    """Held-back residual ``sum ||y - X(lam) r||^2 / rows`` for every weight of ``grid``
    (``y`` and ``r`` the target and the regressors of the free variables ``X``).

    With ``G / e = V diag(s) V^T`` (``e`` the training regressors' mean energy) and
    ``M = (B / e) V``: ``X(lam) = M diag(c) V^T``, ``c = 1 / (s + lam)``, and the held-back
    residual is ``yy - 2 c . a + c^T (W o K) c`` with ``a_k = sum_i M_ik (Bv V)_ik``,
    ``W = V^T Gv V`` and ``K = M^T M``.
    """
    s, V = np.linalg.eigh(train.gram / train.scale)
    s = np.maximum(s, 0.0)
    M = (train.cross / train.scale) @ V
    a = np.einsum("ik,ik->k", M, valid.cross @ V)
    WK = (V.T @ valid.gram @ V) * (M.T @ M)
    out = np.empty(grid.size)
    for i, lam in enumerate(grid):
        c = 1.0 / (s + lam)
        out[i] = valid.yy - 2.0 * c @ a + c @ WK @ c
    return out / valid.rows


class _Certifier:
    """Fits at given weights and certifies them; finds a small weight whose loop is certified.

    From the weight ``lam`` chosen on data: if its loop is not certified, the limit
    ``lam -> inf`` is certified (its verdict only); if it fails too, no weight is searched
    for. Else the weight is multiplied by 4 (from at least the grid's smallest) until the
    loop is certified, then the last factor of 4 is bisected in ``log(lam)`` three times
    (to a factor 4^(1/8) ~ 1.19): the smallest certified weight found is kept. The margin
    need not be monotone in ``lam``; every returned controller is certified whatever the
    path.
    """

    def __init__(self, reduced, param, fs, latency, margin, limit, precision) -> None:
        self.reduced, self.param, self.fs, self.latency = reduced, param, fs, latency
        self.margin, self.limit, self.precision = margin, limit, precision
        self.fit_seconds = self.certify_seconds = 0.0

    def __call__(
        self, lam: float, decide_only: bool = False
    ) -> tuple[MultiModeBank, MultiModeCertificate]:
        t0 = time.perf_counter()
        taps = self.param.taps(None if math.isinf(lam) else _solve(self.reduced, lam))
        t1 = time.perf_counter()
        bank = MultiModeBank(taps, self.fs, self.latency, command_limit=self.limit,
                             precision=self.precision)  # fmt: skip
        cert = multimode_certificate(bank, modulus_margin=self.margin, decide_only=decide_only)
        self.fit_seconds += t1 - t0
        self.certify_seconds += time.perf_counter() - t1
        verdict = "certified" if cert.certified else "refused"
        logger.info("eof: regularisation %.3g, margin bound %.4g (required %.4g): %s", lam,
                    cert.margin, self.margin, verdict)  # fmt: skip
        return bank, cert

    def smallest_certified(self, lam: float) -> tuple[MultiModeBank, MultiModeCertificate, float]:
        bank, cert = self(lam)
        if cert.certified:
            return bank, cert, lam
        limit = self(math.inf, decide_only=True)[1]
        if not limit.certified:
            if not self.param.integral_action:
                what = "zero"
            elif self.param.h == 1:
                what = "persistence, u = p"
            else:
                what = f"the mean of the last {self.param.h} frames"
            raise EOFNotCertifiedError(
                f"the predictor at regularisation {lam:.3g} has margin bound {cert.margin:.4g} "
                f"and its limit for a large regularisation ({what}) at most "
                f"{limit.margin_upper:.4g}, below modulus_margin {self.margin:g}: predictor "
                "refused (a longer history, a lower modulus_margin or integral_action=False)"
            )
        # The search only needs each weight's verdict; the one kept is certified in full.
        low = lam
        high = max(lam * _RAISE_FACTOR, float(REGULARISATION_GRID[0]))
        for _ in range(_MAX_RAISES):
            if self(high, decide_only=True)[1].certified:
                break
            low, high = high, high * _RAISE_FACTOR
        else:
            raise EOFNotCertifiedError(
                f"no regularisation up to {low:.3g} gives a certified loop (margin bound below "
                f"modulus_margin {self.margin:g}); predictor refused"
            )
        low = max(low, float(REGULARISATION_GRID[0]) / _RAISE_FACTOR)
        for _ in range(_BISECTIONS):
            mid = math.sqrt(low * high)
            if self(mid, decide_only=True)[1].certified:
                high = mid
            else:
                low = mid
        bank, cert = self(high)
        if not cert.certified:  # the full certificate decides as decide_only did; a guard
            raise EOFNotCertifiedError(
                f"the predictor at regularisation {high:.3g} passed the search but not its "
                f"full certificate (margin bound {cert.margin:.4g}, required {self.margin:g})"
            )
        return bank, cert, high


def _frames_needed(n: int, h: int, validation: float | None) -> int:
    """Training equations needed: ``n h`` (as many as unknowns per mode), more when a
    fraction is held back."""
    return n * h if validation is None else math.ceil(n * h / (1.0 - validation)) + 1


def eof_min_frames(
    n_modes: int,
    history: int,
    latency_frames: float,
    *,
    validation_fraction: float | None = 0.2,
) -> int:
    """Fewest pseudo-open-loop frames :func:`eof_from_pseudo_open_loop` trains on.

    ``n_modes * history`` training equations (more with a held-back fraction) plus the
    start-up (the first regressors' past and the last target: ``history + k + 1`` frames).
    Enough to train, not to train well: the weight's choice and the predictor improve with
    many times that (``docs/benchmarks.md``).

    Parameters
    ----------
    n_modes : int
        Modes (>= 1).
    history : int
        POL frames per command (>= 1).
    latency_frames : float
        Latency beyond the WFS frame [frames] (>= 0).
    validation_fraction : float or None, default 0.2
        Fraction held back to choose the weight (``None``: the weight is given).

    Returns
    -------
    int

    Examples
    --------
    >>> eof_min_frames(540, 5, 0.83)
    3382
    """
    n = check_int("n_modes", n_modes, minimum=1)
    h = check_int("history", history, minimum=1)
    k0, _ = split_latency(check_nonnegative("latency_frames", latency_frames))
    validation = None
    if validation_fraction is not None:
        validation = check_in_range("validation_fraction", validation_fraction, 0.0, 0.5,
                                    low_inclusive=False, high_inclusive=True)  # fmt: skip
    return _frames_needed(n, h, validation) + h + k0 + 1


def _check_length(
    name: str,
    n_frames: int,
    n: int,
    h: int,
    latency: float,
    validation: float | None,
    start: int,
) -> None:
    """Refuse a record too short to train: ``n h`` training equations (as many as unknowns
    per mode), more when a fraction is held back, plus ``start`` frames (the first
    regressors' past, the last target, and frames dropped before)."""
    needed = _frames_needed(n, h, validation) + start
    if n_frames < needed:
        held = "" if validation is None else f", validation_fraction {validation:g} held back"
        raise ValueError(
            f"{name} has {n_frames} frames; a history-{h} predictor of {n} modes at latency "
            f"{float(latency):g} needs at least {needed} (n_modes * history = {n * h} "
            f"training equations{held}, plus {start} frames of start-up)"
        )


def eof_from_pseudo_open_loop(
    pseudo_open_loop: object,
    fs: float,
    latency_frames: float,
    *,
    history: int = 5,
    regularisation: float | None = None,
    validation_fraction: float = 0.2,
    modulus_margin: float = 0.5,
    integral_action: bool = True,
    command_limit: float | np.ndarray | None = None,
    precision: str = "float32",
    blas_threads: int | None = 1,
) -> EOFResult:
    """Train and certify a multi-mode predictor from a pseudo-open-loop record.

    See the module docstring for the cost, the noise, the choice of the weight and the
    certificate. A diagnostic oracle: ``pseudo_open_loop = z^-1 d`` (the true disturbance
    one frame late, no noise) gives the predictor an instrument could not train.

    Parameters
    ----------
    pseudo_open_loop : array_like, shape (n_frames, n_modes)
        POL ``p = m + G u = z^-1 d + n`` [units], frames along the first axis, all finite.
    fs : float
        Loop rate [Hz].
    latency_frames : float
        RTC latency beyond the one-frame WFS integration [frames], that of the loop the
        controller will run in (:func:`aocontrol.plant.loop_plant`).
    history : int, default 5
        POL frames per command ``h`` (>= 1).
    regularisation : float, optional
        Tikhonov weight ``lam >= 0`` (relative to the regressors' mean energy, module
        docstring); ``None`` (default): chosen on the held-back telemetry.
    validation_fraction : float, default 0.2
        Fraction of the frames held back (the last ones) when ``regularisation`` is
        ``None``, in ``(0, 0.5]``.
    modulus_margin : float, default 0.5
        Required multivariable modulus margin ``min sigma_min(I + G K)``, in ``(0, 1)``.
    integral_action : bool, default True
        Constrain the predictor's DC gain to ``F(1) = sum_j A_j = I``, so ``S(1) = 0``
        whatever the weight (module docstring); ``False``: the free least-squares
        predictor of a zero-mean stationary record. With ``history=1`` and integral action
        the predictor is persistence, ``u = p``, and nothing is fitted.
    command_limit : float or array_like of shape (n_modes,), optional
        The controller's limit on its command (see :class:`MultiModeBank`).
    precision : {"float32", "float64"}, default "float32"
        Precision of the controller's real-time product.
    blas_threads : int or None, default 1
        BLAS threads of the training (``None``: the BLAS's own setting). One by default: on
        a shared machine a second OpenBLAS thread mostly waits (measured, 2 cores at load
        ~3: 540 modes the same 8 s with one or two threads, 100 modes 0.14 s with one and
        7.6 s with two); on a dedicated machine more threads speed the ``N^3`` steps up.

    Returns
    -------
    EOFResult

    Raises
    ------
    ValueError
        ``history < 1``, ``regularisation < 0``, a record with NaN/inf, too few frames
        (the message says how many are needed: ``n_modes * history`` training equations,
        more with a held-back fraction, plus ``history + k + 1`` frames), or a given
        ``regularisation`` that leaves the normal equations singular.
    EOFNotCertifiedError
        If the limit of a large weight (module docstring: the mean of the last ``history``
        frames with integral action) does not meet the required margin while the weight
        chosen on data does not either, or no weight up to ``4^40`` times the chosen one
        meets it.
    """
    p = check_finite_array("pseudo_open_loop", pseudo_open_loop, ndim=2)
    fs = check_positive("fs", fs)
    k0, f = split_latency(latency_frames)
    h = check_int("history", history, minimum=1)
    if regularisation is not None:
        regularisation = check_nonnegative("regularisation", regularisation)
        validation = None
    else:
        validation = check_in_range("validation_fraction", validation_fraction, 0.0, 0.5,
                                    low_inclusive=False, high_inclusive=True)  # fmt: skip
    modulus_margin = check_in_range("modulus_margin", modulus_margin, 0.0, 1.0,
                                    low_inclusive=False)  # fmt: skip
    check_instance("integral_action", integral_action, bool)
    n_frames, n = p.shape
    _check_length("pseudo_open_loop", n_frames, n, h, latency_frames, validation, h + k0 + 1)
    if blas_threads is not None:
        blas_threads = check_int("blas_threads", blas_threads, minimum=1)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=blas_threads, user_api="blas"):
        t_start = time.perf_counter()
        p = np.ascontiguousarray(p, dtype=float)
        q = np.empty_like(p)
        q[0] = (1.0 - f) * p[0]
        q[1:] = (1.0 - f) * p[1:] + f * p[:-1]
        s_first, s_last = h, n_frames - k0 - 2  # rows s: q[s - h + 1 - 1] and p[s + k0 + 1] exist
        grid = np.empty(0)
        scores = np.empty(0)
        chosen = None
        n_valid = 0
        param = _Parametrisation(n, h, integral_action)
        if validation is None or param.n_free == 0:
            # Nothing to choose: the weight is given, or nothing is free (persistence).
            normal = _normal_equations(p, q, h, k0, s_first, s_last)
            lam = 0.0 if regularisation is None else float(regularisation)
        else:
            n_rows = s_last - s_first + 1
            n_valid = max(1, int(round(validation * n_rows)))
            split = s_last - n_valid  # last training row
            train = _normal_equations(p, q, h, k0, s_first, split)
            valid = _normal_equations(p, q, h, k0, split + 1, s_last)
            grid = np.array(REGULARISATION_GRID)
            scores = _scan(param.reduce(train), param.reduce(valid), grid)
            chosen = lam = float(grid[int(np.argmin(scores))])
            normal = train + valid
            logger.info(
                "eof: regularisation %.3g chosen on %d held-back frames (residual %.4g)",
                lam,
                n_valid,
                float(scores.min()),
            )
        reduced = param.reduce(normal)
        fit_seconds = time.perf_counter() - t_start
        design = _Certifier(reduced, param, fs, latency_frames, modulus_margin, command_limit,
                            precision)  # fmt: skip
        bank, cert, lam = design.smallest_certified(lam)
    return EOFResult(
        controller=bank,
        certificate=cert,
        regularisation=lam,
        validation_regularisation=chosen,
        regularisation_grid=grid,
        validation_residual=scores,
        history=h,
        latency_frames=float(latency_frames),
        n_training_frames=normal.rows,
        n_validation_frames=n_valid,
        fit_seconds=fit_seconds + design.fit_seconds,
        certify_seconds=design.certify_seconds,
        integral_action=integral_action,
    )


def eof_predictor(
    telemetry: LoopTelemetry,
    *,
    history: int = 5,
    latency_frames: float | None = None,
    regularisation: float | None = None,
    validation_fraction: float = 0.2,
    modulus_margin: float = 0.5,
    integral_action: bool = True,
    command_limit: float | np.ndarray | None = None,
    precision: str = "float32",
    blas_threads: int | None = 1,
) -> EOFResult:
    """Train and certify a multi-mode predictor from closed-loop telemetry.

    The pseudo-open loop ``p = m + G u`` is rebuilt with
    :func:`aocontrol.synthesis.pseudo_open_loop` and the loop plant of the telemetry's
    latency; its first ``k + 2`` frames (which depend on commands before the record) are
    dropped; then :func:`eof_from_pseudo_open_loop`.

    Parameters
    ----------
    telemetry : LoopTelemetry
        Closed-loop measurements and commands ``(n_frames, n_modes)``, rate and latency.
    history : int, default 5
        POL frames per command (>= 1).
    latency_frames : float, optional
        Latency beyond the WFS frame [frames] when the telemetry does not say it (or to
        override it).
    regularisation : float, optional
        Tikhonov weight ``>= 0``; ``None``: chosen on held-back telemetry.
    validation_fraction : float, default 0.2
        Fraction of the frames held back to choose the weight, in ``(0, 0.5]``.
    modulus_margin : float, default 0.5
        Required multivariable modulus margin, in ``(0, 1)``.
    integral_action : bool, default True
        Constrain the DC gain to ``F(1) = I`` (see :func:`eof_from_pseudo_open_loop`).
    command_limit : float or array_like of shape (n_modes,), optional
        The controller's limit on its command.
    precision : {"float32", "float64"}, default "float32"
        Precision of the real-time product.
    blas_threads : int or None, default 1
        BLAS threads of the training (see :func:`eof_from_pseudo_open_loop`).

    Returns
    -------
    EOFResult

    Raises
    ------
    TypeError
        If ``telemetry`` is not a :class:`LoopTelemetry`.
    ValueError
        No latency known, or the errors of :func:`eof_from_pseudo_open_loop`.
    EOFNotCertifiedError
        If no weight meets the required margin.
    """
    check_instance("telemetry", telemetry, LoopTelemetry)
    latency = telemetry.latency_frames if latency_frames is None else latency_frames
    if latency is None:
        where = f" of {telemetry.source}" if telemetry.source else ""
        raise ValueError(
            f"latency_frames must be given: the telemetry{where} does not say its loop's latency"
        )
    k0, _ = split_latency(latency)
    h = check_int("history", history, minimum=1)
    validation = None
    if regularisation is None:
        validation = check_in_range("validation_fraction", validation_fraction, 0.0, 0.5,
                                    low_inclusive=False, high_inclusive=True)  # fmt: skip
    _check_length("telemetry", telemetry.n_frames, telemetry.n_modes, h, latency, validation,
                  h + 2 * k0 + 3)  # fmt: skip
    plant = loop_plant(telemetry.fs, latency)
    pol = pseudo_open_loop(telemetry.measurements, telemetry.commands, plant)
    return eof_from_pseudo_open_loop(
        pol[k0 + 2 :],
        telemetry.fs,
        latency,
        history=history,
        regularisation=regularisation,
        validation_fraction=validation_fraction,
        modulus_margin=modulus_margin,
        integral_action=integral_action,
        command_limit=command_limit,
        precision=precision,
        blas_threads=blas_threads,
    )
