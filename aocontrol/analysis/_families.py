"""Exact stability intervals of a loop family with one real parameter.

The gain and delay margins ask how far one parameter of the loop can move before the closed
loop becomes unstable: a factor ``s`` on the loop gain, or the fractional part ``s = f`` of the
latency (the plant of :func:`aocontrol.loop_plant` interpolates linearly between two whole
delays, so within one whole frame its numerator is affine in ``f``). In both cases the
characteristic polynomial is affine in the parameter,

    C(w; s) = C0(w) + s C1(w),      w = z^-1   (coefficients lowest power first),

and the closed loop can change stability only where a root of ``C`` crosses the unit circle,
i.e. at an ``s`` for which ``C0(w) + s C1(w) = 0`` with ``|w| = 1``: ``s = -C0(w) / C1(w)`` must
be real there. On ``w = exp(-j theta)``,

    Im(C0(w) conj C1(w)) = -sin(theta) sum_{n >= 1} d_n U_{n-1}(cos theta),

``d_n = r_n - r_{-n}`` with ``r`` the cross-correlation of the coefficients and ``U`` the
Chebyshev polynomials of the second kind (``U_{n-1} = T_n' / n``), so every such angle is an
end (0 or pi) or a real root in ``[-1, 1]`` of one polynomial in ``x = cos(theta)``. Its roots,
and the sign changes of the same quantity on the pole-refined grid of the modulus certificate
(where the polynomial in ``x`` is ill-conditioned: roots crowding near ``z = +-1``), each polished
by Brent's method on the exact expression, give every critical value of ``s``. Between two
consecutive critical values the number of closed-loop poles outside the circle is constant,
so one pole computation at an interior point decides each piece: the stability set of the
family is exact up to the root polish (``1e-13`` rad in ``theta``). A critical value found
where none is (a spurious root) only splits a piece in two: both halves get their own verdict,
so it cannot make a verdict wrong.

The same Chebyshev construction gives the gain crossovers ``|B| = |A|``
(:func:`circle_zeros` with the autocorrelations of :mod:`._certificate`).
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass

import numpy as np
from numpy.polynomial import chebyshev as cheb
from numpy.polynomial import polynomial as poly
from scipy import optimize

from aocontrol.analysis._certificate import pole_refined_grid, trim_back

# Roots of the polynomial in x within this imaginary part are candidates (a double root split
# by round-off); a spurious candidate costs one pole computation, a lost one a wrong verdict.
_IMAG_KEEP = 1e-6
# Half-width [rad] of the bracket searched around a polynomial root for its sign change.
_BRACKET = 1e-6
# Brent's method tolerance on theta [rad].
_XTOL = 1e-13
# Closed-loop poles with modulus above 1 - POLE_TOL are not asymptotically stable (shared
# with :func:`aocontrol.analysis.is_stable`).
POLE_TOL = 1e-9
# Two critical values closer than this (relative) are one.
_SAME = 1e-12


def poly_stable(c: np.ndarray) -> bool:
    """Whether every root ``z`` of ``c`` (powers of ``w = z^-1``, lowest first) has
    ``|z| < 1 - POLE_TOL``; trailing zero coefficients are poles at ``z = 0``."""
    c = trim_back(np.asarray(c, dtype=float))
    if c.size <= 1:
        return True
    # z^N C(1/z) has the coefficients of C, highest power of z first.
    return bool(np.max(np.abs(np.roots(c))) < 1.0 - POLE_TOL)


def _im_chebyshev(c0: np.ndarray, c1: np.ndarray) -> np.ndarray:
    """Chebyshev coefficients in ``x = cos(theta)`` of ``sum_n d_n U_{n-1}(x)`` (module doc)."""
    r = np.convolve(c0, c1[::-1])  # r[n + len(c1) - 1] = sum_l c0[l + n] c1[l]
    mid = c1.size - 1
    n_max = max(c0.size - 1, c1.size - 1)
    d = np.zeros(n_max + 1)
    for n in range(1, n_max + 1):
        pos = r[mid + n] if mid + n < r.size else 0.0
        neg = r[mid - n] if mid - n >= 0 else 0.0
        d[n] = pos - neg
    t = np.zeros(n_max + 1)
    t[1:] = d[1:] / np.arange(1, n_max + 1)
    return cheb.chebder(t) if t.size > 1 else np.zeros(1)


def horner(c: np.ndarray) -> callable:
    """``theta -> c(exp(-j theta))`` for one scalar angle (Horner in plain Python: the root
    polish calls it thousands of times, where a ``numpy`` call's overhead dominates)."""
    coeffs = [complex(x) for x in np.asarray(c, dtype=float)[::-1]]

    def value(theta: float) -> complex:
        w = cmath.exp(-1j * theta)
        acc = 0j
        for x in coeffs:
            acc = acc * w + x
        return acc

    return value


def _polish(f: callable, a: float, b: float, guess: float) -> float:
    """Brent's method on ``[a, b]`` where ``f`` changes sign there, else ``guess`` (a
    tangential zero, or a sign change at round-off that the scalar evaluation does not see)."""
    fa, fb = f(a), f(b)
    if math.isfinite(fa) and math.isfinite(fb) and fa * fb < 0:
        return optimize.brentq(f, a, b, xtol=_XTOL)
    return guess


def circle_zeros(
    cheb_coeffs: np.ndarray,
    fun: callable,
    polys: tuple[np.ndarray, ...],
    scalar: callable,
) -> np.ndarray:
    """Zeros in ``(0, pi)`` of a real function of ``theta`` known as a polynomial in ``cos``.

    Parameters
    ----------
    cheb_coeffs : numpy.ndarray
        Chebyshev coefficients in ``x = cos(theta)`` of a polynomial with the same zeros in
        ``(0, pi)`` as ``fun``.
    fun : callable
        The function itself, vectorised over ``theta`` (evaluated directly, accurate where
        the polynomial is not).
    polys : tuple of numpy.ndarray
        Polynomials (powers of ``w``) whose roots near the circle refine the sampling grid.
    scalar : callable
        ``fun`` for one float (the polish).

    Returns
    -------
    numpy.ndarray
        Sorted angles [rad]: polished roots of the polynomial and of the sign changes of
        ``fun`` on the pole-refined grid (a tangential zero, without sign change, is kept
        at the polynomial's root).
    """
    out: list[float] = []
    f = scalar
    q = cheb.chebtrim(cheb_coeffs, 1e-15 * max(np.max(np.abs(cheb_coeffs)), 1e-300))
    if q.size > 1 and np.any(q[1:] != 0):
        roots = cheb.chebroots(q)
        keep = (np.abs(roots.imag) <= _IMAG_KEEP) & (np.abs(roots.real) < 1.0)
        for t in np.arccos(roots.real[keep]):
            out.append(_polish(f, max(t - _BRACKET, 0.0), min(t + _BRACKET, np.pi), float(t)))
    polished = np.sort(np.asarray(out))
    grid = pole_refined_grid(polys)
    vals = fun(grid)
    ok = np.isfinite(vals[:-1]) & np.isfinite(vals[1:])
    for i in np.flatnonzero(ok & (vals[:-1] * vals[1:] < 0)):
        a, b = grid[i], grid[i + 1]
        j = np.searchsorted(polished, a)
        if j < polished.size and polished[j] <= b:
            continue  # a polished root already holds this sign change
        out.append(_polish(f, a, b, 0.5 * (a + b)))
    out.extend(grid[1:-1][vals[1:-1] == 0.0].tolist())
    theta = np.sort(np.asarray([t for t in out if 0.0 < t < np.pi]))
    if theta.size > 1:
        theta = theta[np.r_[True, np.diff(theta) > 1e-11]]
    return theta


def critical_values(c0: np.ndarray, c1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every real ``s`` at which ``C0 + s C1`` has a root on the unit circle.

    Returns
    -------
    s : numpy.ndarray
        Critical values, sorted (any sign; ``+-inf`` excluded).
    theta : numpy.ndarray
        Angle [rad] in ``[0, pi]`` of the root on the circle for each value.
    """
    c0 = np.asarray(c0, dtype=float)
    c1 = np.asarray(c1, dtype=float)
    scale = max(np.max(np.abs(c0)), np.max(np.abs(c1)), 1e-300)
    c0, c1 = c0 / scale, c1 / scale

    def im(theta: np.ndarray) -> np.ndarray:
        w = np.exp(-1j * theta)
        v0, v1 = poly.polyval(w, c0), poly.polyval(w, c1)
        with np.errstate(divide="ignore", invalid="ignore"):
            return (v0 * np.conj(v1)).imag / (np.abs(v0) * np.abs(v1))

    h0, h1 = horner(c0), horner(c1)

    def im1(theta: float) -> float:
        v0, v1 = h0(theta), h1(theta)
        den = abs(v0) * abs(v1)
        return (v0 * v1.conjugate()).imag / den if den > 0 else math.nan

    zeros = circle_zeros(_im_chebyshev(c0, c1), im, (c0, c1), im1)
    theta = np.concatenate([[0.0], zeros, [np.pi]])
    w = np.exp(-1j * theta)
    v0, v1 = poly.polyval(w, c0), poly.polyval(w, c1)
    good = np.abs(v1) > 1e-14 * np.maximum(np.abs(v0), 1e-300)
    s = -(v0[good] * np.conj(v1[good])).real / np.abs(v1[good]) ** 2
    theta = theta[good]
    order = np.argsort(s)
    return s[order], theta[order]


@dataclass(frozen=True)
class Pieces:
    """The stability of ``C0 + s C1`` over ``[lo, hi]``, piece by piece.

    Attributes
    ----------
    edges : numpy.ndarray, shape (n + 1,)
        ``lo``, the critical values inside, ``hi``.
    theta : numpy.ndarray, shape (n + 1,)
        Angle [rad] of the root on the circle at each edge (``nan`` at ``lo`` and ``hi``
        unless they are critical values).
    stable : numpy.ndarray of bool, shape (n,)
        Verdict of each open piece ``(edges[i], edges[i + 1])``.
    """

    edges: np.ndarray
    theta: np.ndarray
    stable: np.ndarray

    def piece_of(self, s: float) -> int:
        """Index of the piece holding ``s`` (the upper one at an edge)."""
        i = np.searchsorted(self.edges, s, side="right") - 1
        return int(np.clip(i, 0, self.stable.size - 1))

    def stable_run(self, i: int) -> tuple[int, int]:
        """Pieces ``lo..hi`` (inclusive) of the run of stable pieces holding piece ``i``."""
        lo = hi = i
        while lo > 0 and self.stable[lo - 1]:
            lo -= 1
        while hi < self.stable.size - 1 and self.stable[hi + 1]:
            hi += 1
        return lo, hi


def stability_pieces(c0: np.ndarray, c1: np.ndarray, lo: float, hi: float) -> Pieces:
    """Exact stability of ``C0 + s C1`` for ``s`` in ``[lo, hi]`` (``hi`` may be ``inf``).

    Parameters
    ----------
    c0, c1 : numpy.ndarray
        Real coefficients in powers of ``w = z^-1``, lowest first.
    lo, hi : float
        The parameter's range, ``lo < hi``.

    Returns
    -------
    Pieces
    """
    s, theta = critical_values(c0, c1)
    # A value at an end (within round-off) is the end itself: an open-loop pole on the circle
    # at zero gain, the whole-frame plant shared by two latency segments.
    inside = s > lo + _SAME * max(1.0, abs(lo))
    if np.isfinite(hi):
        inside &= s < hi - _SAME * max(1.0, abs(hi))
    s, theta = s[inside], theta[inside]
    if s.size > 1:
        keep = np.r_[True, np.diff(s) > _SAME * np.maximum(np.abs(s[1:]), 1.0)]
        s, theta = s[keep], theta[keep]
    edges = np.concatenate([[lo], s, [hi]])
    thetas = np.concatenate([[np.nan], theta, [np.nan]])
    size = max(c0.size, c1.size)
    a0, a1 = np.zeros(size), np.zeros(size)
    a0[: c0.size], a1[: c1.size] = c0, c1
    verdicts = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        if np.isinf(b):
            x = 2.0 * a + 1.0
        elif a == 0.0 and lo == 0.0 and np.isinf(hi):
            x = 0.5 * b  # the gain family: geometric middle of (0, b) is b / 2 enough
        else:
            x = 0.5 * (a + b)
        verdicts.append(poly_stable(a0 + x * a1))
    return Pieces(edges, thetas, np.asarray(verdicts, dtype=bool))
