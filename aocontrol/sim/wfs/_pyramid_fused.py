"""The pyramid frame's memory-bound element-wise passes as compiled loops (numba; private
helper of :mod:`._pyramid_propagation`).

Besides its two matrix products, a closed-loop pyramid frame spends most of its CPU time in
element-wise passes (profile in ``docs/benchmarks.md``): the y tilts of step x's output and
the constant row, writing the direct images into the product buffer before the second
product and the intensity sums over the products, each a separate numpy pass over a few MB.
Here:

* :func:`tilt_rows` writes the y tilts and the constant row in one pass, with the numpy
  path's floating-point operations in its order (float32 products, the constant row summed row
  after row in float32 and scaled in float64): bit for bit the numpy buffers (tested);
* :func:`intensity_terms` adds the direct images to the product (which the second product
  writes with ``beta = 0``: the same sum, the two terms in the other order) and accumulates the
  squares and the cross terms in one pass over the product, in float64 (the numpy path sums
  in float32 with numpy's ``einsum`` order): equal to float32 rounding (tested).

numba is imported on first use; its compiled code is cached on disk. Without numba, or with
``$AOCONTROL_NO_NUMBA`` set (:mod:`aocontrol.sim._fused`), :func:`kernels` returns ``None``
and the pyramid runs its numpy passes.
"""

from __future__ import annotations

import numpy as np

from aocontrol.sim._fused import compile_once

_KERNELS: list = []  # [(tilt_rows, intensity_terms) compiled, or None], filled on first use


def kernels() -> tuple | None:
    """The compiled ``(tilt_rows, intensity_terms)``, or ``None`` (no numba, or disabled)."""
    return compile_once(_KERNELS, (tilt_rows, intensity_terms), "the pyramid runs its numpy passes")


def tilt_rows(g0, g1, w, w0, j0, j1, two, ny0, y0, out):
    """Step y's input of one pupil-sample parity for the pairs ``j0 .. j1-1`` (plain Python;
    compiled by :func:`kernels`).

    ``g0``, ``g1`` ``(n_m, n_x, n_q, 2)`` float32: step x's output for the lines of class 0
    and 1 (real, imaginary); ``w``: the tilt weights, ``(n_m, n_ns, 2)`` (cosine, sine) when
    ``two`` else ``(n_m, n_one, 1)``, the chunk's first pair at ``w[:, w0]``; ``out`` ``(n_m +
    1, n_g, 2 n_lines)`` float32: rows ``y'`` times the weights (groups: cosine then sine of
    each pair, or one group per pair; columns: real parts of the class-0 then class-1 lines,
    then the imaginary parts), and the constant row ``[-y0 * sum(imaginary), y0 *
    sum(real)]`` (``ny0 = -y0``, float64).
    """
    n_m = out.shape[0] - 1
    n_g = out.shape[1]
    n0, n1 = g0.shape[2], g1.shape[2]
    nl = n0 + n1
    per = 2 if two else 1
    for y in range(n_m):
        for j in range(j1 - j0):
            for h in range(per):
                wt = w[y, w0 + j, h]
                g = per * j + h
                for c in range(2):
                    for li in range(n0):
                        out[y, g, c * nl + li] = g0[y, j0 + j, li, c] * wt
                    for li in range(n1):
                        out[y, g, c * nl + n0 + li] = g1[y, j0 + j, li, c] * wt
    for g in range(n_g):
        for col in range(2 * nl):
            s = out[0, g, col]
            for y in range(1, n_m):
                s = s + out[y, g, col]
            if col < nl:  # the real part's sum goes to the imaginary half
                out[n_m, g, nl + col] = np.float64(s) * y0  # rounded to out's dtype
            else:
                out[n_m, g, col - nl] = np.float64(s) * ny0


def intensity_terms(o, xq, src, d_re, d_im, s, x):
    """Intensity sums of one class's products (plain Python; compiled by :func:`kernels`).

    ``o`` ``(n_l, 2, n_g, 2 n_lines)`` float32: step y's products ``U``, ``V`` without the
    direct images, which are ``xq[src + l] * (d_re, d_im)`` (float32, added first, as the
    numpy path's product buffer holds them); ``s`` ``(n_l, 2 n_lines)`` += the sum over ``U,
    V`` and the groups of the squares (real parts, then imaginary parts), ``x`` ``(n_l,
    n_lines)`` += the sum over the groups of ``Im(V conj U)`` (the cross terms of
    :func:`._pyramid_propagation.accumulate` with ``f = h``: the sine, cosine and one-point groups'
    terms are all this one).
    """
    n_l, _, n_g, nc = o.shape
    nl = nc // 2
    acc_s = np.zeros(nc)
    acc_x = np.zeros(nl)
    for li in range(n_l):
        acc_s[:] = 0.0
        acc_x[:] = 0.0
        for g in range(n_g):
            for c in range(nl):
                xr = xq[src + li, g, c]
                xi = xq[src + li, g, nl + c]
                ur = o[li, 0, g, c] + xr * d_re
                ui = o[li, 0, g, nl + c] + xi * d_re
                vr = o[li, 1, g, c] + xr * d_im
                vi = o[li, 1, g, nl + c] + xi * d_im
                fur, fui = np.float64(ur), np.float64(ui)
                fvr, fvi = np.float64(vr), np.float64(vi)
                acc_s[c] += fur * fur + fvr * fvr
                acc_s[nl + c] += fui * fui + fvi * fvi
                acc_x[c] += fvi * fur - fvr * fui
        for c in range(nc):
            s[li, c] = np.float64(s[li, c]) + acc_s[c]
        for c in range(nl):
            x[li, c] = np.float64(x[li, c]) + acc_x[c]
