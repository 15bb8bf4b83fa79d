"""Stability and the multivariable modulus margin of a multi-mode (MIMO) loop.

The loop of a :class:`~aocontrol.controllers.MultiModeBank`: scalar plant
``G(z) = z^-1 ((1 - f) z^-k + f z^-(k+1))`` on every mode, controller
``K = (I - F G)^-1 F`` with the matrix FIR predictor ``F(z) = sum_{j < h} A_j z^-j`` on the
pseudo-open loop. Conventions of :mod:`aocontrol.plant` (``theta = 2 pi f / fs``).

Stability (exact). With the loop's plant equal to the controller's model, the sensitivity is
``S = (I + G K)^-1 = I - G F``, and ``K S = F``, ``G S`` and ``G K S = G F`` are FIR too:
every closed-loop map is a matrix polynomial in ``z^-1``, the closed-loop state matrix is
nilpotent and all its eigenvalues are 0. That is structural (it holds for any taps); it is
also checked on the real-time path (:func:`multimode_certificate`: from random controller
and plant states, with no disturbance and no noise, the loop's commands must vanish after
``h + 2 (k + 2)`` frames). Eigenvalues of a nilpotent matrix are not computed accurately in
floating point (a perturbation ``eps`` moves them by ``eps^(1/N)``), so the nominal verdict
is the structural one; :func:`multimode_closed_loop_poles` gives the closed-loop
eigenvalues for a plant that differs from the model (a latency or an optical gain), where
the loop is no longer FIR.

Multivariable modulus margin. ``mu = min_theta sigma_min(I + G K) = 1 / max_theta
sigma_max(S)``: the loop stays stable for every stable additive perturbation of ``G K`` of
H-infinity norm below ``mu`` (small gain on ``S``), the MIMO version of the SISO modulus
margin. ``sigma_max(S(theta))`` is computed exactly (to rounding) at points of ``[0, pi]``
(``S(-theta)`` is ``conj(S(theta))``: same singular values) as the square root of the
largest eigenvalue of ``S^H S``, formed in ``O(h n^2)`` per point from the products
``R_l = sum_{k - j = l} A_j^T A_k`` computed once, then LAPACK's Hermitian eigenvalues
(``O(n^3)`` per point). Between points a Lipschitz bound makes the maximum rigorous: for
two frequencies ``|sigma_max(S(a)) - sigma_max(S(b))| <= ||S(a) - S(b)||_2 <= L |a - b|``
with either

* ``L_c = sum_j (k + 1 + f + j) ||A_j||_2`` (the derivative of each term of ``G F``), or
* ``L_b = D max_theta ||S(theta)||_2``: Bernstein's inequality for the matrix trigonometric
  polynomial ``S`` of degree ``D = k + 1 + ceil(f) + h - 1``; self-referential, it gives
  ``max <= m / (1 - D (b - a) / 2)`` on an interval whose end values average ``m``,

so the maximum over ``[a, b]`` is at most ``(s(a) + s(b)) / 2 + L (b - a) / 2`` (the
smaller of the two bounds is used). The grid starts uniform (``max(16, 2 D) + 1`` points)
and every interval whose bound exceeds the largest value found by more than ``rtol`` is
bisected (branch and bound) until the bound and the largest value agree within ``rtol``
(or, with a required margin, until it is proven met or failed). The certified margin is
``1 / bound``, a lower bound of ``mu``; the smallest ``1 / sigma_max`` found is an upper
bound; ``mu`` lies between.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from aocontrol._validation import check_in_range, check_int
from aocontrol.controllers import MultiModeBank
from aocontrol.plant import split_latency

__all__ = ["MultiModeCertificate", "multimode_certificate", "multimode_closed_loop_poles"]

logger = logging.getLogger(__name__)

#: What the stability verdict of a nominal multi-mode certificate rests on.
STRUCTURAL = (
    "structural: the plant equals the controller's model, every closed-loop map is FIR "
    "(all closed-loop poles at z = 0); checked on the real-time path (commands flushed from "
    "random states)"
)
# Relative allowance on sigma_max for the rounding of S^H S and of LAPACK's eigenvalues
# (backward stable: an absolute error of a few n eps ||S^H S|| on the eigenvalue, half that
# relative on its square root); 64 n eps is far above it and far below any tolerance used.
_ROUNDING_FACTOR = 64.0
# Points of the first uniform grid on [0, pi]: at least this, and 2 per degree of S (the
# refinement adds points where the bound needs them: 71 in all for 540 modes, h = 5).
_GRID_MIN, _GRID_PER_DEGREE = 16, 2
# Points evaluated per batch (memory: a few arrays of batch x n^2 complex values).
_BATCH = 4
# After the flush (h + 2 (k0 + 2) frames, plus this many), the commands must be below
# _FLUSH_TOL of the initial state's scale: rounding of the POL's cancellation only.
_FLUSH_EXTRA, _FLUSH_TOL = 4, 1e-9


@dataclass(frozen=True)
class MultiModeCertificate:
    """Stability and multivariable modulus margin of a multi-mode loop (module docstring).

    Attributes
    ----------
    stable : bool
        Closed-loop stability with the controller's plant model (structural, and the
        real-time check passed).
    stability_method : str
        What the verdict rests on.
    flush_residual : float
        Largest command after the flush check, relative to the largest command of its
        transient (at least 1; rounding only, < 1e-9 when stable).
    margin : float
        Certified lower bound of ``min_theta sigma_min(I + G K)`` over the whole circle.
    margin_upper : float
        The smallest ``sigma_min(I + G K)`` met at an evaluated frequency (an upper bound of
        the true margin, which lies in ``[margin, margin_upper]``).
    frequency_hz : float
        Where ``margin_upper`` is reached [Hz].
    required : float or None
        The required margin, if one was given.
    certified : bool
        ``stable`` and (no requirement, or ``margin >= required``).
    converged : bool
        The bound and the largest value found agree within ``rtol`` (else the evaluation
        budget ran out or a failed requirement stopped the refinement early; ``margin`` is
        still a valid lower bound).
    n_evaluations : int
        Frequencies at which ``sigma_max(S)`` was computed.
    lipschitz : float
        ``L_c`` [1/rad] of the module docstring.
    degree : int
        Degree ``D`` of ``S`` in ``z^-1``.
    rtol : float
        Relative tolerance of the refinement.
    freqs_hz : numpy.ndarray, shape (n_evaluations,)
        Evaluated frequencies [Hz], ascending.
    sigma_max : numpy.ndarray, shape (n_evaluations,)
        ``sigma_max(I - G F)`` at ``freqs_hz``.
    method : str
        The grid and its refinement, in words.
    """

    stable: bool
    stability_method: str
    flush_residual: float
    margin: float
    margin_upper: float
    frequency_hz: float
    required: float | None
    certified: bool
    converged: bool
    n_evaluations: int
    lipschitz: float
    degree: int
    rtol: float
    freqs_hz: np.ndarray
    sigma_max: np.ndarray
    method: str

    def __post_init__(self) -> None:
        for name in ("freqs_hz", "sigma_max"):
            arr = np.array(getattr(self, name), dtype=float)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)


class _SensitivityNorm:
    """``sigma_max(I - G F)`` at points of ``[0, pi]``, from products formed once."""

    def __init__(self, bank: MultiModeBank) -> None:
        taps = bank.taps
        self.h, self.n = taps.shape[0], taps.shape[1]
        k0, f = split_latency(bank.latency_frames)
        self.k0, self.f = k0, f
        self.taps = taps
        # R_l = sum_{k - j = l} A_j^T A_k, l = 0..h-1 (R_{-l} = R_l^T).
        self.gram = [
            sum(taps[j].T @ taps[j + lag] for j in range(self.h - lag)) for lag in range(self.h)
        ]
        self.degree = k0 + 1 + (1 if f > 0 else 0) + self.h - 1
        # ||A_j||_2 = sqrt(lambda_max(A_j^T A_j)) (symmetric eigenvalues: cheaper than an SVD).
        norms = [math.sqrt(max(float(np.linalg.eigvalsh(a.T @ a)[-1]), 0.0)) for a in taps]
        self.lipschitz = float(sum((k0 + 1 + f + j) * norms[j] for j in range(self.h)))
        self.rounding = _ROUNDING_FACTOR * self.n * np.finfo(float).eps

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        out = np.empty(theta.size)
        eye = np.eye(self.n)
        for start in range(0, theta.size, _BATCH):
            th = theta[start : start + _BATCH]
            w = np.exp(-1j * th)
            g = w ** (self.k0 + 1) * ((1 - self.f) + self.f * w)
            powers = w[:, None] ** np.arange(self.h)[None, :]
            gF = g[:, None, None] * np.tensordot(powers, self.taps, axes=(1, 0))
            # H = S^H S = I - G F - (G F)^H + |G|^2 F^H F, F^H F = sum_l w^l R_l.
            H = eye[None] - gF - np.conj(np.swapaxes(gF, 1, 2))
            g2 = np.abs(g) ** 2
            H += g2[:, None, None] * self.gram[0][None]
            for lag in range(1, self.h):
                c = (g2 * w**lag)[:, None, None]
                H += c * self.gram[lag][None] + np.conj(c) * self.gram[lag].T[None]
            lam = np.linalg.eigvalsh(H)[:, -1]
            out[start : start + th.size] = np.sqrt(np.maximum(lam, 0.0))
        return out


def _interval_bounds(
    theta: np.ndarray, upper: np.ndarray, lipschitz: float, degree: int
) -> np.ndarray:
    """Upper bound of ``sigma_max`` on each interval between consecutive points."""
    width = np.diff(theta)
    mean = (upper[:-1] + upper[1:]) / 2
    by_coeff = mean + lipschitz * width / 2
    shrink = 1.0 - degree * width / 2
    with np.errstate(divide="ignore"):
        by_bernstein = np.where(shrink > 0, mean / np.where(shrink > 0, shrink, 1.0), np.inf)
    return np.minimum(by_coeff, by_bernstein)


def _flush_check(bank: MultiModeBank, rng: np.random.Generator) -> float:
    """Largest command after the nominal loop ran from random states with d = n = 0,
    relative to the transient's (module docstring)."""
    k0, f = split_latency(bank.latency_frames)
    n, h = bank.n_modes, bank.history
    probe = MultiModeBank(bank.taps, bank.fs, bank.latency_frames, precision="float64")
    depth = k0 + 2
    past_m = rng.standard_normal((h + depth, n))
    past_u = rng.standard_normal((h + depth, n))
    probe.set_history(past_m, past_u)
    # The plant's own command line (the DM's past commands), also random: u[k-1], u[k-2].
    line = list(rng.standard_normal((depth, n)))  # line[i] = u[k-1-i]
    n_frames = h + 2 * depth + _FLUSH_EXTRA
    last = scale = 0.0
    for frame in range(n_frames):
        m = -((1 - f) * line[k0] + (f * line[k0 + 1] if f else 0.0))
        u = probe.step(m)
        line = [u, *line[:-1]]
        scale = max(scale, float(np.abs(u).max()))
        if frame >= n_frames - _FLUSH_EXTRA:
            last = max(last, float(np.abs(u).max()))
    # Relative to the transient's scale (the POL's cancellation rounds at eps of the
    # commands, whatever the size of the taps).
    return last / max(scale, 1.0)


