"""Stability and stability margins of a discrete AO loop.

Why not :func:`control.stability_margins` alone: in python-control 0.10.2 it misses a phase
crossover exactly at the Nyquist frequency (an integrator with a one-frame delay, ``L = g/(z-1)``,
has its -180 deg crossing at ``z = -1``: gain margin ``2/g``), and it reports margins of an
unstable loop without saying so. Here

* the loop is evaluated on the whole half circle, both ends included, and every crossing is
  refined on the exact expression (TF) or by interpolation (FRD);
* stability comes from the closed-loop poles (TF plants: roots of ``Dg Dk + Ng Nk``, the
  unreduced characteristic polynomial, so a hidden unstable cancellation is caught), or for a
  measured FRD plant from the winding number of ``P = Y + G X`` (``K = X/Y``) around the unit
  circle, which counts closed-loop poles outside it when ``G`` is stable.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import control
import numpy as np
from scipy import optimize

from aocontrol._validation import check_frequency_grid
from aocontrol.analysis._certificate import _controller_tf, modulus_certificate
from aocontrol.plant import (
    check_frd_coverage,
    plant_fs,
    z_inverse_coefficients,
)
from aocontrol.plant import frequency_response_unchecked as _response

__all__ = ["Margins", "margins", "is_stable", "closed_loop_poles", "winding_stability"]

logger = logging.getLogger(__name__)

# Grid on the half unit circle used to bracket crossings of a TF loop before refinement.
_N_GRID = 8192
# A closed-loop pole with modulus above 1 - _POLE_TOL is not asymptotically stable.
_POLE_TOL = 1e-9
# Largest phase step of P between FRD grid points for the winding number to be trusted [rad].
_MAX_WINDING_STEP = np.pi / 3


@dataclass(frozen=True)
class Margins:
    """Stability margins of a SISO discrete loop ``L = G K``.

    Attributes
    ----------
    gain_margin : float
        Factor by which the loop gain can be multiplied before a -180 deg crossing reaches
        -1: ``min 1/|L|`` over the crossings of the negative real axis (``inf`` if none).
        Below 1 when a crossing lies beyond -1.
    phase_margin : float
        ``min(180 + arg L)`` [deg] over the gain crossovers ``|L| = 1`` (``inf`` if none).
    modulus_margin : float
        ``min |1 + L|`` over [0, fs/2] (the inverse of ``||S||_inf``), certified by
        :func:`aocontrol.analysis.modulus_certificate`: exact over the whole circle for
        rational plant and controller (not a grid minimum: a lightly damped controller pole
        makes a dip narrower than any grid), grid plus refinement for a measured plant.
    delay_margin : float
        Extra loop delay [frames] that would make the loop marginally stable:
        ``min phase_margin[rad] / theta_c`` over the gain crossovers (``inf`` if none).
    stable : bool
        Closed-loop stability (poles strictly inside the unit circle). Margins of an unstable
        loop are reported as computed, but read this flag first.
    phase_crossover_hz, gain_crossover_hz : float
        Frequencies [Hz] of the crossings that set the gain and phase margins (``nan`` if none).
    modulus_frequency_hz : float
        Frequency [Hz] of the minimum of ``|1 + L|``.
    """

    gain_margin: float
    phase_margin: float
    modulus_margin: float
    delay_margin: float
    stable: bool
    phase_crossover_hz: float
    gain_crossover_hz: float
    modulus_frequency_hz: float


class _LoopEval:
    """Evaluates L(theta) on the half circle, exact for TF plants, interpolated for FRD."""

    def __init__(self, plant: object, controller: object, fs: float) -> None:
        self.fs = fs
        self.plant = plant
        self.controller = controller
        self.exact = isinstance(plant, control.TransferFunction) and isinstance(
            controller, control.TransferFunction
        )
        if self.exact:
            self.theta = np.linspace(0.0, np.pi, _N_GRID + 1)
        else:
            omega = np.asarray(
                plant.omega if isinstance(plant, control.FRD) else controller.omega, dtype=float
            )
            self.theta = omega / fs  # rad/s * dt = rad/sample
        self.values = self(self.theta)

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        f = np.clip(np.asarray(theta, dtype=float) * self.fs / (2 * np.pi), 0.0, self.fs / 2)
        # Both validated by the caller: the unchecked evaluation (called in root refinement).
        with np.errstate(divide="ignore", invalid="ignore"):
            return _response(self.plant, f, self.fs) * _response(self.controller, f, self.fs)


def _roots_of(fun, theta: np.ndarray, values: np.ndarray, exact: bool) -> list[float]:
    """Zeros of a real function sampled on ``theta``, refined by brentq (exact) or lerp."""
    out = []
    finite = np.isfinite(values)
    for i in np.flatnonzero(finite[:-1] & finite[1:] & (values[:-1] * values[1:] < 0)):
        a, b = theta[i], theta[i + 1]
        if exact:
            va, vb = values[i], values[i + 1]

            def bracketed(t: float, a=a, b=b, va=va, vb=vb) -> float:
                # A pole of L on the circle (an integrator's at 0 Hz) makes the exact value
                # non-finite at a bracket end: use the grid's finite stand-in there.
                v = fun(t)
                return v if np.isfinite(v) else (va if t - a < b - t else vb)

            out.append(optimize.brentq(bracketed, a, b, xtol=1e-13))
        else:
            va, vb = values[i], values[i + 1]
            out.append(a + (b - a) * va / (va - vb))
    out.extend(theta[finite & (values == 0.0)].tolist())
    return out


def margins(
    plant: control.TransferFunction | control.FRD,
    controller: object,
    *,
    fs: float | None = None,
    mode: int = 0,
) -> Margins:
    """Gain, phase, modulus and delay margins and closed-loop stability of ``L = G K``.

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant (e.g. :func:`aocontrol.loop_plant`). An FRD plant is assumed
        stable (as AO plants are: pure delays) for the stability verdict.
    controller : control.TransferFunction or ControllerBank
        Controller; for a bank, ``mode`` selects the SISO controller.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    mode : int, default 0
        Mode of a controller bank.

    Returns
    -------
    Margins

    Raises
    ------
    ValueError
        An FRD plant or controller that does not cover [0, fs/2] (margins and the stability
        verdict need the whole band); an improper (non-causal) or non-finite controller or
        plant; a controller at another rate than the plant.

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> from aocontrol.controllers import Integrator
    >>> m = margins(loop_plant(1000.0, 0.0), Integrator(0.5, fs=1000.0))
    >>> round(m.gain_margin, 9), m.stable      # 2/g, crossover at Nyquist
    (4.0, True)
    """
    fs_ = plant_fs(plant, fs)
    K = _controller_tf(controller, fs_, mode)
    # Margins read on a measured response are those of the measured band only: require the
    # whole of [0, fs/2], as for the stability verdict.
    for name, sys in (("plant", plant), ("controller", K)):
        if isinstance(sys, control.FRD):
            check_frd_coverage(name, sys, fs_)
    ev = _LoopEval(plant, K, fs_)
    theta, L = ev.theta, ev.values
    finite = np.isfinite(L)

    # Phase crossovers: Im L = 0 with Re L < 0; both ends of the half circle are real axis
    # points for real-coefficient systems, and are checked explicitly (python-control misses
    # the Nyquist end).
    im = np.where(finite, L.imag, np.nan)
    cands = _roots_of(lambda t: float(ev(np.array([t]))[0].imag), theta, im, ev.exact)
    for end in (theta[0], theta[-1]):
        if end in (0.0, np.pi):
            cands.append(float(end))
    pc = [(t, ev(np.array([t]))[0]) for t in cands]
    pc = [
        (t, v)
        for t, v in pc
        if np.isfinite(v) and v.real < 0 and abs(v.imag) <= 1e-7 * max(1.0, abs(v))
    ]
    if pc:
        t_pc, v_pc = max(pc, key=lambda tv: abs(tv[1]))
        gm, f_pc = 1.0 / abs(v_pc), t_pc * fs_ / (2 * np.pi)
    else:
        gm, f_pc = np.inf, np.nan

    # Gain crossovers: |L| = 1.
    mag = np.where(finite, np.abs(L) - 1.0, np.where(np.isnan(L), np.nan, np.inf))
    gc = _roots_of(
        lambda t: float(np.abs(ev(np.array([t]))[0]) - 1.0),
        theta,
        np.where(np.isfinite(mag), mag, 1e300),
        ev.exact,
    )
    pm, dm, f_gc = np.inf, np.inf, np.nan
    for t in gc:
        v = ev(np.array([t]))[0]
        pm_t = np.degrees(np.angle(-v))  # 180 + arg L, wrapped to (-180, 180]
        if pm_t < pm:
            pm, f_gc = float(pm_t), t * fs_ / (2 * np.pi)
        if t > 0:
            dm = min(dm, np.radians(pm_t) / t)

    # Modulus margin: the certificate (exact for rational systems, not a grid minimum).
    cert = modulus_certificate(plant, K, fs=fs_)
    mm, t_mm = cert.value, cert.frequency_hz * 2 * np.pi / fs_

    stable = is_stable(plant, K, fs=fs_)
    if not stable:
        logger.info("margins computed for an unstable closed loop")
    return Margins(
        float(gm),
        float(pm),
        mm,
        float(dm),
        stable,
        float(f_pc),
        float(f_gc),
        float(t_mm * fs_ / (2 * np.pi)),
    )


def closed_loop_poles(
    plant: control.TransferFunction, controller: object, *, fs: float | None = None, mode: int = 0
) -> np.ndarray:
    """Roots of the unreduced characteristic polynomial ``Dg Dk + Ng Nk`` (z-plane).

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

    Raises
    ------
    TypeError
        If ``plant`` is an FRD (use :func:`winding_stability`).
    """
    if not isinstance(plant, control.TransferFunction):
        raise TypeError(
            "closed_loop_poles needs a control.TransferFunction plant; "
            f"got {type(plant).__name__} (use winding_stability for an FRD)"
        )
    fs_ = plant_fs(plant, fs)
    K = _controller_tf(controller, fs_, mode)
    if not isinstance(K, control.TransferFunction):
        raise TypeError("closed_loop_poles needs a transfer-function controller")
    bg, ag = z_inverse_coefficients(plant, "plant")
    bk, ak = z_inverse_coefficients(K, "controller")
    # In powers of z^-1: char(z^-1) = Ag Ak + Bg Bk; multiply by z^N to get z-plane roots.
    p = np.polynomial.polynomial.polyadd(
        np.polynomial.polynomial.polymul(ag, ak), np.polynomial.polynomial.polymul(bg, bk)
    )
    p = np.trim_zeros(p, "b")
    # p(w) with w = z^-1: z-plane roots are 1/w-roots; zero w-degree terms are poles at 0.
    # Equivalently, the z-polynomial has coefficients p (highest power of z first).
    return np.roots(p)


def winding_stability(
    plant: object,
    controller: object,
    *,
    fs: float | None = None,
    mode: int = 0,
    freqs: np.ndarray | None = None,
) -> bool:
    """Closed-loop stability from the winding number of ``P = Y + G X`` (``K = X/Y``).

    With ``w = z^-1``, ``P(w)`` is analytic on the closed unit disc when ``G`` is stable and
    causal; the closed loop is stable iff ``P`` has no zero there, i.e. iff the winding number
    of ``P`` around 0 along the unit circle is zero and ``P`` does not vanish on it. Works for
    FRD plants (evaluated on their grid, or ``freqs``) and TF plants (dense grid, refined
    where the phase of ``P`` moves fast).

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
    freqs : array_like, optional
        Grid [Hz] for a TF plant instead of the default dense one.

    Raises
    ------
    ValueError
        If the grid (the FRD's, or ``freqs``) does not cover [0, fs/2] (the missing band is
        named, see :func:`aocontrol.plant.check_frd_coverage`), or is too coarse to follow
        the phase of ``P``; an improper or non-finite controller or plant.
    """
    fs_ = plant_fs(plant, fs)
    K = _controller_tf(controller, fs_, mode)
    if not isinstance(K, control.TransferFunction):
        raise TypeError("winding_stability needs a transfer-function controller")
    if freqs is None:
        if isinstance(plant, control.FRD):
            freqs, grid_name = np.asarray(plant.omega, dtype=float) / (2 * np.pi), "plant"
        else:
            freqs, grid_name = np.linspace(0.0, fs_ / 2, _N_GRID + 1), "freqs"
    else:
        freqs, grid_name = check_frequency_grid("freqs", freqs, fs_), "freqs"
    # The contour must be the whole unit circle: refuse a grid that leaves a band unseen.
    check_frd_coverage(grid_name, freqs, fs_)
    bk, ak = z_inverse_coefficients(K, "controller")

    def char(f: np.ndarray) -> np.ndarray:
        zi = np.exp(-2j * np.pi * f / fs_)
        return np.polyval(ak[::-1], zi) + _response(plant, f, fs_) * np.polyval(bk[::-1], zi)

    P = char(freqs)
    exact = isinstance(plant, control.TransferFunction)
    for _ in range(40 if exact else 0):
        # Exact plants: refine where the phase of P moves fast (a zero close to the circle).
        big = np.abs(np.angle(P[1:] / P[:-1])) > _MAX_WINDING_STEP
        if not big.any():
            break
        mid = 0.5 * (freqs[:-1][big] + freqs[1:][big])
        freqs = np.sort(np.concatenate([freqs, mid]))
        P = char(freqs)
    return _winding_zeros(P) == 0


def _winding_zeros(P: np.ndarray) -> int:
    """Zeros inside the unit disc of ``P(w)``, ``w = z^-1``, from its values on [0, fs/2].

    ``P`` is a real-coefficient polynomial (or analytic function) sampled on a grid covering
    the upper half of the unit circle from ``w = 1`` (0 Hz) to ``w = -1`` (Nyquist), first to
    last (:func:`aocontrol.plant.check_frd_coverage`). The contour is closed from the end
    points to the real axis, where ``P`` is real; the lower half mirrors the upper one. The
    one winding count of the project (analysis and the data-driven synthesis share it).

    Parameters
    ----------
    P : numpy.ndarray of complex, shape (n_freqs,)
        ``Y + G X`` on the grid.

    Returns
    -------
    int
        Number of zeros of ``P`` inside the unit disc (``0``: closed loop stable); a zero on
        the circle (``|P|`` at most ``1e-12`` of its maximum) counts as one.

    Raises
    ------
    ValueError
        If the grid is too coarse to follow the phase of ``P`` (a step, or the closure at
        an end, above pi/3).
    """
    P = np.asarray(P, dtype=complex)
    if not np.all(np.isfinite(P)):
        raise ValueError("P = Y + G X is not finite on the grid")
    scale = np.max(np.abs(P))
    if scale == 0 or np.min(np.abs(P)) <= 1e-12 * scale:
        return 1
    dphi = np.angle(P[1:] / P[:-1])
    # Closure to the nearest real value at each end (P is real at w = 1 and w = -1).
    start = np.angle(P[0] * np.sign(P[0].real or 1.0))
    end = -np.angle(P[-1] * np.sign(P[-1].real or 1.0))
    steps = np.concatenate([[start, end], dphi])
    if np.max(np.abs(steps)) > _MAX_WINDING_STEP:
        raise ValueError(
            "frequency grid too coarse to follow the phase of Y + G X "
            f"(max step {np.max(np.abs(steps)):.2f} rad); give a denser FRD or freqs"
        )
    total = 2.0 * (start + np.sum(dphi) + end)
    return int(round(-total / (2 * np.pi)))


def is_stable(
    plant: control.TransferFunction | control.FRD,
    controller: object,
    *,
    fs: float | None = None,
    mode: int = 0,
) -> bool:
    """Closed-loop stability of the loop ``G K``.

    TF plant: all roots of the characteristic polynomial strictly inside the unit circle.
    FRD plant: winding-number test (the FRD is assumed stable, as AO plants are, and must
    cover [0, fs/2]: a verdict from part of the band is refused, not guessed).

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

    Returns
    -------
    bool

    Raises
    ------
    ValueError
        An FRD plant not covering [0, fs/2], or a grid too coarse for the winding number;
        an improper (non-causal) or non-finite controller or plant; mismatched rates.

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> from aocontrol.controllers import Integrator
    >>> G = loop_plant(1000.0, 1.0)                  # total delay d = 2 frames: g < 1
    >>> is_stable(G, Integrator(0.99, fs=1000.0)), is_stable(G, Integrator(1.01, fs=1000.0))
    (True, False)
    """
    fs_ = plant_fs(plant, fs)
    if isinstance(plant, control.FRD):
        return winding_stability(plant, controller, fs=fs_, mode=mode)
    poles = closed_loop_poles(plant, controller, fs=fs_, mode=mode)
    return bool(poles.size == 0 or np.max(np.abs(poles)) < 1.0 - _POLE_TOL)
