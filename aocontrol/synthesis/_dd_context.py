"""The design context of one data-driven call, and the controller's parameterisation.

Private module of :mod:`aocontrol.synthesis._datadriven`. Every mode of one call shares a
:class:`DesignContext` (pickled once per chunk of modes for the worker processes): the plant
and its responses on the grids, the objective's data grids, the parameter set and the solver
settings. The controller ``K = X / Y`` of a mode is the parameter vector ``v`` of
:mod:`aocontrol.synthesis._socp`::

    X = sum_{i=0}^{q} x_i w^i,   Y = F (1 + sum_{i=1}^{q} y_i w^i),   w = z^-1,
    v = [x_0 * s .. x_q * s, y_1 .. y_q]     (s: the plant response scale)

with ``q`` the free order and ``F`` the fixed factor of the denominator (an integrator
``1 - z^-1``, a leak, or 1); the methods here map between ``v`` and coefficients ``(b, a)``
and build the grid rows of the convex problem.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from aocontrol.synthesis._socp import GridData

__all__ = ["DesignContext", "MARGIN_SAFETY", "ModeItem", "design_margin", "exact_quotient"]

#: The design grid enforces the modulus margin this much higher (relative) than asked, so
#: that the certified margin over the whole circle meets the asked one; at most 0.999.
MARGIN_SAFETY = 0.05
# Relative size of a division's remainder below which the division is exact.
_EXACT_RTOL = 1e-10


def exact_quotient(a: np.ndarray, factor: np.ndarray) -> np.ndarray | None:
    """``a / factor`` (polynomials, lowest power first) if ``factor`` divides ``a`` exactly
    (remainder within a relative 1e-10 of ``a``'s largest coefficient), else ``None``."""
    a = np.trim_zeros(np.asarray(a, dtype=float), "b")
    quot, rem = np.polynomial.polynomial.polydiv(a, factor)
    if rem.size and np.max(np.abs(rem)) > _EXACT_RTOL * max(1.0, np.max(np.abs(a))):
        return None
    return quot


class ModeItem(NamedTuple):
    """One mode's work item of a data-driven call (what varies per mode).

    Attributes
    ----------
    mode : int
        Index of the mode in the call.
    psd, noise : ndarray, shape (n_freqs,)
        Disturbance and noise PSDs on the input grid [units^2/Hz].
    b0, a0 : ndarray
        The starting controller's coefficients (powers of ``z^-1``).
    fixed_factor : ndarray
        The mode's fixed denominator factor (may differ from the context's: an integrator
        start for a mode whose poles are otherwise free).
    bound_start : bool
        Whether the mode also tries the margin-constrained bound's reduction as a start.
    """

    mode: int
    psd: np.ndarray
    noise: np.ndarray
    b0: np.ndarray
    a0: np.ndarray
    fixed_factor: np.ndarray
    bound_start: bool


@dataclass(frozen=True)
class DesignContext:
    """What every mode of one data-driven call shares.

    Attributes
    ----------
    plant : control.TransferFunction or control.FRD
        Loop plant.
    fs : float
        Loop rate [Hz].
    input_freqs : ndarray, shape (n_freqs,)
        The caller's frequency grid [Hz] (where the PSDs are given; the residual is
        reported on it).
    input_weights : ndarray, shape (n_freqs,)
        Trapezoid weights of ``input_freqs`` [Hz] (integral = weights @ values).
    h2_freqs : ndarray
        The points of ``input_freqs`` where the H2 objective is evaluated (a subsample).
    design_freqs, design_response : ndarray
        The design grid [Hz] (``h2_freqs`` plus margin-only points covering [0, fs/2]) and
        the plant's response there.
    dense_freqs, dense_response : ndarray
        The dense grid [Hz] of the stability (winding) constraints and of the candidates'
        checks, and the plant's response there.
    winding_index : ndarray of int
        Points of the dense grid that carry a winding constraint.
    fixed_factor : ndarray
        Fixed factor ``F`` of every mode's denominator (powers of ``z^-1``, ``F[0] = 1``).
    free_order : int
        ``q``: order of ``X`` and of the free part of ``Y``.
    modulus_margin : float
        The asked modulus margin ``mu`` (``||S||_inf <= 1 / mu``).
    hinf_weight : float
        Weight of ``||T||_inf^2`` in the objective.
    response_scale : float
        ``s``: median ``|G|`` on the design grid (the numerator's scale in ``v``).
    plant_coefficients : tuple of ndarray or None
        ``(b, a)`` of a rational plant in powers of ``z^-1`` (``None`` for a measured one).
    max_iter : int
        Convex iterations per mode.
    tol : float
        Relative decrease of the objective below which the iterations stop.
    extrapolate : bool
        Whether the iterations take an extrapolated step when they stall.
    max_pole_radius : float or None
        Radius the free controller poles stay inside (``None``: unconstrained).
    auto_orders : tuple of int
        Candidate orders of ``order="auto"`` (empty for a fixed order).
    auto_tol : float
        ``order="auto"``: a higher order is kept only if it lowers the residual by more than
        this fraction.
    uncertainty : UncertaintySet or None
        The loop gains and latencies every design must survive (robust design), or ``None``.
    variant_plants : tuple of control.TransferFunction
        The plants of the uncertainty set the convex problem constrains at every point (its
        corners and edge middles, :meth:`~aocontrol.analysis.UncertaintySet.corners`); the
        certificate covers the whole set.
    """

    plant: object
    fs: float
    input_freqs: np.ndarray
    input_weights: np.ndarray
    h2_freqs: np.ndarray
    design_freqs: np.ndarray
    design_response: np.ndarray
    dense_freqs: np.ndarray
    dense_response: np.ndarray
    winding_index: np.ndarray
    fixed_factor: np.ndarray
    free_order: int
    modulus_margin: float
    hinf_weight: float
    response_scale: float
    plant_coefficients: tuple | None
    max_iter: int
    tol: float
    extrapolate: bool
    max_pole_radius: float | None
    auto_orders: tuple = ()
    auto_tol: float = 0.02
    uncertainty: object = None
    variant_plants: tuple = ()

    @property
    def rows_per_point(self) -> int:
        """Grid rows per frequency: the nominal plant and every variant plant."""
        return 1 + len(self.variant_plants)

    @property
    def design_margin(self) -> float:
        """The modulus margin the design grid enforces (``MARGIN_SAFETY`` above the asked)."""
        return design_margin(self.modulus_margin)

    @property
    def n_params(self) -> int:
        """Length of ``v``: ``2 q + 1``."""
        return 2 * self.free_order + 1

    @property
    def exact(self) -> bool:
        """Whether the plant is rational (certificates exact over the whole circle)."""
        return self.plant_coefficients is not None

    def with_structure(self, fixed_factor: np.ndarray, order: int) -> DesignContext:
        """The same context for another fixed factor and total denominator order."""
        from dataclasses import replace

        return replace(self, fixed_factor=fixed_factor, free_order=order - (fixed_factor.size - 1))

    def grid_data(self, f: np.ndarray, g: np.ndarray, mu: float | np.ndarray) -> GridData:
        """Rows of the convex problem at frequencies ``f`` [Hz] (plant response ``g``)."""
        q = self.free_order
        w = np.exp(-2j * np.pi * f / self.fs)
        powers = w[:, None] ** np.arange(q + 1)
        F = np.polyval(self.fixed_factor[::-1], w)
        AX = np.zeros((f.size, self.n_params), complex)
        AY = np.zeros((f.size, self.n_params), complex)
        AX[:, : q + 1] = (g / self.response_scale)[:, None] * powers
        AY[:, q + 1 :] = F[:, None] * powers[:, 1:]
        return GridData(AY, AX, F.astype(complex), mu, self.hinf_weight)

    def to_v(self, b: np.ndarray, a: np.ndarray) -> np.ndarray | None:
        """Parameter vector of ``K = b/a`` if it lies in the parameter set, else None."""
        q = self.free_order
        b = np.trim_zeros(np.asarray(b, float), "b")
        a = np.trim_zeros(np.asarray(a, float), "b")
        if b.size > q + 1 or a.size > q + self.fixed_factor.size:
            return None
        quot = exact_quotient(a, self.fixed_factor)
        if quot is None:
            return None
        quot = np.concatenate([quot, np.zeros(q + 1 - quot.size)])
        x = np.concatenate([b, np.zeros(q + 1 - b.size)]) * self.response_scale
        return np.concatenate([x, quot[1:]])

    def warm_v(self, b: np.ndarray, a: np.ndarray, leak: float) -> np.ndarray | None:
        """Parameter vector of a warm start ``K = b/a`` (the previous mode's design), or None.

        A design with integral action (a pole at z = 1) lies outside the radius of a mode
        whose poles are all free: its integrator becomes the leaky one ``1 - (1 - leak) z^-1``
        of that mode's default start, the other poles kept.
        """
        v = self.to_v(b, a)
        if self.fixed_factor.size != 1 or self.max_pole_radius is None:
            return v
        if v is not None:
            poles = self.free_poles(v)
            if not poles.size or np.max(np.abs(poles)) <= self.max_pole_radius:
                return v
        quot = exact_quotient(a, np.array([1.0, -1.0]))
        if quot is None:
            return None
        return self.to_v(b, np.polynomial.polynomial.polymul(quot, [1.0, -(1.0 - leak)]))

    def from_v(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coefficients ``(b, a)`` (powers of ``z^-1``) of the parameter vector ``v``."""
        q = self.free_order
        b = v[: q + 1] / self.response_scale
        a = np.polynomial.polynomial.polymul(self.fixed_factor, np.concatenate([[1.0], v[q + 1 :]]))
        return b, a

    def free_poles(self, v: np.ndarray) -> np.ndarray:
        """Controller poles free in the design (roots of ``Y'``, the fixed factor apart)."""
        y = v[self.free_order + 1 :]
        if y.size == 0:
            return np.empty(0, complex)
        # Y'(w) = 1 + sum y_i w^i, w = z^-1: the z-plane poles are the roots of z^q + y_1 ...
        return np.roots(np.concatenate([[1.0], y]))


def design_margin(mu: float) -> float:
    """The modulus margin a design grid enforces for an asked margin ``mu``."""
    return min(mu * (1 + MARGIN_SAFETY), 0.999)