def _refine(norm, n_first, required, rtol, max_evaluations, decide_only):
    """Branch and bound on ``[0, pi]`` (module docstring): ``(theta, sigma, bound,
    converged)``."""
    theta = np.linspace(0.0, np.pi, n_first)
    sig = norm(theta)
    limit = None if required is None else 1.0 / required
    while True:
        upper = sig * (1.0 + norm.rounding)
        lo = float(sig.max())
        bounds = _interval_bounds(theta, upper, norm.lipschitz, norm.degree)
        bound = max(float(upper.max()), float(bounds.max()))
        converged = bound <= lo * (1.0 + rtol)
        decided = limit is not None and (lo > limit or (decide_only and bound <= limit))
        # A requirement between the largest value found and the bound is not yet decided,
        # however close the two: the verdict is the certificate, so refine on.
        open_verdict = limit is not None and lo <= limit < bound
        if decided or (converged and not open_verdict):
            break
        # Bisect every interval that could hold a value above the target: the largest value
        # found (within rtol), or the requirement's limit when only the decision is wanted
        # or the only thing left open.
        on_limit = limit is not None and (decide_only or converged)
        target = limit if on_limit else lo * (1.0 + rtol)
        refine = np.flatnonzero(bounds > target)
        if theta.size + refine.size > max_evaluations:
            logger.warning(
                "multimode_certificate: evaluation budget %d reached; margin bound %.4g, grid %.4g",
                max_evaluations,
                1.0 / bound,
                1.0 / lo,
            )
            break
        mid = (theta[refine] + theta[refine + 1]) / 2
        theta = np.concatenate([theta, mid])
        sig = np.concatenate([sig, norm(mid)])
        order = np.argsort(theta)
        theta, sig = theta[order], sig[order]

    return theta, sig, bound, converged


