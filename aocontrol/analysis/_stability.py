"""Closed-loop stability of a discrete AO loop: the verdicts every analysis relies on.

* TF plants: the roots of the unreduced characteristic polynomial ``Dg Dk + Ng Nk``, so a
  hidden unstable cancellation is caught (:func:`closed_loop_poles`, :func:`is_stable`);
* measured (FRD) plants: the winding number of ``P = Y + G X`` (``K = X/Y``) around the unit
  circle, which counts closed-loop poles outside it when ``G`` is stable
  (:func:`winding_stability`, :func:`winding_zeros`, the one winding count of the project:
  the analysis and the data-driven synthesis share it).
"""

from __future__ import annotations

import control
import numpy as np

from aocontrol._validation import check_frequency_grid
from aocontrol.analysis._certificate import _controller_tf, trim_back
from aocontrol.analysis._families import POLE_TOL
from aocontrol.plant import check_frd_coverage, plant_fs, z_inverse_coefficients
from aocontrol.plant import frequency_response_unchecked as _response

__all__ = ["closed_loop_poles", "is_stable", "winding_stability", "winding_zeros"]

# Dense grid of the winding-number test of a TF plant (refined where P turns fast).
_N_GRID = 8192
# Largest phase step of P between FRD grid points for the winding number to be trusted [rad].
_MAX_WINDING_STEP = np.pi / 3


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
    return characteristic_roots(bg, ag, bk, ak)


def characteristic_roots(
    bg: np.ndarray, ag: np.ndarray, bk: np.ndarray, ak: np.ndarray
) -> np.ndarray:
    """Closed-loop poles (z-plane) of ``G = bg / ag`` and ``K = bk / ak`` (powers of ``z^-1``,
    lowest first): the roots of ``Ag Ak + Bg Bk``, unreduced. What
    :func:`closed_loop_poles` computes, from coefficients already checked."""
    # In powers of z^-1: char(z^-1) = Ag Ak + Bg Bk; multiply by z^N to get z-plane roots.
    p = np.polynomial.polynomial.polyadd(
        np.polynomial.polynomial.polymul(ag, ak), np.polynomial.polynomial.polymul(bg, bk)
    )
    p = trim_back(p)
    # p(w) with w = z^-1: z-plane roots are 1/w-roots; zero w-degree terms are poles at 0.
    # Equivalently, the z-polynomial has coefficients p (highest power of z first).
    return np.roots(p)


def poles_stable(poles: np.ndarray) -> bool:
    """The verdict of :func:`is_stable` on closed-loop poles: every ``|z| < 1 - POLE_TOL``."""
    return bool(poles.size == 0 or np.max(np.abs(poles)) < 1.0 - POLE_TOL)


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
    return winding_zeros(P) == 0


def winding_zeros(P: np.ndarray) -> int:
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
    return poles_stable(closed_loop_poles(plant, controller, fs=fs_, mode=mode))
