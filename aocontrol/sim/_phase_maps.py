"""One DM shape per frame for the sensors that read phase maps (private).

A diffractive sensor in the loop (:class:`aocontrol.sim.wfs.DiffractiveSensor`) reads the
residual OPD map of every frame, so the engine synthesises the stage's DM shape once per
frame. ``basis.synthesize`` is a float64 product with the whole ``(n_modes, n_valid)`` mode
matrix (15 MB for 400 modes on an 80-pixel pupil, read once per frame: memory bound).
:class:`ShapeSynthesizer` gives the same shape:

* through the mirror's separable Gaussian influences when the basis carries them
  (``basis.mirror``, :class:`aocontrol.sim._projection.SeparableMirror`, and ``basis.m2c``):
  the commands ``m2c @ y`` on the actuator grid, then ``G_y^T C G_x`` on the map and the
  pupil mean removed (``modes = m2c^T (F - f 1^T)``), in float32 (the influences' subnormal
  float32 tails set to zero, as the projection does: they slow the products ~10x);
* otherwise as the product with a float32 copy of the modes.

Precision: float32 (relative rounding ~1e-7 of the shape, < 1e-5 of its largest value:
``tests/test_phase_maps.py``), far below what the pyramid's own single-precision
propagation rounds (complex64).
"""

from __future__ import annotations

import weakref
from typing import Any

import numpy as np

from aocontrol.sim._projection import _flush_subnormal

__all__ = ["ShapeSynthesizer", "shape_synthesizer"]

_DTYPE = np.float32


class ShapeSynthesizer:
    """DM shapes ``(n_valid,)`` [nm, float32] of modal coefficients ``(n_modes,)``, one frame
    at a time (module docstring).

    Parameters
    ----------
    basis : ModalBasis-like
        ``modes`` (n_modes, n_valid) and ``pupil``; ``mirror`` and ``m2c`` for the separable
        path.
    """

    def __init__(self, basis: Any) -> None:
        self.basis = basis
        mirror = getattr(basis, "mirror", None)
        m2c = getattr(basis, "m2c", None)
        self.separable = mirror is not None and m2c is not None
        if self.separable:
            pupil = basis.pupil
            na = mirror.n_actuators
            self._na = na
            self._act = np.asarray(mirror.act_index)
            self._m2c = np.ascontiguousarray(m2c, dtype=_DTYPE)  # (n_act, n_modes)
            self._mean = np.asarray(mirror.mean, dtype=_DTYPE)
            # subnormal float32 tails of the Gaussian influences set to zero: a product with
            # them runs ~10x slower, and they are ~1e-38 of the largest entry
            self._gyt = _flush_subnormal(np.asarray(mirror.gy).T, _DTYPE)
            self._gx = _flush_subnormal(mirror.gx, _DTYPE)
            self._index = np.asarray(pupil.index)
        else:
            self._modes = np.asarray(basis.modes, dtype=_DTYPE)

    def __call__(self, coeffs: np.ndarray) -> np.ndarray:
        """Shape on the valid pupil pixels ``(n_valid,)`` [nm, float32] of ``coeffs``
        ``(n_modes,)`` [nm RMS]."""
        c = np.asarray(coeffs, dtype=_DTYPE)
        if not self.separable:
            return c @ self._modes
        acts = self._m2c @ c
        grid = np.zeros((self._na, self._na), dtype=_DTYPE)  # per call: thread-safe
        grid.flat[self._act] = acts
        shape = (self._gyt @ grid @ self._gx).ravel()[self._index]
        shape -= acts @ self._mean
        return shape


_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def shape_synthesizer(basis: Any) -> ShapeSynthesizer:
    """The :class:`ShapeSynthesizer` of ``basis``, built once per live basis object."""
    try:
        hit = _CACHE.get(basis)
        if hit is None:
            hit = _CACHE[basis] = ShapeSynthesizer(basis)
    except TypeError:  # not weakly referenceable or not hashable
        return ShapeSynthesizer(basis)
    return hit
