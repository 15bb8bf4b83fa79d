"""The frames of a linear stage's chunk as one compiled loop (numba), same values bit for bit.

:meth:`aocontrol.sim._runner._StageRun.run_frames` runs a linear stage (linear modal sensor,
no optical-gain tracker, no DM clip, an :class:`~aocontrol.controllers.IIRBank` without a
command limit) in one fused loop per chunk. In numpy that loop still costs ~15 calls per
frame (~35 us at 540 modes on the benchmark machine, most of it call overhead: the
arithmetic is ~10 operations per mode); :func:`linear_frames` is the same loop compiled, a
few microseconds per frame. It performs, per mode and frame, exactly the floating-point
operations of the numpy path in the same order (IEEE double, no fused multiply-add: numba
contracts nothing without ``fastmath``), so the results are bit-identical (tested against
the numpy loop and the golden runs). The one difference is the guard's residual energy,
summed mode after mode instead of by the BLAS dot product: it decides only whether the
guard's element-wise check runs (``_StageRun._diverged``).

numba is imported on first use (a run of a linear stage), not with :mod:`aocontrol.sim`;
its compiled code is cached on disk (``cache=True``). Without numba (import error), or with
``$AOCONTROL_NO_NUMBA`` set to a non-empty value, the runner uses its numpy loop.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable

import numpy as np

logger = logging.getLogger(__name__)

#: Environment variable: set (non-empty) to run the numpy loop instead of the compiled one.
ENV_NO_NUMBA = "AOCONTROL_NO_NUMBA"

# Status codes of linear_frames.
DONE, GUARD, NOT_FINITE = 0, 1, 2

_KERNEL: list = []  # [the compiled function or None], filled on first use


def kernel() -> Callable | None:
    """The compiled :func:`linear_frames`, or ``None`` (no numba, or disabled)."""
    if os.environ.get(ENV_NO_NUMBA):
        return None
    if not _KERNEL:
        try:
            import numba
        except ImportError:  # pragma: no cover - numba is a dependency
            logger.info("numba is not installed: linear stages run the numpy frame loop")
            _KERNEL.append(None)
        else:
            _KERNEL.append(numba.njit(cache=True, nogil=True)(linear_frames))
    return _KERNEL[0]


def warm_up() -> None:
    """Import numba and compile (or load from its cache) :func:`linear_frames` now, e.g.
    before timing runs (~0.6 s of CPU for the import, ~1 s per signature to compile)."""
    compiled = kernel()
    if compiled is None:
        return
    z1, z2 = np.zeros(1), np.zeros((1, 1))
    taps = np.zeros((2, 2))
    compiled(0, z2, z2, False, z2, z1, True, z1, taps, np.zeros((4, 2)), 0, np.zeros((2, 1)),
             0, 0, 1.0, 0.0, 1.0, z2.copy(), z2.copy(), z2.copy(), z2.copy())  # fmt: skip


def linear_frames(
    first, r, offset, has_offset, noise, og, unit_gain, e_prev, taps, hist_c, head, ring, k,
    k0, w0, frac, limit, out_m, out_u, out_y, out_e,
):  # fmt: skip
    """Frames ``first ... len(r) - 1`` of a chunk of a linear stage (plain Python; compiled
    by :func:`kernel`).

    Per frame ``j`` and mode ``i`` (the numpy loop of ``_StageRun._fused_frames``):
    measurement ``m = og e_prev + noise[j]`` (``e_prev + noise[j]`` with unit gains); the
    IIR bank's ``_step`` on the history window ``hist_c[head : head + depth]`` (products by
    ``taps``, summed row after row, then the measurement half plus the command half); the
    command ``u`` into the history, the delay ``ring`` and ``out_u``; the DM shape ``y =
    w0 ring[k - k0] + frac ring[k - k0 - 1]`` (or ``ring[k - k0]`` when ``frac`` is 0) plus
    ``offset[j]``; the residual ``e = r[j] - y``.

    Returns
    -------
    tuple of int
        ``(status, j, head)``: ``DONE`` (``j`` the number of frames), ``GUARD`` (the residual
        energy of frame ``j`` reached ``limit``: the caller checks it element-wise and
        continues at ``j + 1``) or ``NOT_FINITE`` (a command of frame ``j`` is not finite:
        the controller's error); ``head`` the controller's history position after the last
        frame run.
    """
    m, n = r.shape
    depth = taps.shape[0]
    ring_depth = ring.shape[0]
    for j in range(first, m):
        if j > first:
            e_prev = out_e[j - 1]
        head = (head - 1) % depth
        for i in range(n):
            if unit_gain:
                mi = e_prev[i] + noise[j, i]
            else:
                mi = og[i] * e_prev[i] + noise[j, i]
            out_m[j, i] = mi
            hist_c[head, i] = mi
            hist_c[head + depth, i] = mi
        bad = False
        for i in range(n):
            s_m = taps[0, i] * hist_c[head, i]
            s_u = taps[0, n + i] * hist_c[head, n + i]
            for row in range(1, depth):
                s_m = s_m + taps[row, i] * hist_c[head + row, i]
                s_u = s_u + taps[row, n + i] * hist_c[head + row, n + i]
            u = s_m + s_u
            out_u[j, i] = u
            if u - u != 0.0:  # inf or NaN
                bad = True
        if bad:
            return NOT_FINITE, j, head
        slot = k % ring_depth
        for i in range(n):
            u = out_u[j, i]
            hist_c[head, n + i] = u
            hist_c[head + depth, n + i] = u
            ring[slot, i] = u
        now = (k - k0) % ring_depth
        before = (k - k0 - 1) % ring_depth
        energy = 0.0
        for i in range(n):
            if frac != 0.0:
                y = ring[now, i] * w0
                y = y + frac * ring[before, i]
            else:
                y = ring[now, i]
            if has_offset:
                y = y + offset[j, i]
            out_y[j, i] = y
            e = r[j, i] - y
            out_e[j, i] = e
            energy += e * e
        k += 1
        if not energy < limit:
            return GUARD, j, head
    return DONE, m, head
