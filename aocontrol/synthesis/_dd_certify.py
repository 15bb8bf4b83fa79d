"""Per-mode context, parameterisation and certificates of the data-driven synthesis (private).

Private module of :mod:`aocontrol.synthesis._datadriven`: the controller ``K = X / Y`` as a
parameter vector ``v`` (see :mod:`aocontrol.synthesis._socp`), the design and dense grids,
and :class:`_ModeCertifier`, which certifies every candidate (modulus margin over the whole
circle, closed-loop stability, controller pole radius, ``|S|`` peaks between design points)
and supplies :func:`~aocontrol.synthesis._ccp.ccp` with grid rows, H2 weights and the
winding blocks.
"""

from __future__ import annotations

import logging

import numpy as np

from aocontrol.analysis import (
    ModulusCertificate,
    RobustMargin,
    modulus_certificate,
    polynomial_certificate,
    robust_from_coefficients,
    winding_stability,
    winding_zeros,
)
from aocontrol.plant import frequency_response_unchecked, tf_from_z_inverse
from aocontrol.synthesis._ccp import Certifier, Check
from aocontrol.synthesis._dd_context import DesignContext
from aocontrol.synthesis._dd_grids import _interp_matrix
from aocontrol.synthesis._socp import _P_FLOOR, POLE_FLOOR, GridData

logger = logging.getLogger(__name__)


