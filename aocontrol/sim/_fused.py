"""The frames of a linear stage's chunk as one compiled loop (numba), same values bit for bit.

:meth:`aocontrol.sim._stage_run._StageRun.run_frames` runs a linear stage (linear modal sensor,
no optical-gain tracker, no DM clip, an :class:`~aocontrol.controllers.IIRBank` without a
command limit) in one fused loop per chunk. In numpy that loop still costs ~15 calls per
frame, most of its time call overhead (the arithmetic is ~10 operations per mode);
:func:`linear_frames` is the same loop compiled. It performs, per mode and frame, exactly
the floating-point
operations of the numpy path in the same order (IEEE double, no fused multiply-add: numba
contracts nothing without ``fastmath``), so the results are bit-identical (tested against
the numpy loop and the golden runs). The one difference is the guard's residual energy,
summed mode after mode instead of by the BLAS dot product: it decides only whether the
guard's element-wise check runs (``_StageRun._diverged``).

numba is imported on first use (a run of a linear stage), not with :mod:`aocontrol.sim`;
its compiled code is cached on disk (``cache=True``). Without numba (import error), or with
``$AOCONTROL_NO_NUMBA`` set to a non-empty value, :func:`run_chunk` runs its numpy loop.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from aocontrol._jit import compile_once

# The fused loop needs no check of the measurement's finiteness when the residual guard and
# the noise are below this bound: their sum is then finite.
_FUSED_BOUND = 1e150

# Status codes of linear_frames.
DONE, GUARD, NOT_FINITE = 0, 1, 2

_KERNEL: list = []  # [(the compiled function,) or None], filled on first use


def kernel() -> Callable | None:
    """The compiled :func:`linear_frames`, or ``None`` (no numba, or disabled)."""
    out = compile_once(_KERNEL, (linear_frames,), "linear stages run the numpy frame loop")
    return None if out is None else out[0]


def warm_up() -> None:
    """Import numba and compile (or load from its cache) :func:`linear_frames` now, e.g.
    before timing runs (the import and each signature's compilation take seconds)."""
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

    Per frame ``j`` and mode ``i`` (the numpy loop of :func:`run_chunk`):
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


def run_chunk(run: Any, r: np.ndarray, offset: np.ndarray | None) -> bool:
    """The chunk's frames of ``run`` (a ``_StageRun``) in one loop: per frame exactly the
    operations of ``_StageRun.step``
    (sensor read, ``IIRBank.step``, delay line, DM, residual, guard) on the same values (``r``
    the residual inputs, ``offset`` the dCAO offsets, one row per frame),
    without the calls and checks that a linear stage makes redundant. The measurement
    ``e_prev + noise`` is finite (the guard bounds the residual, the noise is checked
    per chunk); a non-finite command is reported with the controller's
    ``FloatingPointError`` (at the guard that it trips, or at the end of the chunk).
    Returns False (nothing done) when the chunk's noise or guard is too large for that.
    """
    sensor = run.sensor
    noise = sensor.noise
    m = r.shape[0]
    if not (run.limit < _FUSED_BOUND and np.all(np.abs(noise[:m]) < _FUSED_BOUND)):
        return False
    ctrl = run.ctrl
    taps, hist_c, products, sums = ctrl._recursion_state()
    n, depth = run.n, taps.shape[0]
    og = None if sensor.unit_gain else sensor.optical_gain
    ring, ring_depth, k0, w0, frac = run.hist, run.depth, run.k0, run.w0, run.frac
    out_m = run.out_m if run.out_m is not None else np.empty((m, n))
    out_u = run.out_u if run.out_u is not None else np.empty((m, n))
    out_y, out_e = run.out_y, run.out_e
    compiled = kernel()
    if compiled is not None:
        _run_compiled(run, compiled, np.ascontiguousarray(r), offset, out_m, out_u)
        return True
    tmp = np.empty(n)
    head, k, e, limit = ctrl._head, run.k, run.e_prev, run.limit_check
    two = depth == 2
    j = 0
    try:
        for j in range(m):
            # The sensor (_LinearRun.read): og e + noise.
            mj = out_m[j]
            if og is None:
                np.add(e, noise[j], out=mj)
            else:
                np.multiply(og, e, out=mj)
                mj += noise[j]
            # IIRBank._step on a finite measurement.
            head = (head - 1) % depth
            hist_c[head, :n] = mj
            hist_c[head + depth, :n] = mj
            np.multiply(taps, hist_c[head : head + depth], out=products)
            if two:
                np.add(products[0], products[1], out=sums)
            else:
                np.add.reduce(products, axis=0, out=sums)
            u = np.add(sums[:n], sums[n:], out=out_u[j])
            hist_c[head, n:] = u
            hist_c[head + depth, n:] = u
            # The delay line and the DM (frame()).
            ring[k % ring_depth] = u
            y = out_y[j]
            if frac:
                np.multiply(ring[(k - k0) % ring_depth], w0, out=y)
                y += np.multiply(frac, ring[(k - k0 - 1) % ring_depth], out=tmp)
            else:
                y[...] = ring[(k - k0) % ring_depth]
            if offset is not None:
                y += offset[j]
            e = np.subtract(r[j], y, out=out_e[j])
            if not e @ e < limit:
                run.k = k
                _finite_commands(out_u[: j + 1])
                run._diverged(k, np.abs(e))
            k += 1
        _finite_commands(out_u[:m])
    finally:
        ctrl._head = head
        run.k, run.e_prev = k, e
    ctrl._last_command = out_u[m - 1].copy()
    return True


def _run_compiled(
    run: Any,
    compiled: Callable,
    r: np.ndarray,
    offset: np.ndarray | None,
    out_m: np.ndarray,
    out_u: np.ndarray,
) -> None:
    """:func:`run_chunk` through the compiled loop :func:`linear_frames`."""
    ctrl, sensor = run.ctrl, run.sensor
    taps, hist_c, _, _ = ctrl._recursion_state()
    m = r.shape[0]
    # Writable C-contiguous float64 arrays only: one compiled signature (numba types
    # read-only arrays apart).
    r, taps, og, noise = (
        _plain(x) for x in (r, taps, np.asarray(sensor.optical_gain, float), sensor.noise)
    )
    has_offset = offset is not None
    off = _plain(offset) if has_offset else np.zeros((1, run.n))
    k_start, head, first, e_prev = run.k, ctrl._head, 0, run.e_prev
    try:
        while True:
            status, j, head = compiled(
                first, r, off, has_offset, noise, og, bool(sensor.unit_gain),
                _plain(e_prev), taps, hist_c, head, run.hist, k_start + first, run.k0,
                run.w0, run.frac, run.limit_check, out_m, out_u, run.out_y, run.out_e,
            )  # fmt: skip
            if status == DONE:
                run.k, run.e_prev = k_start + m, run.out_e[m - 1]
                break
            run.k = k_start + j
            if status == NOT_FINITE:
                _finite_commands(out_u[j : j + 1])
            run._diverged(k_start + j, np.abs(run.out_e[j]))  # raises, or goes on
            first, e_prev = j + 1, run.out_e[j]
            if first == m:
                run.k, run.e_prev = k_start + m, run.out_e[m - 1]
                break
    finally:
        ctrl._head = head
    ctrl._last_command = out_u[m - 1].copy()


def _plain(x: np.ndarray) -> np.ndarray:
    """``x`` as a writable C-contiguous float64 array (a copy only when it is not)."""
    if x.flags.writeable and x.flags.c_contiguous and x.dtype == np.float64:
        return x
    return np.array(x, dtype=np.float64, order="C")


def _finite_commands(u: np.ndarray) -> None:
    """Raise the controller's ``FloatingPointError`` at the first non-finite command row."""
    bad_rows = ~np.isfinite(u).all(axis=1)
    if bad_rows.any():
        row = u[int(np.flatnonzero(bad_rows)[0])]
        bad = np.flatnonzero(~np.isfinite(row))[:10].tolist()
        raise FloatingPointError(f"controller command is not finite for modes {bad}")