def multimode_certificate(
    controller: MultiModeBank,
    *,
    modulus_margin: float | None = None,
    rtol: float = 1e-2,
    max_evaluations: int = 4096,
    decide_only: bool = False,
    seed: int = 0,
) -> MultiModeCertificate:
    """Closed-loop stability and certified multivariable modulus margin of a multi-mode loop.

    The loop is the controller with its own plant model (module docstring): stability is
    structural and checked on the real-time path; the margin
    ``min_theta sigma_min(I + G K) = 1 / max_theta sigma_max(I - G F)`` is bounded below
    over the whole circle by a grid, a Lipschitz bound between its points and refinement
    (branch and bound) until the bound is within ``rtol`` of the largest value found.

    Cost: ``O(n^3)`` per frequency (a Hermitian eigenvalue problem of size ``n_modes``, on
    one BLAS thread) on a first grid of ``max(16, 2 D) + 1`` points and the refinement
    (``D`` the degree of ``S``: ``k + h`` or ``k + h + 1``); measured ~0.06 s per frequency
    and ~70 frequencies at 540 modes, ``h = 5`` (``benchmarks/bench_eof.py``).

    Parameters
    ----------
    controller : MultiModeBank
        The controller (its taps, latency model and rate).
    modulus_margin : float, optional
        Required margin in ``(0, 1)``; ``certified`` says whether it is met. A point below
        it stops the refinement early (the requirement is then proven failed).
    rtol : float, default 1e-2
        Relative tolerance between the certified bound and the largest ``sigma_max(S)``
        found, in ``(0, 1)``.
    max_evaluations : int, default 4096
        Budget of frequencies; beyond it the refinement stops (``converged`` False, the
        margin still a valid lower bound).
    decide_only : bool, default False
        With ``modulus_margin``: stop as soon as the requirement is proven met or failed
        (fewer frequencies; ``margin`` is then a valid but unrefined lower bound).
    seed : int, default 0
        Seed of the random states of the real-time flush check.

    Returns
    -------
    MultiModeCertificate

    Raises
    ------
    TypeError
        If ``controller`` is not a :class:`~aocontrol.controllers.MultiModeBank`.
    ValueError
        ``modulus_margin`` outside ``(0, 1)``, ``rtol`` outside ``(0, 1)`` or
        ``max_evaluations`` below the first grid.

    Examples
    --------
    ``u = 0.5 p`` on one mode, no latency: ``S = 1 - 0.5 z^-1``, ``max |S| = 1.5`` at
    Nyquist, margin ``2/3``.

    >>> from aocontrol.controllers import MultiModeBank
    >>> cert = multimode_certificate(MultiModeBank([[[0.5]]], 1000.0, 0.0), modulus_margin=0.5)
    >>> cert.stable, cert.certified, round(cert.margin_upper, 6), cert.margin > 0.66
    (True, True, 0.666667, True)
    """
    if not isinstance(controller, MultiModeBank):
        raise TypeError(
            f"controller must be a MultiModeBank (a multi-mode loop), got "
            f"{type(controller).__name__}; a modal bank's margins: aocontrol.analysis.margins"
        )
    required = None
    if modulus_margin is not None:
        required = check_in_range("modulus_margin", modulus_margin, 0.0, 1.0,
                                  low_inclusive=False)  # fmt: skip
    rtol = check_in_range("rtol", rtol, 0.0, 1.0, low_inclusive=False)
    k0, f = split_latency(controller.latency_frames)
    degree = k0 + 1 + (1 if f > 0 else 0) + controller.history - 1
    n_first = max(_GRID_MIN, _GRID_PER_DEGREE * degree) + 1
    max_evaluations = check_int("max_evaluations", max_evaluations, minimum=n_first)

    flush = _flush_check(controller, np.random.default_rng(seed))
    stable = flush < _FLUSH_TOL
    if not stable:
        logger.warning(
            "multimode_certificate: the real-time path did not flush (residual %.3g of the "
            "state's scale): the controller's realisation disagrees with its plant model",
            flush,
        )

    from threadpoolctl import threadpool_limits

    # One BLAS thread: the products are n x n, where a second OpenBLAS thread on a shared
    # machine only waits (measured: 0.34 s per frequency with two threads, 0.04 s with one,
    # 540 modes, load ~3 on 2 cores).
    with threadpool_limits(limits=1, user_api="blas"):
        norm = _SensitivityNorm(controller)
        theta, sig, bound, converged = _refine(norm, n_first, required, rtol, max_evaluations,
                                               decide_only)  # fmt: skip
    fs = controller.fs
    i_max = int(np.argmax(sig))
    margin = 1.0 / bound
    certified = stable and (required is None or margin >= required)
    method = (
        f"sigma_max(I - G F) at {theta.size} frequencies of [0, fs/2] (uniform {n_first}, "
        f"then bisection where the Lipschitz bound exceeded the largest value by > "
        f"{rtol:g}); bound between points: min of L_c = {norm.lipschitz:.4g} /rad and "
        f"Bernstein with degree {norm.degree}"
    )
    return MultiModeCertificate(
        stable=bool(stable),
        stability_method=STRUCTURAL,
        flush_residual=flush,
        margin=margin,
        margin_upper=1.0 / float(sig[i_max]),
        frequency_hz=float(theta[i_max] * fs / (2 * math.pi)),
        required=required,
        certified=bool(certified),
        converged=bool(converged),
        n_evaluations=int(theta.size),
        lipschitz=norm.lipschitz,
        degree=norm.degree,
        rtol=rtol,
        freqs_hz=theta * fs / (2 * math.pi),
        sigma_max=sig,
        method=method,
    )


