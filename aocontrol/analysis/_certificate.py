"""The modulus-margin certificate: ``min |1 + G K|`` over the whole unit circle.

A grid, however dense, certifies only its points: a controller pole at radius 0.9998 makes a dip
of ``|1 + G K|`` about ``(1 - r) fs / pi`` wide (0.2 Hz at 3 kHz), narrower than any practical
grid step. For rational ``G`` and ``K`` the minimum is certified exactly instead:

with ``w = z^-1``, ``G = Bg / Ag`` and ``K = Bk / Ak``,

    |1 + G K|^2 = |C(w)|^2 / |D(w)|^2,   C = Ag Ak + Bg Bk,   D = Ag Ak.

On ``w = exp(-j theta)``, ``|C|^2 = r_0 + 2 sum_k r_k cos(k theta)`` (``r`` the autocorrelation
of the coefficients of ``C``) is a polynomial in ``x = cos(theta)`` written in the Chebyshev
basis, ``N(x) = r_0 + 2 sum_k r_k T_k(x)``, and likewise ``M(x)`` for ``|D|^2``. The ratio
``R = N / M`` is stationary in ``theta`` where ``sin(theta) = 0`` (the ends 0 Hz and fs/2) or
where ``N' M - N M' = 0``, a polynomial in ``x``. Its real roots in ``[-1, 1]`` and the two
ends are every candidate for the minimum: the smallest value of ``|1 + G K|`` among them is the
minimum over the circle. Each candidate is polished on the exact rational expression (Newton
steps on its theta-derivative around it), so root-finding round-off cannot lose a narrow dip;
roots with a small imaginary part (a double real root split by round-off) are kept as
candidates too.

In floating point that polynomial can lose a dip: where the controller's poles crowd near
``z = 1`` (or ``-1``), ``|D|^2`` is tiny there and ``N' M - N M'`` falls to round-off, so its
roots mean nothing (``tests/test_certified.py`` holds such a controller, five poles at radius
0.996-0.998, whose dip the roots miss).
The candidates therefore also include the local minima of ``|1 + G K|``, evaluated directly
(Horner on the circle, accurate where the polynomial in ``x`` is not), on a grid of uniform
steps refined around every closed-loop and open-loop pole within radius 0.9 to 1.1 of the
circle, geometrically from a hundredth of the pole's distance to the circle out to two
uniform steps: a dip narrower than the uniform step comes from a pole that close to the
circle, and is sampled across. Each is polished by Newton steps between its grid neighbours.

For a measured plant (``control.FRD``) the plant is known on its grid only: the minimum is
taken over the FRD's points and, where the controller has lightly damped poles, over refined
points around them (the controller exact, the plant interpolated between its measured points,
as :func:`aocontrol.plant.frequency_response` does). What that covers is said in
:attr:`ModulusCertificate.method`.

One owner: :func:`aocontrol.analysis.margins` and the data-driven synthesis both certify the
modulus margin here.
"""

from __future__ import annotations

from dataclasses import dataclass

import control
import numpy as np
from numpy.polynomial import chebyshev as cheb
from numpy.polynomial import polynomial as poly

from aocontrol.analysis._loop import _as_siso_controller
from aocontrol.controllers import ControllerBank
from aocontrol.plant import check_frd_coverage, plant_fs, z_inverse_coefficients
from aocontrol.plant import frequency_response_unchecked as _response

__all__ = [
    "ModulusCertificate",
    "modulus_certificate",
    "polynomial_certificate",
    "rational_modulus_minima",
]

