"""The modulus margin over an uncertainty set: every loop gain and latency of an interval.

A controller is designed on a model; the instrument's loop gain (optical gains, a DM's gain)
and latency differ from it. :class:`UncertaintySet` is the box of loop-gain factors
``k in [k_lo, k_hi]`` and latency changes ``d in [d_lo, d_hi]`` frames (the plant's pure delay
moved as :func:`aocontrol.loop_plant` models a fractional latency, :func:`aocontrol.with_latency`);
:func:`robust_margin` certifies a lower bound of ``min |1 + k L_d|`` over the whole box and
over the unit circle, and the closed-loop stability of every loop in it:

* in the gain, exactly. With ``L = B / A``, ``|1 + k L|^2`` is a convex quadratic in ``k``: its
  minimum over ``[k_lo, k_hi]`` is at an end or, where ``k* = -Re(B conj A) / |B|^2`` lies
  inside, ``|Im(B conj A)| / (|A| |B|) = |B A~ - B~ A| / (2 |A| |B|)`` on the circle (``A~``:
  the reversed polynomial). Both ends are the exact certificate of
  :func:`~aocontrol.analysis.modulus_certificate` (polynomial roots); the interior value is a
  ratio of polynomial moduli whose every stationary point is found the same way
  (:func:`~aocontrol.analysis.rational_modulus_minima`), kept where ``k*`` is inside.
* in the latency, exactly too. Between two knots (the interval's ends, the nominal latency
  and the whole frames inside) the numerator is affine in the latency, ``B_t = B_a + t dB``,
  so with ``m = k t`` the loop's ``A + k B_a + m dB`` is affine in ``(k, m)`` over a
  trapezoid. At each frequency the smallest ``|1 + k L|`` over it is the distance from 0 to
  the image polygon, reached on its edges unless 0 is inside; at 0 Hz and Nyquist the
  polygon is a real segment covered by its edges, and moving with the frequency 0 can only
  enter it through an edge. So the minimum over the piece is the smallest over its four
  edges: the gain interval at each of its two latencies (above) and the latency segment at
  each end of the gain interval, ``min |C + t D| / |A|`` for ``t in [0, 1]``, an end or the
  foot of the perpendicular ``|D C~ - D~ C| / (2 |D| |A|)``, found the same way.
* stability: every loop of the box is stable if the nominal one is and the bound is above 0
  (a closed-loop pole reaching the circle would make ``1 + k L_d`` vanish there); the loops at
  the grid latencies are also checked by their poles.

The value is exact (to the polynomial roots' accuracy), in the gain and in the latency alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import control
import numpy as np
from numpy.polynomial import polynomial as npoly

from aocontrol.analysis._certificate import _controller_tf, rational_modulus_minima
from aocontrol.analysis._families import poly_stable
from aocontrol.plant import plant_fs, pure_delay_form, split_latency, z_inverse_coefficients

__all__ = ["RobustMargin", "UncertaintySet", "robust_from_coefficients", "robust_margin"]

# A bound at or below this is zero to round-off: a closed-loop pole may sit on the circle.
_ZERO = 1e-9
_METHOD_GAIN = (
    "exact in the loop gain (polynomial roots: both ends and the interior's stationary points)"
)
_METHOD_LATENCY = (
    "exact in the latency (each whole-frame piece a box whose four edges are segment "
    "families, polynomial roots)"
)


@dataclass(frozen=True)
class UncertaintySet:
    """Loop-gain factors and latency changes a loop must survive (a box).

    Parameters
    ----------
    gain : (float, float), default (1, 1)
        Interval of factors on the loop gain, ``0 < low <= 1 <= high`` (``(0.7, 1.3)``: +-30 %).
    latency : (float, float), default (0, 0)
        Interval of latency changes [frames], ``low <= 0 <= high`` (``(-0.3, 0.3)``), the
        true latency staying >= 0.
    latency_step : float, default 0.025
        Largest step [frames] of :meth:`latencies`, a grid for scans and plots (the
        certificate, :func:`robust_margin`, is exact in the latency and does not use it).

    Raises
    ------
    ValueError
        A reversed or empty-of-nominal interval, a gain interval reaching 0 or not finite,
        a step <= 0.
    """

    gain: tuple[float, float] = (1.0, 1.0)
    latency: tuple[float, float] = (0.0, 0.0)
    latency_step: float = 0.025

    def __post_init__(self) -> None:
        lo, hi = (float(x) for x in self.gain)
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"gain must be a finite interval, got {self.gain!r}")
        if lo > hi:
            raise ValueError(f"gain interval reversed: got ({lo:g}, {hi:g}), expected low <= high")
        if lo <= 0:
            raise ValueError(
                f"gain interval must stay above 0 (a loop gain of 0 is no loop), got ({lo:g}, "
                f"{hi:g})"
            )
        if not lo <= 1.0 <= hi:
            raise ValueError(f"gain interval must hold the nominal 1, got ({lo:g}, {hi:g})")
        dlo, dhi = (float(x) for x in self.latency)
        if not (math.isfinite(dlo) and math.isfinite(dhi)):
            raise ValueError(f"latency must be a finite interval, got {self.latency!r}")
        if dlo > dhi:
            raise ValueError(
                f"latency interval reversed: got ({dlo:g}, {dhi:g}), expected low <= high"
            )
        if not dlo <= 0.0 <= dhi:
            raise ValueError(
                f"latency interval must hold the nominal 0, got ({dlo:g}, {dhi:g}) frames"
            )
        step = float(self.latency_step)
        if not step > 0:
            raise ValueError(f"latency_step must be > 0 frames, got {self.latency_step!r}")
        object.__setattr__(self, "gain", (lo, hi))
        object.__setattr__(self, "latency", (dlo, dhi))
        object.__setattr__(self, "latency_step", step)

    @property
    def nominal_only(self) -> bool:
        """Whether the set is the nominal loop alone."""
        return self.gain == (1.0, 1.0) and self.latency == (0.0, 0.0)

    def knots(self, nominal: float) -> np.ndarray:
        """The latencies [frames] that split the interval around ``nominal`` into pieces on
        which the loop is affine in the latency: its ends (the true latency >= 0), the
        nominal and the whole frames inside."""
        lo = max(nominal + self.latency[0], 0.0)
        hi = nominal + self.latency[1]
        knots = [lo, nominal, hi, *range(math.ceil(lo), math.floor(hi) + 1)]
        return np.unique(np.clip(knots, lo, hi))

    def latencies(self, nominal: float) -> np.ndarray:
        """A grid of latencies [frames] around ``nominal``: the :meth:`knots` and steps of at
        most ``latency_step`` between them."""
        knots = self.knots(nominal)
        out = [knots[:1]]
        for a, b in zip(knots[:-1], knots[1:], strict=True):
            n = max(1, math.ceil((b - a) / self.latency_step - 1e-9))
            out.append(np.linspace(a, b, n + 1)[1:])
        return np.concatenate(out)

    def corners(self) -> list[tuple[float, float]]:
        """``(gain, latency change)`` of the box's corners, the nominal apart: the loops a
        design constrains explicitly at every point (the certificate covers the rest, and
        its worst frequencies join the design grid)."""
        gains = sorted({self.gain[0], self.gain[1]})
        lats = sorted({self.latency[0], self.latency[1]})
        return [(k, d) for k in gains for d in lats if (k, d) != (1.0, 0.0)]

    def describe(self) -> str:
        """The set in words (for results and reports)."""
        g, d = self.gain, self.latency
        return (
            f"loop gain x[{g[0]:g}, {g[1]:g}], latency {d[0]:+g}..{d[1]:+g} frames (both "
            "certified exactly)"
        )


@dataclass(frozen=True)
class RobustMargin:
    """A certified lower bound of the modulus margin over an uncertainty set.

    Attributes
    ----------
    value : float
        Lower bound of ``min |1 + k L_d|`` over the box and the unit circle.
    stable : bool
        Every loop of the box is stable (certified: see the module docstring).
    worst_gain, worst_latency, worst_frequency_hz : float
        Where the smallest grid value is reached (gain factor, latency [frames], [Hz]).
    latency_bound : float
        What a bound between latency grid points cost the value: 0, the certificate being
        exact in the latency (kept for the results written before it was).
    latencies : numpy.ndarray
        The knots of the latency interval [frames]: its ends, the nominal latency and the
        whole frames inside (between two, the loop is affine in the latency).
    method : str
        What the value covers.
    """

    value: float
    stable: bool
    worst_gain: float
    worst_latency: float
    worst_frequency_hz: float
    latency_bound: float
    latencies: np.ndarray
    method: str

    def below(self, margin: float) -> np.ndarray:
        """``[worst_frequency_hz]`` if the value is below ``margin``, else empty (a cut)."""
        return np.array([self.worst_frequency_hz]) if self.value < margin else np.empty(0)


def _reversed(p: np.ndarray, n: int) -> np.ndarray:
    """``w^n p(1/w)`` (coefficients reversed, padded to degree ``n``)."""
    out = np.zeros(n + 1)
    out[: p.size] = p
    return out[::-1]


def _gain_family_minimum(A: np.ndarray, B: np.ndarray, k_lo: float, k_hi: float):
    """``(value, gain, theta)``: ``min |A + k B| / |A|`` over ``k in [k_lo, k_hi]`` and the
    circle, exact (module docstring): the segment family ``C = A + k_lo B``,
    ``D = (k_hi - k_lo) B`` of :func:`_segment_minimum`."""
    value, t, theta = _segment_minimum(
        npoly.polyadd(A, k_lo * B), (k_hi - k_lo) * B, A, end=npoly.polyadd(A, k_hi * B)
    )
    gain = k_hi if t == 1.0 else k_lo + t * (k_hi - k_lo)
    return value, float(gain), theta


def robust_margin(
    plant: control.TransferFunction,
    controller: object,
    uncertainty: UncertaintySet,
    *,
    fs: float | None = None,
    mode: int = 0,
) -> RobustMargin:
    """Certified modulus margin and stability of ``G K`` over an uncertainty set.

    Parameters
    ----------
    plant : control.TransferFunction
        Nominal loop plant (its pure delay in the form of :func:`aocontrol.loop_plant`, any
        other factor kept: a DM's response).
    controller : control.TransferFunction or ControllerBank
        Controller; for a bank, ``mode`` selects the SISO controller.
    uncertainty : UncertaintySet
        The box of loop gains and latency changes.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    mode : int, default 0
        Mode of a controller bank.

    Returns
    -------
    RobustMargin

    Raises
    ------
    TypeError
        A measured (FRD) plant or controller (the certificate needs polynomials).
    ValueError
        A latency interval on a plant without a pure delay to move.

    Examples
    --------
    An integrator on ``z^-2`` is stable for ``g < 1`` (Jury): with ``g = 0.4`` and the loop gain
    up to 1.5x it keeps a margin; up to 3x (``g = 1.2``) it does not.

    >>> from aocontrol.plant import loop_plant
    >>> from aocontrol.controllers import Integrator
    >>> G, K = loop_plant(1000.0, 1.0), Integrator(0.4, fs=1000.0)
    >>> robust_margin(G, K, UncertaintySet(gain=(0.5, 1.5))).stable
    True
    >>> robust_margin(G, K, UncertaintySet(gain=(0.5, 3.0))).stable
    False
    """
    fs_ = plant_fs(plant, fs)
    K = _controller_tf(controller, fs_, mode)
    if not isinstance(plant, control.TransferFunction) or not isinstance(
        K, control.TransferFunction
    ):
        raise TypeError("robust_margin needs a transfer-function plant and controller")
    bg, ag = z_inverse_coefficients(plant, "plant")
    bk, ak = z_inverse_coefficients(K, "controller")
    return robust_from_coefficients(bg, ag, bk, ak, fs_, uncertainty)


def _segment_minimum(
    C: np.ndarray, D: np.ndarray, A: np.ndarray, end: np.ndarray | None = None
) -> tuple[float, float, float]:
    """``(value, t, theta)``: ``min |C + t D| / |A|`` over ``t in [0, 1]`` and the circle,
    exact: at an end (:func:`rational_modulus_minima` of ``C`` and ``C + D`` over ``A``;
    ``end``, if given, is ``C + D`` as the caller computed it) or where the foot of the
    perpendicular ``t* = -Re(D conj C) / |D|^2`` lies inside, the distance
    ``|Im(D conj C)| / (|D| |A|) = |D C~ - D~ C| / (2 |D| |A|)`` (``~``: reversed)."""
    best = (np.inf, 0.0, 0.0)
    for t, P in ((0.0, C), (1.0, npoly.polyadd(C, D) if end is None else end)):
        theta, vals = rational_modulus_minima(P, A)
        i = int(np.argmin(vals))
        if vals[i] < best[0]:
            best = (float(vals[i]), t, float(theta[i]))
    if not np.any(D):
        return best
    n = max(C.size, D.size) - 1
    N = npoly.polysub(npoly.polymul(D, _reversed(C, n)), npoly.polymul(_reversed(D, n), C))
    theta, vals = rational_modulus_minima(N, 2.0 * npoly.polymul(D, A))
    w = np.exp(-1j * theta)
    c, d = npoly.polyval(w, C), npoly.polyval(w, D)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_star = -(d * np.conj(c)).real / np.abs(d) ** 2
    inside = np.isfinite(vals) & (t_star > 0.0) & (t_star < 1.0)
    if inside.any():
        i = int(np.flatnonzero(inside)[np.argmin(vals[inside])])
        if vals[i] < best[0]:
            best = (float(vals[i]), float(t_star[i]), float(theta[i]))
    return best


def robust_from_coefficients(
    bg: np.ndarray,
    ag: np.ndarray,
    bk: np.ndarray,
    ak: np.ndarray,
    fs: float,
    uset: UncertaintySet,
    target: float | None = None,
) -> RobustMargin:
    """:func:`robust_margin` of ``G = bg / ag`` and ``K = bk / ak`` (powers of ``z^-1``), from
    their coefficients: the synthesis certifies every candidate this way.

    Exact in the gain and in the latency (module docstring): the value does not depend on
    ``target``, kept for the callers that pass the margin they need.

    Parameters
    ----------
    bg, ag : numpy.ndarray
        Plant numerator and denominator, powers of ``z^-1`` (lowest first).
    bk, ak : numpy.ndarray
        Controller numerator and denominator, likewise.
    fs : float
        Loop rate [Hz].
    uset : UncertaintySet
        The box of loop gains and latency changes.
    target : float, optional
        A margin the caller needs: refinement stops once the bound is above it.

    Returns
    -------
    RobustMargin
    """
    A = npoly.polymul(ag, ak)
    k_lo, k_hi = uset.gain
    if uset.latency == (0.0, 0.0):
        val, kk, th = _gain_family_minimum(A, npoly.polymul(bg, bk), k_lo, k_hi)
        stable = poly_stable(npoly.polyadd(A, npoly.polymul(bg, bk)))
        return RobustMargin(
            value=val, stable=bool(stable and val > _ZERO), worst_gain=float(kk),
            worst_latency=float("nan"), worst_frequency_hz=float(th * fs / (2 * np.pi)),
            latency_bound=0.0, latencies=np.empty(0), method=_METHOD_GAIN,
        )  # fmt: skip
    form = pure_delay_form(bg)
    if form is None:
        raise ValueError("a latency interval needs a plant with a pure delay to move")
    core, nominal = form
    e0 = npoly.polymul(bk, core)

    def numerator(tau: float) -> np.ndarray:
        """``B`` of the loop at latency ``tau``: ``K core z^-(1+k) ((1-f) + f z^-1)``."""
        k, f = split_latency(tau)
        e = np.concatenate([np.zeros(1 + k), e0])
        return npoly.polyadd(e * (1.0 - f), np.concatenate([[0.0], e]) * f)

    # Knots: the interval's ends, the nominal and the whole frames inside; between two knots
    # B is affine in the latency, so each piece is a box whose edges are segment families.
    knots = uset.knots(nominal)
    B = {float(t): numerator(float(t)) for t in knots}
    best = (np.inf, 1.0, nominal, 0.0)  # value, gain, latency, theta
    for t in knots:  # the edges of constant latency: the gain interval at each knot
        val, kk, th = _gain_family_minimum(A, B[float(t)], k_lo, k_hi)
        if val < best[0]:
            best = (val, kk, float(t), th)
    for ta, tb in zip(knots[:-1], knots[1:], strict=True):  # edges of constant gain
        dB = npoly.polysub(B[float(tb)], B[float(ta)])
        for k in sorted({k_lo, k_hi}):
            val, t, th = _segment_minimum(npoly.polyadd(A, k * B[float(ta)]), k * dB, A)
            if val < best[0]:
                best = (val, k, float(ta + t * (tb - ta)), th)
    value, kk, tau, th = best
    stable = poly_stable(npoly.polyadd(A, numerator(nominal)))
    return RobustMargin(
        value=float(value),
        stable=bool(stable and value > _ZERO),
        worst_gain=float(kk),
        worst_latency=float(tau),
        worst_frequency_hz=float(th * fs / (2 * np.pi)),
        latency_bound=0.0,
        latencies=knots,
        method=_METHOD_GAIN + f"; {_METHOD_LATENCY} ({knots.size - 1} pieces)",
    )
