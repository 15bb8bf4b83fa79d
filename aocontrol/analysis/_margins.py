"""Stability and stability margins of a discrete AO loop.

Why not :func:`control.stability_margins` alone: in python-control 0.10.2 it misses a phase
crossover exactly at the Nyquist frequency (an integrator with a one-frame delay, ``L = g/(z-1)``,
has its -180 deg crossing at ``z = -1``: gain margin ``2/g``), and it reports margins of an
unstable loop without saying so. Here

* the loop is examined on the whole half circle, both ends included;
* a loop has several crossovers and a gain margin on both sides (a resonant controller or an
  LQG is conditionally stable: lowering its gain destabilises it too). The gain margin is an
  interval, the range of loop-gain factors ``k`` for which ``Y + k G X`` stays stable; the
  delay margin an interval, the range of latencies, the plant's pure delay moved as
  :func:`aocontrol.loop_plant` models a fractional latency; the phase margin is taken at every
  gain crossover. For rational systems each is exact (:mod:`._families`: the characteristic
  polynomial is affine in the gain, and in the fractional part of the latency within a whole
  frame, so stability changes only at parameter values where a pole crosses the circle, found
  as polynomial roots; each piece between them is decided by its closed-loop poles). A margin
  read off the phase at one crossover (``PM / omega_c``), as python-control does, is wrong on
  such loops: negative on stable ones, with a wrapped phase;
* the stability verdicts (closed-loop poles, winding numbers) are those of
  :mod:`aocontrol.analysis._stability`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import control
import numpy as np
from numpy.polynomial import polynomial as npoly

from aocontrol.analysis._certificate import (
    _cheb_of_abs2,
    _controller_tf,
    modulus_certificate,
    polynomial_certificate,
    rational_modulus_minima,
)
from aocontrol.analysis._families import (
    Pieces,
    circle_zeros,
    horner,
    stability_pieces,
)
from aocontrol.analysis._stability import (
    characteristic_roots,
    is_stable,
    poles_stable,
    winding_zeros,
)
from aocontrol.plant import (
    check_frd_coverage,
    plant_fs,
    pure_delay_form,
    split_latency,
    z_inverse_coefficients,
)
from aocontrol.plant import frequency_response_unchecked as _response

__all__ = ["Margins", "margins", "DELAY_SEARCH_FRAMES"]

logger = logging.getLogger(__name__)

#: The delay margins search this many frames beyond the nominal latency: a loop still stable
#: there reports this value, meaning "at least" (an AO latency error is a fraction of a frame).
DELAY_SEARCH_FRAMES = 32.0
# A measured plant's added latency: scan step and bisection tolerance [frames].
_FRD_DELAY_STEP = 1.0 / 32.0
_FRD_DELAY_TOL = 1e-4


@dataclass(frozen=True)
class Margins:
    """Stability margins of a SISO discrete loop ``L = G K``.

    Every margin says how far one thing can change before the closed loop loses stability,
    and each is exact for a rational plant and controller (see the module docstring; for a
    measured plant, what a margin covers is said in :attr:`delay_method`):

    * the loop gain, both ways: multiplied by any factor in ``(gain_margin_down,
      gain_margin)`` the loop stays stable. A conditionally stable loop (a resonant
      controller, an LQG) has a finite lower end; an integrator's is 0.
    * a phase shift at the gain crossovers: ``phase_margin`` is the smallest angular distance
      of ``L`` from -1 over every crossover ``|L| = 1``, so at least ``2 asin(mu / 2)`` for a
      modulus margin ``mu``.
    * the latency, both ways: the loop stays stable for every latency in
      ``[latency_frames - delay_margin_removed, latency_frames + delay_margin]``, the plant's
      pure delay moved as :func:`aocontrol.loop_plant` models a fractional latency (linear
      interpolation between whole frames: the exact sampled model of a held command).

    Attributes
    ----------
    gain_margin : float
        Factor by which the loop gain can be multiplied before instability (``inf`` if
        never). For an unstable loop, the upper end of the stabilising gain interval nearest
        to 1 (below 1: the gain must fall), ``nan`` if no gain stabilises it.
    phase_margin : float
        ``min |180 + arg L|`` [deg] over the gain crossovers (``inf`` if none). For an
        unstable loop the smallest signed value (negative: a crossover beyond -180 deg).
    modulus_margin : float
        ``min |1 + L|`` over [0, fs/2] (the inverse of ``||S||_inf``), certified by
        :func:`aocontrol.analysis.modulus_certificate`: exact over the whole circle for
        rational plant and controller (not a grid minimum: a lightly damped controller pole
        makes a dip narrower than any grid), grid plus refinement for a measured plant.
    delay_margin : float
        Latency [frames] that can be added before instability (``inf`` if the loop never
        crosses ``|L| = 1``; ``DELAY_SEARCH_FRAMES`` means at least that much). ``nan`` for
        an unstable loop.
    stable : bool
        Closed-loop stability (poles strictly inside the unit circle). Read it first.
    phase_crossover_hz : float
        Frequency [Hz] where ``L`` reaches -1 when the gain rises by ``gain_margin``
        (``nan`` if it never does).
    gain_crossover_hz : float
        Frequency [Hz] of the crossover that sets ``phase_margin`` (``nan`` if none).
    modulus_frequency_hz : float
        Frequency [Hz] of the minimum of ``|1 + L|``.
    gain_margin_down : float
        Factor below 1 to which the loop gain can fall before instability (0: any smaller
        gain is stable). For an unstable loop, the lower end of the interval of
        ``gain_margin``.
    delay_margin_removed : float
        Latency [frames] that can be removed before instability, at most
        ``latency_frames`` (equal to it: stable down to no latency). ``nan`` where the plant
        has no latency to remove (a measured plant) and for an unstable loop.
    crossovers_hz : tuple of float
        Every gain crossover ``|L| = 1`` [Hz], increasing.
    crossover_phase_margins : tuple of float
        ``180 + arg L`` [deg] wrapped to ``(-180, 180]`` at each crossover: positive, the
        phase lag that crossover tolerates; negative, it tolerates that much phase lead (the
        loop passes -180 deg above the unit circle there, as a conditionally stable loop
        does).
    latency_frames : float
        The plant's latency beyond the WFS frame [frames] read from its numerator, from
        which the delay margins move it (``nan`` for a measured plant).
    delay_method : str
        What the delay margins cover.
    """

    gain_margin: float
    phase_margin: float
    modulus_margin: float
    delay_margin: float
    stable: bool
    phase_crossover_hz: float
    gain_crossover_hz: float
    modulus_frequency_hz: float
    gain_margin_down: float
    delay_margin_removed: float
    crossovers_hz: tuple[float, ...]
    crossover_phase_margins: tuple[float, ...]
    latency_frames: float
    delay_method: str

    @classmethod
    def unknown(cls, stable: bool) -> Margins:
        """Margins that could not be computed (``nan``), with a stability verdict."""
        nan = float("nan")
        return cls(nan, nan, nan, nan, bool(stable), nan, nan, nan, nan, nan, (), (), nan, "")

    @property
    def gain_margin_db(self) -> float:
        """``gain_margin`` in dB (how far the gain can rise)."""
        return _db(self.gain_margin)

    @property
    def gain_margin_down_db(self) -> float:
        """``gain_margin_down`` in dB, negative (``-inf``: any smaller gain is stable)."""
        return _db(self.gain_margin_down)

    @property
    def gain_interval(self) -> tuple[float, float]:
        """``(gain_margin_down, gain_margin)``: the stable range of loop-gain factors."""
        return (self.gain_margin_down, self.gain_margin)

    @property
    def delay_interval(self) -> tuple[float, float]:
        """``(-delay_margin_removed, delay_margin)`` [frames]: the stable latency changes."""
        return (0.0 - self.delay_margin_removed, self.delay_margin)


def _db(factor: float) -> float:
    if np.isnan(factor):
        return float("nan")
    return float(20.0 * np.log10(factor)) if factor > 0 else -np.inf


class _LoopEval:
    """Evaluates L(theta) on the half circle, exact for TF plants, interpolated for FRD."""

    def __init__(self, plant: object, controller: object, fs: float) -> None:
        self.fs = fs
        self.plant = plant
        self.controller = controller
        omega = np.asarray(
            plant.omega if isinstance(plant, control.FRD) else controller.omega, dtype=float
        )
        self.theta = omega / fs  # rad/s * dt = rad/sample
        self.values = self(self.theta)

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        f = np.clip(np.asarray(theta, dtype=float) * self.fs / (2 * np.pi), 0.0, self.fs / 2)
        # Both validated by the caller: the unchecked evaluation.
        with np.errstate(divide="ignore", invalid="ignore"):
            return _response(self.plant, f, self.fs) * _response(self.controller, f, self.fs)


def _lerp_roots(theta: np.ndarray, values: np.ndarray) -> list[float]:
    """Zeros of a real function sampled on ``theta``, by linear interpolation."""
    out = []
    finite = np.isfinite(values)
    for i in np.flatnonzero(finite[:-1] & finite[1:] & (values[:-1] * values[1:] < 0)):
        a, b, va, vb = theta[i], theta[i + 1], values[i], values[i + 1]
        out.append(a + (b - a) * va / (va - vb))
    out.extend(theta[finite & (values == 0.0)].tolist())
    return sorted(out)


def margins(
    plant: control.TransferFunction | control.FRD,
    controller: object,
    *,
    fs: float | None = None,
    mode: int = 0,
) -> Margins:
    """Gain, phase, modulus and delay margins and closed-loop stability of ``L = G K``.

    Exact for a transfer-function plant and controller: the gain interval and the delay
    interval from the critical values of one-parameter families (every crossing of the unit
    circle by a closed-loop pole, from polynomial roots, each piece between them decided by
    its closed-loop poles), the phase margin at every gain crossover, the modulus margin
    certified over the whole circle. For a measured (FRD) plant the crossings are
    interpolated on its grid and stability decided by winding numbers; see
    :attr:`Margins.delay_method`.

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
    TypeError
        A measured (FRD) controller: its stability verdict needs its polynomials.

    Examples
    --------
    An integrator ``g / (1 - z^-1)`` on ``G = z^-1`` (no latency beyond the WFS frame): the
    closed-loop pole ``1 - k g`` stays inside the circle for loop-gain factors ``k`` in
    ``(0, 2/g)``, the -180 deg crossing at Nyquist. With a latency ``1 + f`` added, the
    closed loop ``z^3 - z^2 + g (1-f) z + g f`` is stable (Jury) while ``f < sqrt(1 - g) / g``:
    for ``g = 0.8``, a delay margin of ``1 + sqrt(0.2) / 0.8`` frames.

    >>> from aocontrol.plant import loop_plant
    >>> from aocontrol.controllers import Integrator
    >>> m = margins(loop_plant(1000.0, 0.0), Integrator(0.8, fs=1000.0))
    >>> m.stable, m.gain_margin_down, round(m.gain_margin, 12)
    (True, 0.0, 2.5)
    >>> round(m.delay_margin, 9), round(1 + 0.2**0.5 / 0.8, 9), m.delay_interval[0]
    (1.559016994, 1.559016994, 0.0)
    """
    fs_ = plant_fs(plant, fs)
    K = _controller_tf(controller, fs_, mode)
    # Margins read on a measured response are those of the measured band only: require the
    # whole of [0, fs/2], as for the stability verdict.
    for name, sys in (("plant", plant), ("controller", K)):
        if isinstance(sys, control.FRD):
            check_frd_coverage(name, sys, fs_)
    if not isinstance(K, control.TransferFunction):
        raise TypeError(
            "margins needs a transfer-function controller (its closed-loop stability comes "
            f"from its polynomials), got {type(K).__name__}"
        )
    hz = fs_ / (2 * np.pi)
    if isinstance(plant, control.TransferFunction):
        # Both checked once: the verdict, the certificate and the families from the same
        # coefficients (is_stable and modulus_certificate compute these from them too).
        bg, ag = z_inverse_coefficients(plant, "plant")
        bk, ak = z_inverse_coefficients(K, "controller")
        stable = poles_stable(characteristic_roots(bg, ag, bk, ak))
        # Modulus margin: the certificate (exact for rational systems, not a grid minimum).
        cert = polynomial_certificate(bg, ag, bk, ak, fs_)
        parts = _exact_margins(bg, ag, bk, ak, stable)
    else:
        stable = is_stable(plant, K, fs=fs_)
        cert = modulus_certificate(plant, K, fs=fs_)
        parts = _measured_margins(plant, K, fs_, stable)
    if not stable:
        logger.info("margins computed for an unstable closed loop")
    gain, crossings, delay = parts
    (k_down, k_up, t_up) = gain
    theta_c, pm_c = crossings
    if pm_c.size:
        i = int(np.argmin(np.abs(pm_c) if stable else pm_c))
        pm, f_gc = float(abs(pm_c[i]) if stable else pm_c[i]), float(theta_c[i] * hz)
    else:
        pm, f_gc = np.inf, np.nan
    added, removed, latency, method = delay
    return Margins(
        gain_margin=float(k_up),
        phase_margin=pm,
        modulus_margin=cert.value,
        delay_margin=float(added),
        stable=stable,
        phase_crossover_hz=float(t_up * hz),
        gain_crossover_hz=f_gc,
        modulus_frequency_hz=float(cert.frequency_hz),
        gain_margin_down=float(k_down),
        delay_margin_removed=float(removed),
        crossovers_hz=tuple(float(t * hz) for t in theta_c),
        crossover_phase_margins=tuple(float(p) for p in pm_c),
        latency_frames=float(latency),
        delay_method=method,
    )


def _gain_interval(pieces: Pieces, stable: bool) -> tuple[float, float, float]:
    """``(down, up, theta_up)`` from the gain family's pieces (class docstring of Margins)."""
    if stable:
        lo, hi = pieces.stable_run(pieces.piece_of(1.0))
    else:
        runs, i = [], 0
        while i < pieces.stable.size:
            if pieces.stable[i]:
                run = pieces.stable_run(i)
                runs.append(run)
                i = run[1] + 1
            else:
                i += 1
        if not runs:
            return np.nan, np.nan, np.nan

        def distance(run: tuple[int, int]) -> float:
            a, b = pieces.edges[run[0]], pieces.edges[run[1] + 1]
            with np.errstate(divide="ignore"):
                return float(np.log(a) if a > 1.0 else -np.log(b))

        lo, hi = min(runs, key=distance)
    return float(pieces.edges[lo]), float(pieces.edges[hi + 1]), float(pieces.theta[hi + 1])