#: Method names of a certificate.
EXACT = (
    "exact (stationary points of |1 + G K|^2 as polynomial roots, and local minima on a grid "
    "refined around every pole near the circle; each polished)"
)
FRD = (
    "measured plant: its grid points, refined around the controller's lightly damped poles "
    "with the plant interpolated between measured points"
)
# Roots of the stationarity polynomial within this imaginary part are kept as candidates
# (a double real root split by round-off); extra candidates cost one evaluation each.
_IMAG_KEEP = 1e-3
# Half-width [rad] of the polish around each candidate (covers the root's round-off in theta:
# near x = +-1, dx ~ 1e-12 maps to dtheta ~ 1e-6).
_POLISH = 1e-4
# Newton steps of the polish (quadratic convergence from a root accurate to ~1e-8 rad: three
# or four reach round-off; the iterations stop earlier when the steps vanish).
_NEWTON_STEPS = 8
# ... or when every step is below this [rad]: a dip as narrow as a pole at radius 1 - 1e-6
# (width 1e-6 rad) then has its minimum to ~1e-10 relative.
_NEWTON_STOP = 1e-11
# The direct-evaluation grid: uniform steps on [0, pi], and around each pole within
# _GRID_POLE_BAND of the circle offsets from _GRID_FINEST of its distance to two uniform steps.
_GRID_UNIFORM = 1024
_GRID_POLE_BAND = 0.1
_GRID_FINEST = 1e-2
_GRID_OFFSETS = 48
# A grid minimum below every polished root by more than this (relative) is a lost dip.
_GRID_LOST = 1e-9
_UNIFORM_THETA = np.linspace(0.0, np.pi, _GRID_UNIFORM + 1)
_GEOM_T = np.linspace(0.0, 1.0, _GRID_OFFSETS)
# Candidates within this factor of the smallest one are polished.
_POLISH_WITHIN = 2.0
# Controller poles above this radius are "lightly damped" for the FRD refinement.
_FRD_POLE_RADIUS = 0.9
# Points per pole bandwidth in the FRD refinement, and bandwidths each side.
_FRD_POINTS, _FRD_WIDTHS = 41, 8.0


@dataclass(frozen=True)
class ModulusCertificate:
    """Certified modulus margin of a SISO loop ``L = G K``.

    Attributes
    ----------
    value : float
        ``min |1 + G K|`` over [0, fs/2] (``1 / ||S||_inf``).
    frequency_hz : float
        Where the minimum is reached [Hz].
    exact : bool
        True for rational plant and controller: the minimum over the whole circle, from the
        stationary points (see the module docstring). False for a measured plant.
    method : str
        What the value covers.
    minima_hz : numpy.ndarray, shape (n,)
        Frequencies [Hz] of every local minimum of ``|1 + G K|`` found (the candidates).
    minima : numpy.ndarray, shape (n,)
        ``|1 + G K|`` at ``minima_hz``.
    """

    value: float
    frequency_hz: float
    exact: bool
    method: str
    minima_hz: np.ndarray
    minima: np.ndarray

    def below(self, margin: float) -> np.ndarray:
        """Frequencies [Hz] of the local minima of ``|1 + G K|`` below ``margin``, worst first."""
        bad = self.minima < margin
        order = np.argsort(self.minima[bad])
        return self.minima_hz[bad][order]


def trim_back(c: np.ndarray) -> np.ndarray:
    """``numpy.trim_zeros(c, "b")`` of a 1-D array: the same view, without its overhead
    (the margins trim thousands of short polynomials).

    >>> trim_back(np.array([0.0, 1.0, 0.0, 0.0]))
    array([0., 1.])
    """
    nz = np.flatnonzero(c)
    return c[: nz[-1] + 1] if nz.size else c[:0]


def _cheb_of_abs2(c: np.ndarray) -> np.ndarray:
    """Chebyshev coefficients in ``x = cos(theta)`` of ``|c(exp(-j theta))|^2``."""
    r = np.correlate(c, c, mode="full")[c.size - 1 :]
    out = 2.0 * r
    out[0] = r[0]
    return out


def _abs2_derivatives(p: np.ndarray, w: np.ndarray) -> tuple:
    """``|p(w)|^2`` at ``w = exp(-j theta)`` and its first two theta-derivatives.

    With ``c(theta) = p(w)``: ``c' = -j w p'(w)`` and ``c'' = -w p'(w) - w^2 p''(w)``, so
    ``|c|^2' = 2 Re(conj(c) c')`` and ``|c|^2'' = 2 (|c'|^2 + Re(conj(c) c''))``.
    """
    k = np.arange(p.size)
    W = w[:, None] ** k  # (n, deg + 1)
    c = W @ p
    wc1 = W @ (k * p)  # w p'(w)
    w2c2 = W @ (k * (k - 1) * p)  # w^2 p''(w)
    ct = -1j * wc1
    ctt = -wc1 - w2c2
    a = np.abs(c) ** 2
    return a, 2.0 * (np.conj(c) * ct).real, 2.0 * (np.abs(ct) ** 2 + (np.conj(c) * ctt).real)


