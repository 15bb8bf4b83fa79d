"""Helpers shared by the wavefront sensor models (private)."""

from __future__ import annotations

import numpy as np

from aocontrol._blas import blas_threads
from aocontrol._validation import check_finite_array

__all__ = ["blas_threads", "bin_matrix", "check_opd", "opd_to_phase"]


def opd_to_phase(opd: np.ndarray, wavelength: float) -> np.ndarray:
    """Phase [rad] at ``wavelength`` [m] of an optical path difference [nm]."""
    return np.asarray(opd) * (2.0 * np.pi / (wavelength * 1e9))


def bin_matrix(n_in: int, n_out: int) -> np.ndarray:
    """Area-weighted 1-D rebinning matrix ``(n_out, n_in)``.

    Entry ``(i, j)`` is the length of input sample ``j`` (``[j, j+1)``) inside output bin
    ``i`` (``[i, i+1) * n_in / n_out``), in input samples: ``B @ x`` sums ``x`` over each bin
    (fractional overlaps when ``n_in`` is not a multiple of ``n_out``), so ``B @ I @ B.T``
    rebins an image conserving its flux.
    """
    edges = np.arange(n_out + 1) * (n_in / n_out)
    lo = np.maximum(edges[:-1, None], np.arange(n_in)[None, :])
    hi = np.minimum(edges[1:, None], np.arange(n_in)[None, :] + 1.0)
    return np.clip(hi - lo, 0.0, None)


def check_opd(opd: object, n_pix: int) -> np.ndarray:
    """Finite OPD maps [nm] of shape ``(..., n_pix, n_pix)``, or a clear ``ValueError``."""
    opd = check_finite_array("opd", opd)
    if opd.shape[-2:] != (n_pix, n_pix):
        raise ValueError(f"opd must end with shape ({n_pix}, {n_pix}), got {opd.shape}")
    return opd