def _exact_margins(bg, ag, bk, ak, stable: bool):
    """Gain interval, crossovers and delay interval of a rational loop (exact), from the
    plant's and the controller's coefficients in powers of ``z^-1``."""
    A = npoly.polymul(ag, ak)
    B = npoly.polymul(bg, bk)
    gain = _gain_interval(stability_pieces(A, B, 0.0, np.inf), stable)

    # Gain crossovers |B| = |A|: a polynomial in cos(theta) (the certificate's construction).
    nb, na = _cheb_of_abs2(B), _cheb_of_abs2(A)
    size = max(nb.size, na.size)
    diff = np.zeros(size)
    diff[: nb.size] += nb
    diff[: na.size] -= na

    def log_ratio(theta: np.ndarray) -> np.ndarray:
        w = np.exp(-1j * theta)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log(np.abs(npoly.polyval(w, B))) - np.log(np.abs(npoly.polyval(w, A)))

    hb, ha = horner(B), horner(A)

    def log_ratio1(theta: float) -> float:
        b, a = abs(hb(theta)), abs(ha(theta))
        return math.log(b) - math.log(a) if a > 0 and b > 0 else math.nan

    theta_c = circle_zeros(diff, log_ratio, (A, B), log_ratio1)
    ends = np.array([0.0, np.pi])
    theta_c = np.sort(np.concatenate([theta_c, ends[np.abs(log_ratio(ends)) < 1e-12]]))
    w = np.exp(-1j * theta_c)
    L = npoly.polyval(w, B) / npoly.polyval(w, A)
    pm_c = np.degrees(np.angle(-L))

    delay = (np.nan, np.nan, np.nan, "")
    form = pure_delay_form(bg)
    if form is not None:
        core, latency = form
        method = (
            "exact: every latency from 0 up, the plant's pure delay "
            f"z^-(1+k) ((1-f) + f z^-1) moved (searched to +{DELAY_SEARCH_FRAMES:g} frames)"
        )
        if not stable:
            added = removed = np.nan
        elif _small_gain(npoly.polymul(bk, core), A):
            # |L| < 1 at every latency (the interpolation only shrinks it): never unstable.
            added, removed = np.inf, latency
        else:
            added, removed = _latency_interval(ag, ak, bk, core, latency)
        delay = (added, removed, latency, method)
    return gain, (theta_c, pm_c), delay