def _newton_polish(
    num: np.ndarray,
    den: np.ndarray,
    theta: np.ndarray,
    vals: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Newton steps on ``dR/dtheta = 0`` (``R = |num|^2 / |den|^2``), all candidates at once.

    A step is taken where the curvature is positive (a minimum), stays within ``_POLISH``
    of the candidate (or within ``bounds``, per candidate) and in ``[0, pi]``; a candidate
    keeps its smallest value seen (``|num| / |den|``), so polishing never raises a value.
    """
    theta, vals = theta.astype(float).copy(), vals.astype(float).copy()
    if bounds is None:
        bounds = (theta - _POLISH, theta + _POLISH)
    t, lo, hi = theta.copy(), np.maximum(bounds[0], 0.0), np.minimum(bounds[1], np.pi)
    for it in range(_NEWTON_STEPS):
        w = np.exp(-1j * t)
        (a, a1, a2), (b, b1, b2) = _abs2_derivatives(num, w), _abs2_derivatives(den, w)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            v = np.sqrt(a / b)
            R1 = (a1 * b - a * b1) / b**2
            R2 = (a2 * b - a * b2) / b**2 - 2.0 * b1 * (a1 * b - a * b1) / b**3
        better = np.isfinite(v) & (v < vals)
        theta[better], vals[better] = t[better], v[better]
        ok = np.isfinite(R1) & np.isfinite(R2) & (R2 > 0)
        step = np.where(ok, -R1 / np.where(ok, R2, 1.0), 0.0)
        t_next = np.clip(t + step, lo, hi)
        moves = np.abs(t_next - t)
        # Converged (or held at a bound); or at round-off: after two steps, steps of ~1e-10
        # rad that no longer lower any value (the derivatives' round-off, measured near
        # clustered poles; the first pass only evaluates the start).
        stalled = it >= 2 and not np.any(better) and np.all(moves <= 1e-8)
        if np.all(moves <= _NEWTON_STOP) or stalled:
            break
        t = t_next
    else:
        w = np.exp(-1j * t)
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.abs(poly.polyval(w, num)) / np.abs(poly.polyval(w, den))
        better = np.isfinite(v) & (v < vals)
        theta[better], vals[better] = t[better], v[better]
    return theta, vals


def rational_modulus_minima(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local minima over ``theta in [0, pi]`` of ``|num(w)| / |den(w)|``, ``w = exp(-j theta)``.

    Parameters
    ----------
    num, den : numpy.ndarray
        Real polynomial coefficients in powers of ``w`` (lowest first), ``den`` not zero.

    Returns
    -------
    theta : numpy.ndarray
        Candidate angles [rad] (ends included, each polished on the exact expression).
    values : numpy.ndarray
        ``|num| / |den|`` there (``inf`` where ``den`` vanishes on the circle).
    """
    num = trim_back(np.asarray(num, dtype=float))
    den = trim_back(np.asarray(den, dtype=float))
    if num.size == 0:
        num = np.zeros(1)
    # One common scale for both: the ratio is unchanged, the coefficients stay O(1).
    scale = max(np.max(np.abs(num)), np.max(np.abs(den)))
    num, den = num / scale, den / scale
    N, M = _cheb_of_abs2(num), _cheb_of_abs2(den)
    Q = cheb.chebsub(cheb.chebmul(cheb.chebder(N), M), cheb.chebmul(N, cheb.chebder(M)))
    Q = cheb.chebtrim(Q, 1e-15 * max(np.max(np.abs(Q)), 1e-300))
    cands = [0.0, np.pi]
    if Q.size > 1 and np.any(Q != 0):
        roots = cheb.chebroots(Q)
        keep = (np.abs(roots.imag) <= _IMAG_KEEP) & (np.abs(roots.real) <= 1.0 + _IMAG_KEEP)
        cands.extend(np.arccos(np.clip(roots.real[keep], -1.0, 1.0)).tolist())

    theta = np.unique(np.asarray(cands))
    vals = _ratio(num, den, theta)
    # Polish the candidates that may hold the minimum (round-off in a root moves the value by
    # far less than this factor); the others only report local minima.
    sel = np.flatnonzero(vals <= _POLISH_WITHIN * np.min(vals))
    theta[sel], vals[sel] = _newton_polish(num, den, theta[sel], vals[sel])
    # The direct-evaluation candidates (where the polynomial in x is ill-conditioned): the
    # grid's local minima below every polished root, i.e. the dips the roots lost, polished
    # between their grid neighbours. Where the roots are right there are none.
    g_theta, g_vals, g_lo, g_hi = _grid_minima(num, den)
    lost = g_vals < np.min(vals) * (1.0 - _GRID_LOST)
    if np.any(lost):
        g_theta, g_vals = _newton_polish(
            num, den, g_theta[lost], g_vals[lost], bounds=(g_lo[lost], g_hi[lost])
        )
        theta, vals = np.concatenate([theta, g_theta]), np.concatenate([vals, g_vals])
    order = np.argsort(theta, kind="stable")
    return theta[order], vals[order]


def _ratio(num: np.ndarray, den: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``|num(w)| / |den(w)|`` at ``w = exp(-j theta)`` (``inf`` where ``den`` vanishes)."""
    w = np.exp(-1j * theta)
    with np.errstate(divide="ignore", invalid="ignore"):
        vals = np.abs(poly.polyval(w, num)) / np.abs(poly.polyval(w, den))
    return np.where(np.isnan(vals), np.inf, vals)


def pole_refined_grid(polys: tuple[np.ndarray, ...]) -> np.ndarray:
    """Angles [rad] on ``[0, pi]``: uniform steps, refined around the roots near the circle.

    Uniform steps of ``pi / 1024``; around each root (in ``z = 1 / w``) of each polynomial
    (powers of ``w = z^-1``, lowest first) within radius 0.9 to 1.1 of the circle, offsets
    from a hundredth of its distance to the circle out to two uniform steps, geometrically
    spaced: a feature narrower than the uniform step comes from a root that close to the
    circle, and is sampled across. Sorted, ends included. The one such grid of the package
    (the modulus certificate's dips and the margins' crossings).
    """
    step = np.pi / _GRID_UNIFORM
    parts = [_UNIFORM_THETA]
    for p in polys:
        p = trim_back(np.asarray(p, dtype=float))
        if p.size < 2 or not np.any(p[1:]):
            continue
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            # A top coefficient at round-off (subnormal) overflows the companion matrix:
            # its roots lie far off the circle, where no refinement is needed.
            try:
                w_roots = np.roots(p[::-1])  # roots in w = z^-1
            except np.linalg.LinAlgError:
                continue
        z = 1.0 / w_roots[w_roots != 0]
        near = z[np.abs(np.abs(z) - 1.0) <= _GRID_POLE_BAND]
        if near.size:
            dist = np.maximum(np.abs(1.0 - np.abs(near)), 1e-12)
            lo = np.log(_GRID_FINEST * dist)
            hi = np.maximum(np.log(2.0 * step), lo)
            offsets = np.exp(lo[:, None] + (hi - lo)[:, None] * _GEOM_T)  # (roots, offsets)
            ang = np.abs(np.angle(near))[:, None]
            parts.append((ang + offsets).ravel())
            parts.append((ang - offsets).ravel())
            parts.append(ang.ravel())
    return np.sort(np.clip(np.concatenate(parts), 0.0, np.pi))


def _grid_minima(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, ...]:
    """Local minima of ``|num| / |den|`` on the pole-refined grid (module docstring):
    ``(theta, values, lower, upper)``, the bounds their grid neighbours."""
    theta = pole_refined_grid((num, den))
    vals = _ratio(num, den, theta)
    # Local minima (ends included).
    left = np.concatenate([[np.inf], vals[:-1]])
    right = np.concatenate([vals[1:], [np.inf]])
    idx = np.flatnonzero((vals <= left) & (vals <= right) & np.isfinite(vals))
    lo = theta[np.maximum(idx - 1, 0)]
    hi = theta[np.minimum(idx + 1, theta.size - 1)]
    return theta[idx], vals[idx], lo, hi


def _controller_tf(controller: object, fs: float, mode: int) -> object:
    """The SISO controller of ``mode`` (a bank's row, or the transfer function itself)."""
    controller = _as_siso_controller(controller, fs)
    if isinstance(controller, ControllerBank):
        return controller.transfer_function(mode)
    return controller


def modulus_certificate(
    plant: control.TransferFunction | control.FRD,
    controller: object,
    *,
    fs: float | None = None,
    mode: int = 0,
    extra_freqs: np.ndarray | None = None,
) -> ModulusCertificate:
    """Certified ``min |1 + G K|`` over [0, fs/2] (the modulus margin).

    Exact for a transfer-function plant and controller (every stationary point of
    ``|1 + G K|`` on the unit circle, from polynomial roots, and the local minima on a grid
    refined around every closed-loop and open-loop pole near the circle, where the
    polynomial's round-off can hide a dip; each polished on the exact expression); for a
    measured (FRD) plant, the minimum over its grid points and over refined points around
    the controller's lightly damped poles (radius above 0.9), the plant interpolated between
    its measured points. The closed loop's stability is not part of the certificate (see
    :func:`aocontrol.analysis.is_stable`).

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant.
    controller : control.TransferFunction or ControllerBank
        Controller; for a bank, ``mode`` selects the SISO controller.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    mode : int, default 0
        Mode of a controller bank.
    extra_freqs : array_like, optional
        Measured plant only: more frequencies [Hz] in [0, fs/2] at which to evaluate (the
        plant interpolated), e.g. a dense grid.

    Returns
    -------
    ModulusCertificate

    Raises
    ------
    ValueError
        An FRD plant that does not cover [0, fs/2]; an improper or non-finite system.

    Examples
    --------
    An integrator ``g / (1 - z^-1)`` on ``G = z^-1``: ``1 + L = (1 - (1 - g) z^-1) / (1 - z^-1)``,
    smallest at Nyquist (``z = -1``), ``1 - g / 2``.

    >>> from aocontrol.plant import loop_plant
    >>> from aocontrol.controllers import Integrator
    >>> cert = modulus_certificate(loop_plant(1000.0, 0.0), Integrator(0.5, fs=1000.0))
    >>> cert.exact, round(cert.value, 12), round(cert.frequency_hz, 6)
    (True, 0.75, 500.0)
    """
    fs_ = plant_fs(plant, fs)
    K = _controller_tf(controller, fs_, mode)
    if isinstance(plant, control.TransferFunction) and isinstance(K, control.TransferFunction):
        bg, ag = z_inverse_coefficients(plant, "plant")
        bk, ak = z_inverse_coefficients(K, "controller")
        return polynomial_certificate(bg, ag, bk, ak, fs_)
    return _frd_certificate(plant, K, fs_, extra_freqs)


def polynomial_certificate(
    bg: np.ndarray, ag: np.ndarray, bk: np.ndarray, ak: np.ndarray, fs: float
) -> ModulusCertificate:
    """The exact certificate of ``G = bg / ag`` and ``K = bk / ak`` (powers of ``z^-1``).

    What :func:`modulus_certificate` computes for transfer functions, from their coefficients
    (lowest power first) without building the systems: the synthesis certifies every
    candidate controller this way.
    """
    d = poly.polymul(ag, ak)
    c = poly.polyadd(d, poly.polymul(bg, bk))
    theta, vals = rational_modulus_minima(c, d)
    i = int(np.argmin(vals))
    hz = theta * fs / (2 * np.pi)
    return ModulusCertificate(float(vals[i]), float(hz[i]), True, EXACT, hz, vals)


def _frd_certificate(
    plant: object, K: object, fs: float, extra_freqs: np.ndarray | None
) -> ModulusCertificate:
    """Grid of the measured system, refined around the controller's lightly damped poles."""
    meas = plant if isinstance(plant, control.FRD) else K
    name = "plant" if isinstance(plant, control.FRD) else "controller"
    check_frd_coverage(name, meas, fs)
    f = np.asarray(meas.omega, dtype=float) / (2 * np.pi)
    f = np.clip(f, 0.0, fs / 2)
    extra = [] if extra_freqs is None else [np.asarray(extra_freqs, dtype=float).ravel()]
    if isinstance(K, control.TransferFunction):
        _, ak = z_inverse_coefficients(K, "controller")
        # Poles in z: roots of z^n A(1/z), i.e. of the reversed coefficient list.
        poles = np.roots(ak) if ak.size > 1 else np.empty(0)
        for p in poles[np.abs(poles) > _FRD_POLE_RADIUS]:
            f0 = abs(np.angle(p)) * fs / (2 * np.pi)
            bw = max((1.0 - min(abs(p), 1.0)) * fs / (2 * np.pi), 1e-9 * fs)
            extra.append(f0 + bw * np.linspace(-_FRD_WIDTHS, _FRD_WIDTHS, _FRD_POINTS))
    if extra:
        f = np.unique(np.clip(np.concatenate([f, *extra]), 0.0, fs / 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.abs(1.0 + _response(plant, f, fs) * _response(K, f, fs))
    d = np.where(np.isnan(d), np.inf, d)
    interior = np.flatnonzero(np.r_[True, d[1:] <= d[:-1]] & np.r_[d[:-1] <= d[1:], True])
    i = int(np.argmin(d))
    return ModulusCertificate(float(d[i]), float(f[i]), False, FRD, f[interior], d[interior])
