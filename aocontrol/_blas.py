"""The BLAS thread limit (private): one owner for the simulator's engine runs, the wavefront
sensors' products (:mod:`aocontrol.sim.wfs`) and the synthesis layer's small least-squares
fits, so that nested limits cost nothing."""

from __future__ import annotations

import contextlib
import functools

__all__ = ["blas_threads"]


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

    The WFS products (pyramid propagation, reconstructor) and the telemetry check's
    least-squares fits are small enough that a multi-threaded OpenBLAS stalls on them on a
    machine shared with other jobs (see ``docs/benchmarks.md``).
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