def _p_of(
    ctx: DesignContext, f: np.ndarray, g: np.ndarray, b: np.ndarray, a: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``Y`` and ``P = Y + G X`` of ``K = b/a`` at ``f`` [Hz] (plant response ``g``)."""
    w = np.exp(-2j * np.pi * f / ctx.fs)
    Y = np.polyval(np.asarray(a)[::-1], w)
    return Y, Y + g * np.polyval(np.asarray(b)[::-1], w)


def _stable(ctx: DesignContext, dense: GridData, v: np.ndarray) -> bool:
    """Closed-loop stability of ``v``: poles (TF plant) or winding number of ``P`` (FRD)."""
    b, a = ctx.from_v(v)
    if ctx.plant_coefficients is not None:
        bg, ag = ctx.plant_coefficients
        pp = np.polynomial.polynomial
        char = np.trim_zeros(pp.polyadd(pp.polymul(ag, a), pp.polymul(bg, b)), "b")
        return bool(char.size <= 1 or np.max(np.abs(np.roots(char))) < 1.0 - 1e-9)
    # FRD: P = Y + G X has no zero in |z^-1| <= 1 iff its phase does not wind (G stable);
    # the dense grid covers [0, fs/2] (checked in _prepare). A grid too coarse to follow the
    # phase certifies nothing: the iterate is refused.
    try:
        return winding_zeros(dense.A @ v + dense.F) == 0
    except ValueError:
        return False


# Poles of the winding grid of the pole-radius constraint: uniform, and focused around the
# controller's outermost poles (where the scaled denominator turns fastest).
# (The roots decide: a step that leaves the radius between rows is damped. Measured on 32
# turbulence modes: 32 + 4 x 8 rows instead of 128 + 4 x 16 cut the solve time by ~10 % at the
# same residuals.)
_N_POLE_UNIFORM, _N_POLE_FOCUS, _POLE_FOCUS_POLES = 32, 8, 4
# A |S| peak between design points joins the grid when |S|^2 there exceeds this factor times
# the design grid's (linear) interpolation of |S|^2 and |S| exceeds _PEAK_MIN_S. A margin of 0.5
# or more bounds |S| by 2 everywhere, which bounds what a peak between points can hide; smaller
# margins allow the peaks of 13 to 240 that the objective must see. (Each peak cut costs a
# solve: with |S| <= 2 the fine check and the fallback to the start are enough.)
_PEAK_FACTOR, _PEAK_MIN_S = 2.0, 1.2
# At most this many of the start's |S| peaks seed the design grid.
_MAX_SEEDS = 4


def start_certificate(ctx: DesignContext, b: np.ndarray, a: np.ndarray) -> ModulusCertificate:
    """The modulus certificate of a mode's starting controller ``b / a`` (the initial bank's
    row), reported for a design rejected as worse than its start: the one call for it, made
    by the mode's worker where its design is worse on the input grid and by the assembly for
    any other (:func:`aocontrol.analysis.modulus_certificate` of the row's transfer function).
    """
    return modulus_certificate(ctx.plant, tf_from_z_inverse(b, a, 1.0 / ctx.fs), fs=ctx.fs)


class _ModeCertifier(Certifier):
    """Certificates, grid rows and objective weights of one mode (see :func:`ccp`)."""

    def __init__(self, ctx, psd, noise, v_ref, b0, a0, dense, mu_d):
        self.ctx, self.psd, self.noise, self.v_ref = ctx, psd, noise, v_ref
        self.b0, self.a0, self.dense, self.mu_d = b0, a0, dense, mu_d
        self.rows_per_point = ctx.rows_per_point
        self.wind = dense.take(ctx.winding_index)
        # A robust design: the winding rows of every variant plant too.
        f_w = ctx.dense_freqs[ctx.winding_index]
        self.wind_variants = [
            ctx.grid_data(f_w, frequency_response_unchecked(p, f_w, ctx.fs), ctx.modulus_margin)
            for p in ctx.variant_plants
        ]
        self._robust: dict[bytes, RobustMargin] = {}
        self.h2_f = ctx.h2_freqs
        self.h2_extra = np.empty(0)
        # Certificates already computed, by the bytes of ``v``: a candidate is certified once
        # (the start's seeds, the accepted iterate's final check and its peaks reuse it).
        self._margins: dict[bytes, ModulusCertificate] = {}
        self._stability: dict[bytes, bool] = {}

    # -- grid ---------------------------------------------------------------------------
    def _plants(self) -> tuple:
        return (self.ctx.plant, *self.ctx.variant_plants)

    def rows(self, f: np.ndarray) -> GridData:
        """Rows at ``f`` [Hz]: the nominal plant's, then each variant plant's, point after
        point (``rows_per_point`` per frequency)."""
        ctx = self.ctx
        parts = [
            ctx.grid_data(f, frequency_response_unchecked(p, f, ctx.fs), self.mu_d)
            for p in self._plants()
        ]
        return parts[0] if len(parts) == 1 else _interleave(parts)

    def p_start(self, f: np.ndarray) -> np.ndarray:
        ctx = self.ctx
        P = [
            _p_of(ctx, f, frequency_response_unchecked(p, f, ctx.fs), self.b0, self.a0)[1]
            for p in self._plants()
        ]
        return np.stack(P, axis=1).ravel()

    def weights(self, f: np.ndarray) -> tuple:
        """``(r1, rn, h)`` on the grid ``f``: the H2 quadrature on its H2 points.

        The H2 points are the design grid's and the ``|S|`` peaks added as cuts ("peaks");
        ``|S|^2`` and ``|T|^2`` are interpolated linearly between them at the input points
        (trapezoid rule on the input grid). Other points constrain the margin only.
        """
        ctx = self.ctx
        is_h2 = np.isin(f, ctx.h2_freqs) | np.isin(f, self.h2_extra)
        h2 = np.unique(f[is_h2])
        self.h2_f = h2
        H = _interp_matrix(h2, ctx.input_freqs)
        q1 = (self.psd * ctx.input_weights) @ H.T
        qn = (self.noise * ctx.input_weights) @ H.T
        t = q1 + qn
        with np.errstate(invalid="ignore", divide="ignore"):
            r1_h = np.where(t > 0, np.sqrt(q1 / t), 0.0)
            rn_h = np.where(t > 0, np.sqrt(qn / t), 0.0)
        pos = np.searchsorted(h2, f[is_h2])
        k = self.rows_per_point  # the variant plants' rows constrain the margin only
        r1, rn, h = np.zeros(f.size * k), np.zeros(f.size * k), np.zeros(f.size * k)
        idx = np.flatnonzero(is_h2) * k
        r1[idx], rn[idx], h[idx] = r1_h[pos], rn_h[pos], t[pos] / self.v_ref
        return r1, rn, h

    # -- winding blocks -----------------------------------------------------------------
    def winding(self, v: np.ndarray | None) -> list:
        ctx = self.ctx
        if v is None:
            Pw = _p_of(ctx, ctx.dense_freqs[ctx.winding_index], self.wind_g, self.b0, self.a0)[1]
        else:
            Pw = self.wind.A @ v + self.wind.F
        blocks = [(self.wind.A, self.wind.F, Pw, _P_FLOOR)]
        for wv, p in zip(self.wind_variants, ctx.variant_plants, strict=True):
            if v is None:
                f_w = ctx.dense_freqs[ctx.winding_index]
                g_w = frequency_response_unchecked(p, f_w, ctx.fs)
                Pv = _p_of(ctx, f_w, g_w, self.b0, self.a0)[1]
            else:
                Pv = wv.A @ v + wv.F
            blocks.append((wv.A, wv.F, Pv, _P_FLOOR))
        if ctx.max_pole_radius is not None:
            A = self._pole_rows(v)
            Ys = A @ v + 1.0 if v is not None else np.ones(A.shape[0], complex)
            blocks.append((A, np.ones(A.shape[0], complex), Ys, POLE_FLOOR))
        return blocks

    @property
    def wind_g(self) -> np.ndarray:
        return self.ctx.dense_response[self.ctx.winding_index]

    def _pole_rows(self, v: np.ndarray | None) -> np.ndarray:
        """Rows of ``Ys(u) = Y'(u / rho)`` on the unit circle: ``Ys = A v + 1``."""
        ctx, rho = self.ctx, self.ctx.max_pole_radius
        theta = [np.linspace(0.0, np.pi, _N_POLE_UNIFORM)]
        poles = ctx.free_poles(v) if v is not None else np.empty(0)
        poles = poles[np.argsort(-np.abs(poles))][:_POLE_FOCUS_POLES]
        for i in range(_POLE_FOCUS_POLES):
            if i < poles.size:
                # The root of Ys lies 1 - |p| / rho from the circle: its phase turns over
                # an arc of about that width around the pole's angle.
                th0, width = abs(np.angle(poles[i])), max(1.0 - abs(poles[i]) / rho, 1e-12)
            else:
                th0, width = 0.0, 1e-3
            theta.append(np.clip(th0 + width * np.linspace(-4, 4, _N_POLE_FOCUS), 0.0, np.pi))
        u = np.exp(-1j * np.concatenate(theta))
        A = np.zeros((u.size, 2 * ctx.free_order + 1), complex)
        i = np.arange(1, ctx.free_order + 1)
        A[:, ctx.free_order + 1 :] = (u[:, None] / rho) ** i
        return A

    @property
    def n_pole_rows(self) -> int:
        return _N_POLE_UNIFORM + _N_POLE_FOCUS * _POLE_FOCUS_POLES

    def seeds(self, v: np.ndarray) -> np.ndarray:
        """The start's ``|S|`` peaks inside the input range: H2 and margin points.

        The certified local minima of ``|1 + G K|`` below 1 (``|S| > 1``, worst first), not
        on the design grid: the steps tend to deepen such a dip between design points.
        """
        cert = self.margin(v)
        ctx = self.ctx
        f, m = cert.minima_hz, cert.minima
        keep = (
            (m < 1.0)
            & (f > ctx.input_freqs[0])
            & (f < ctx.input_freqs[-1])
            & ~np.isin(f, self.h2_f)
        )
        f = f[keep][np.argsort(m[keep])][:_MAX_SEEDS]
        self.h2_extra = np.union1d(self.h2_extra, f)
        return f

    # -- certificates -------------------------------------------------------------------
    def margin(self, v: np.ndarray) -> ModulusCertificate:
        """The modulus-margin certificate of ``v`` (exact for a TF plant; computed once)."""
        key = np.asarray(v, dtype=float).tobytes()
        cert = self._margins.get(key)
        if cert is None:
            ctx = self.ctx
            b, a = ctx.from_v(v)
            if ctx.plant_coefficients is not None:
                cert = polynomial_certificate(*ctx.plant_coefficients, b, a, ctx.fs)
            else:
                K = tf_from_z_inverse(b, a, 1.0 / ctx.fs)
                cert = modulus_certificate(ctx.plant, K, fs=ctx.fs, extra_freqs=ctx.dense_freqs)
            self._margins[key] = cert
        return cert

    def robust(self, v: np.ndarray) -> RobustMargin | None:
        """The certified margin over the uncertainty set (``None`` without one; computed
        once per candidate)."""
        ctx = self.ctx
        if ctx.uncertainty is None:
            return None
        key = np.asarray(v, dtype=float).tobytes()
        rm = self._robust.get(key)
        if rm is None:
            b, a = ctx.from_v(v)
            rm = self._robust[key] = robust_from_coefficients(
                *ctx.plant_coefficients, b, a, ctx.fs, ctx.uncertainty, ctx.modulus_margin
            )
        return rm

    def stable(self, v: np.ndarray) -> bool:
        """Closed-loop stability of ``v`` (:func:`_stable`; computed once)."""
        key = np.asarray(v, dtype=float).tobytes()
        ok = self._stability.get(key)
        if ok is None:
            ok = self._stability[key] = _stable(self.ctx, self.dense, v)
        return ok

    def check(self, v: np.ndarray, v_prev: np.ndarray | None = None) -> Check:
        """Pole radius, closed-loop stability, certified margin and |S| peaks of ``v``."""
        ctx = self.ctx
        empty = np.empty(0)
        if ctx.max_pole_radius is not None:
            poles = ctx.free_poles(v)
            if poles.size and np.max(np.abs(poles)) > ctx.max_pole_radius * (1 + 1e-12):
                return Check(False, empty, "poles")
        # The margin first: a closed-loop pole crossing the circle makes |1 + G K| vanish
        # there, so the certificate also locates a lost stability.
        cert = self.margin(v)
        bad = cert.below(ctx.modulus_margin)
        if bad.size:
            logger.debug("margin certificate failed at %s Hz (min %.4g)", bad, cert.value)
            return Check(False, bad, "margin")
        if not self.stable(v):
            # A closed-loop pole crossed the circle between winding points: there P turned
            # by more than 90 degrees from the previous (stabilising) controller's.
            P = self.dense.A @ v + self.dense.F
            if v_prev is not None:
                Pb = self.dense.A @ v_prev + self.dense.F
            else:
                Pb = _p_of(ctx, ctx.dense_freqs, ctx.dense_response, self.b0, self.a0)[1]
            cos = (P * np.conj(Pb)).real / (np.abs(P) * np.abs(Pb) + 1e-300)
            return Check(False, ctx.dense_freqs[np.argsort(cos)[:16]], "stability")
        rm = self.robust(v)
        if rm is not None and not (rm.stable and rm.value >= ctx.modulus_margin):
            logger.debug("robust certificate failed at %.4g Hz (bound %.4g)",
                         rm.worst_frequency_hz, rm.value)  # fmt: skip
            return Check(False, np.array([rm.worst_frequency_hz]), "margin")
        peaks = self._misrepresented_peaks(cert, v)
        if peaks.size:
            # They join the grid as H2 points (margin cuts only constrain).
            self.h2_extra = np.union1d(self.h2_extra, peaks[:4])
            return Check(False, peaks, "peaks")
        return Check(True, empty)

    def check_final(self, v: np.ndarray) -> tuple[float, str] | None:
        """``(certified margin, method)`` if ``v`` passes every certificate, else None."""
        ctx = self.ctx
        if ctx.max_pole_radius is not None:
            poles = ctx.free_poles(v)
            if poles.size and np.max(np.abs(poles)) > ctx.max_pole_radius * (1 + 1e-12):
                return None
        if ctx.plant_coefficients is not None:
            # The roots of the characteristic polynomial A_G A_K + B_G B_K (what
            # aocontrol.analysis.is_stable computes for a TF plant, same tolerance).
            stable = self.stable(v)
        else:
            b, a = ctx.from_v(v)
            K = tf_from_z_inverse(b, a, 1.0 / ctx.fs)
            try:
                # The winding number on the dense grid (the FRD's own grid may be too coarse
                # to follow the phase of Y + G X near a sharp resonance of the controller).
                stable = winding_stability(ctx.plant, K, fs=ctx.fs, freqs=ctx.dense_freqs)
            except ValueError:  # winding number not resolved by the grid
                stable = False
        cert = self.margin(v)
        if not stable or cert.value < ctx.modulus_margin * (1 - 1e-9):
            return None
        rm = self.robust(v)
        if rm is not None and not (rm.stable and rm.value >= ctx.modulus_margin * (1 - 1e-9)):
            return None
        return cert.value, cert.method

    def _misrepresented_peaks(self, cert: ModulusCertificate, v: np.ndarray) -> np.ndarray:
        """|S| peaks inside the input range that the H2 grid's interpolation understates.

        The objective sees ``|S|^2`` interpolated linearly between H2 points: a peak between
        them (a lightly damped closed-loop pole, which a small margin allows) would be
        invisible to it. Such a peak joins the grid as an H2 point. Exact plants only (the
        peaks are the certificate's local minima of ``|1 + G K|``).
        """
        if not cert.exact or cert.minima.size == 0:
            return np.empty(0)
        ctx, h2 = self.ctx, self.h2_f
        f, s2 = cert.minima_hz, 1.0 / np.maximum(cert.minima, 1e-300) ** 2
        inside = (f > max(ctx.input_freqs[0], h2[0])) & (f < min(ctx.input_freqs[-1], h2[-1]))
        inside &= (s2 > _PEAK_MIN_S**2) & ~np.isin(f, h2)
        if not inside.any():
            return np.empty(0)
        f, s2 = f[inside], s2[inside]
        # |S|^2 at the neighbouring H2 points, interpolated (what the objective sees).
        j = np.clip(np.searchsorted(h2, f) - 1, 0, h2.size - 2)
        nb = np.concatenate([h2[j], h2[j + 1]])
        g_nb = frequency_response_unchecked(ctx.plant, nb, ctx.fs)
        Y, P = _p_of(ctx, nb, g_nb, *ctx.from_v(v))
        s2_nb = np.abs(Y) ** 2 / np.abs(P) ** 2
        t = (f - h2[j]) / (h2[j + 1] - h2[j])
        interp = (1 - t) * s2_nb[: f.size] + t * s2_nb[f.size :]
        worse = s2 > _PEAK_FACTOR * interp
        order = np.argsort(-(s2 / interp)[worse])
        return f[worse][order]


def _interleave(parts: list[GridData]) -> GridData:
    """Grids of the same points as one, their rows point after point."""

    def mix(arrays: list[np.ndarray]) -> np.ndarray:
        return np.stack(arrays, axis=1).reshape((-1, *arrays[0].shape[1:]))

    return GridData(
        mix([p.AY for p in parts]),
        mix([p.AX for p in parts]),
        mix([p.F for p in parts]),
        mix([p.mu_rows() for p in parts]),
        parts[0].hinf_weight,
    )