def multimode_closed_loop_poles(
    controller: MultiModeBank,
    *,
    latency_frames: float | None = None,
    optical_gain: float | np.ndarray = 1.0,
    mixing: np.ndarray | None = None,
    dm_coefficients: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Eigenvalues of the closed-loop state matrix with a plant that may differ from the model.

    The true plant is ``diag(og) M G_t H``: ``G_t`` the loop plant of latency
    ``latency_frames`` (default the controller's), ``H`` a response of the DM common to the
    modes (``dm_coefficients``, e.g. :meth:`aocontrol.sim.model_errors.DMResponse.coefficients`),
    ``M`` a mixing of the modes (a misregistration's modal matrix) and ``og`` the optical
    gains; the controller rebuilds the POL with its own model ``G``. The state is the last
    ``h - 1`` POL frames, the last ``D`` applied commands (``D`` the longer of the model's
    and the true plant's command memory) and the last ``n_a - 1`` outputs of the true plant
    (``n_a`` the length of ``H``'s denominator), dimension ``n_modes (h - 1 + D + n_a - 1)``;
    the eigenvalues come from a dense ``numpy.linalg.eigvals`` (``O(dim^3)``: for tens of
    modes, not hundreds). The loop is stable iff all have modulus < 1. With the nominal plant
    the matrix is nilpotent and these eigenvalues are only rounding noise of size
    ``eps^(1/N)`` around 0 (use :func:`multimode_certificate`, whose verdict is structural).

    Parameters
    ----------
    controller : MultiModeBank
        The controller.
    latency_frames : float, optional
        True latency beyond the WFS frame [frames] (default the controller's model).
    optical_gain : float or ndarray (n_modes,), default 1.0
        True loop gain ``og`` of the plant (> 0), one or one per mode, e.g. a pyramid's
        optical gains.
    mixing : ndarray (n_modes, n_modes), optional
        ``M``: the modes the DM applies for unit commands (default the identity).
    dm_coefficients : tuple of ndarray, optional
        ``(b, a)`` of ``H(z)`` in powers of ``z^-1`` (``a[0] != 0``; default ``H = 1``).

    Returns
    -------
    numpy.ndarray, shape (dim,), complex
        Closed-loop poles.

    Raises
    ------
    TypeError
        If ``controller`` is not a :class:`~aocontrol.controllers.MultiModeBank`.
    ValueError
        A negative latency, a non-positive optical gain, a mixing or DM response of the
        wrong shape.
    """
    if not isinstance(controller, MultiModeBank):
        raise TypeError(f"controller must be a MultiModeBank, got {type(controller).__name__}")
    taps, n, h = controller.taps, controller.n_modes, controller.history
    og = np.broadcast_to(np.asarray(optical_gain, dtype=float), (n,))
    if not np.all(np.isfinite(og) & (og > 0)):
        raise ValueError(f"optical_gain must be > 0 (one or one per mode), got {optical_gain!r}")
    gain = np.diag(og)
    if mixing is not None:
        mixing = np.asarray(mixing, dtype=float)
        if mixing.shape != (n, n):
            raise ValueError(f"mixing must have shape ({n}, {n}), got {mixing.shape}")
        gain = gain @ mixing
    bh, ah = (np.array([1.0]), np.array([1.0])) if dm_coefficients is None else dm_coefficients
    bh, ah = np.atleast_1d(np.asarray(bh, float)), np.atleast_1d(np.asarray(ah, float))
    if bh.ndim != 1 or ah.ndim != 1 or ah[0] == 0:
        raise ValueError("dm_coefficients must be (b, a), 1-D, in powers of z^-1 with a[0] != 0")
    bh, ah = bh / ah[0], ah / ah[0]
    # The model's and the true plant's impulse responses on the command line, in powers of
    # z^-1 (index i for u[k - i]; index 0 is 0: one frame at least).
    model = _plant_taps(*split_latency(controller.latency_frames))
    kt, ft = split_latency(controller.latency_frames if latency_frames is None
                           else latency_frames)  # fmt: skip
    true = np.convolve(_plant_taps(kt, ft), bh)
    depth = max(model.size, true.size) - 1  # commands u[k-1] .. u[k-depth]
    na = ah.size - 1  # true outputs s[k-1] .. s[k-na]
    dim = n * (h - 1 + depth + na)
    u0, s0 = n * (h - 1), n * (h - 1 + depth)  # where the command and output blocks start
    # s[k] = -sum_j ah_j s[k-j] + sum_i true_i (og M) u[k-i]; p[k] = sum_i model_i u[k-i] - s[k].
    s_row = np.zeros((n, dim))
    for i in range(1, true.size):
        s_row[:, u0 + n * (i - 1) : u0 + n * i] += true[i] * gain
    for j in range(1, na + 1):
        s_row[:, s0 + n * (j - 1) : s0 + n * j] -= ah[j] * np.eye(n)
    pol_row = -s_row
    for i in range(1, model.size):
        pol_row[:, u0 + n * (i - 1) : u0 + n * i] += model[i] * np.eye(n)
    # u[k] = A_0 p[k] + sum_{j>=1} A_j p[k-j], x[k] = (p[k-1..k-h+1], u[k-1..], s[k-1..]).
    u_row = taps[0] @ pol_row
    for j in range(1, h):
        u_row[:, n * (j - 1) : n * j] += taps[j]
    A = np.zeros((dim, dim))
    if h > 1:
        A[:n] = pol_row  # p[k] becomes the newest stored POL frame
        A[n:u0, : n * (h - 2)] = np.eye(n * (h - 2))
    A[u0 : u0 + n] = u_row  # u[k] becomes the newest stored command
    A[u0 + n : s0, u0 : s0 - n] = np.eye(n * (depth - 1))
    if na:
        A[s0 : s0 + n] = s_row  # s[k] becomes the newest stored output
        A[s0 + n :, s0 : dim - n] = np.eye(n * (na - 1))
    return np.linalg.eigvals(A)


def _plant_taps(k: int, f: float) -> np.ndarray:
    """``G(z) = z^-1 ((1 - f) z^-k + f z^-(k+1))`` as coefficients of ``z^-i``, ``i = 0..k+2``."""
    g = np.zeros(k + 3)
    g[k + 1] = 1.0 - f
    g[k + 2] = f
    return g
