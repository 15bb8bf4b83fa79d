"""Helpers shared by the wavefront sensor models (private)."""

from __future__ import annotations

import contextlib
import functools

import numpy as np

from aocontrol._validation import check_finite_array


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


@functools.cache
def _blas_controller():
    """The process's BLAS libraries (``threadpoolctl``; inspected once, at first use)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


_blas_limit: list[int] = []  # the limits in force (nested calls), innermost last


@contextlib.contextmanager
def blas_threads(n: int):
    """Context: at most ``n`` BLAS threads (process-wide while it runs; a nested context with
    the same ``n`` costs nothing).

    The WFS products (pyramid propagation, reconstructor) are small enough that a
    multi-threaded OpenBLAS stalls on them on a machine shared with other jobs (measured: a
    400 x 2496 reconstructor product 25x slower in CPU time with 2 threads than with 1).
    """
    if _blas_limit and _blas_limit[-1] == n:
        yield
        return
    with _blas_controller().limit(limits=n, user_api="blas"):
        _blas_limit.append(n)
        try:
            yield
        finally:
            _blas_limit.pop()