# An end of the circle where |den / num| is below 1 by more than this (relative) decides
# _small_gain at once: the certificate's minimum is at most its value there.
_END_WITNESS = 1e-9


def _small_gain(num: np.ndarray, den: np.ndarray) -> bool:
    """Whether ``|num / den| < 1`` on the whole circle (exact: the certificate's minima of
    ``|den / num|``).

    The ends ``w = +-1`` are among the certificate's candidates and its polish never raises
    a value, so its minimum is at most ``|den / num|`` there: an end clearly below 1 (an
    integrator's ``den(1) = 0``) gives the certificate's verdict without computing it.
    """
    if not np.any(num):
        return True
    for w in (1.0, -1.0):
        d, n = abs(npoly.polyval(w, den)), abs(npoly.polyval(w, num))
        if n > 0 and d <= (1.0 - _END_WITNESS) * n:
            return False
    _, vals = rational_modulus_minima(den, num)
    return bool(np.min(vals) > 1.0)


def _latency_family(ag, ak, bk, core, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``C0 + f C1``: the characteristic polynomial at latency ``k + f``, ``f`` in [0, 1]."""
    e = np.concatenate([np.zeros(1 + k), npoly.polymul(bk, core)])
    c0 = npoly.polyadd(npoly.polymul(ag, ak), e)
    c1 = npoly.polysub(np.concatenate([[0.0], e]), e)  # e (w - 1)
    return c0, c1


def _latency_interval(ag, ak, bk, core, latency: float) -> tuple[float, float]:
    """``(added, removed)`` [frames]: the stable latency interval around ``latency``."""
    k0, f0 = split_latency(latency)
    tau0 = k0 + f0
    families: dict[int, Pieces] = {}

    def pieces(k: int) -> Pieces:
        # The nominal frame's family serves both searches.
        if k not in families:
            families[k] = stability_pieces(*_latency_family(ag, ak, bk, core, k), 0.0, 1.0)
        return families[k]

    # Up: whole frame by whole frame, from the nominal point.
    added, k, start = float(DELAY_SEARCH_FRAMES), k0, f0
    while k - k0 < DELAY_SEARCH_FRAMES:
        p = pieces(k)
        i = p.piece_of(start)
        if not p.stable[i]:
            added = k + start - tau0
            break
        _, hi = p.stable_run(i)
        if hi < p.stable.size - 1:
            added = k + float(p.edges[hi + 1]) - tau0
            break
        k, start = k + 1, 0.0

    # Down: to no latency at all.
    removed, k, start = tau0, k0, f0
    if f0 == 0.0:
        k, start = k0 - 1, 1.0
    while k >= 0:
        p = pieces(k)
        i = p.piece_of(start) if start < 1.0 else p.stable.size - 1
        if not p.stable[i]:
            removed = tau0 - (k + start)
            break
        lo, _ = p.stable_run(i)
        if lo > 0:
            removed = tau0 - (k + float(p.edges[lo]))
            break
        k, start = k - 1, 1.0
    return float(added), float(max(removed, 0.0))


def _measured_margins(plant: control.FRD, K: control.TransferFunction, fs: float, stable: bool):
    """Gain interval, crossovers and added-latency margin on a measured plant's grid."""
    ev = _LoopEval(plant, K, fs)
    theta, L = ev.theta, ev.values
    finite = np.isfinite(L)
    f = theta * fs / (2 * np.pi)
    G = _response(plant, f, fs)
    bk, ak = z_inverse_coefficients(K, "controller")
    w = np.exp(-1j * theta)
    Y, X = npoly.polyval(w, ak), npoly.polyval(w, bk)

    def verdict(P: np.ndarray) -> bool | None:
        try:
            return winding_zeros(P) == 0
        except ValueError:
            return None

    # Gain: critical factors at the negative-real crossings of L (interpolated).
    im = np.where(finite, L.imag, np.nan)
    cands = _lerp_roots(theta, im) + [float(theta[0]), float(theta[-1])]
    # A spurious candidate only splits a piece in two, each with its own verdict.
    crit = sorted(
        (1.0 / abs(v), t)
        for t, v in zip(cands, ev(np.asarray(cands)), strict=True)
        if np.isfinite(v) and v.real < 0 and v != 0
    )
    edges = np.array([0.0, *[c for c, _ in crit], np.inf])
    thetas = np.array([np.nan, *[t for _, t in crit], np.nan])
    verdicts = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        x = 2.0 * a + 1.0 if np.isinf(b) else (0.5 * (a + b))
        verdicts.append(bool(verdict(Y + x * G * X)))
    gain = _gain_interval(Pieces(edges, thetas, np.asarray(verdicts)), stable)

    # Gain crossovers.
    mag = np.where(finite, np.log(np.abs(L)), np.nan)
    theta_c = np.asarray(_lerp_roots(theta, mag))
    pm_c = np.degrees(np.angle(-ev(theta_c))) if theta_c.size else np.empty(0)

    # Latency added as a held (ZOH) delay d = m + f: L w^m ((1 - f) + f w), scanned then
    # bisected; nothing to remove (the measured plant's own latency is not known).
    method = (
        f"measured plant: latency added as z^-m ((1-f) + f z^-1), scanned in steps of "
        f"{_FRD_DELAY_STEP:g} frame and bisected to {_FRD_DELAY_TOL:g}, winding numbers on "
        f"the plant's grid (searched to +{DELAY_SEARCH_FRAMES:g} frames)"
    )

    def ok(d: float) -> bool | None:
        m = np.floor(d)
        fr = d - m
        D = w**m * ((1.0 - fr) + fr * w)
        return verdict(Y + G * X * D)

    added = np.nan
    if stable and np.all(np.abs(L[finite]) < 1.0) and finite.all():
        added = np.inf  # |L| < 1 on the grid, the delay only rotates it
    elif stable:
        added, last = float(DELAY_SEARCH_FRAMES), 0.0
        for d in np.arange(_FRD_DELAY_STEP, DELAY_SEARCH_FRAMES + 1e-9, _FRD_DELAY_STEP):
            v = ok(d)
            if v is None:  # the grid no longer follows the delayed phase: a lower bound
                added = last
                break
            if not v:
                lo, hi = last, d
                while hi - lo > _FRD_DELAY_TOL:
                    mid = 0.5 * (lo + hi)
                    lo, hi = (mid, hi) if ok(mid) else (lo, mid)
                added = lo
                break
            last = d
    return gain, (theta_c, pm_c), (added, np.nan, np.nan, method)
