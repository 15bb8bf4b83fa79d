"""The pyramid frame's memory-bound element-wise passes as compiled loops (numba; private
helper of :mod:`._pyramid_propagation`).

Besides its two matrix products, a closed-loop pyramid frame spends about half its CPU time in
element-wise passes (profile in ``docs/benchmarks.md``): the pupil field and its x tilts, step
x's direct images, the y tilts of step x's output and the constant row, step y's direct images,
the intensity sums over the products and the binning, each a separate numpy pass over up to a
few MB. Here:

* :func:`front` computes the pupil field from the phase, its x tilts and step x's direct
  images in one pass over the pupil rows (the field's ``cos``/``sin`` in the propagation's
  precision instead of numpy's complex ``exp``, the direct images as one gather per row: equal
  to float32 rounding, tested);
* :func:`tilt_rows` writes the y tilts and the constant row in one pass, with the numpy
  path's floating-point operations in its order (float32 products, the constant row summed row
  after row in float32 and scaled in float64): bit for bit the numpy buffers (tested);
* :func:`intensity_terms` adds the direct images to the product (which the second product
  writes with ``beta = 0``: the same sum, the two terms in the other order) and accumulates the
  squares and the cross terms in one pass over the product, in float64 (the numpy path sums
  in float32 with numpy's ``einsum`` order): equal to float32 rounding (tested);
  :func:`bilinear_terms` is the same pass for two fields' products (a frame derivative);
* :func:`bin_lines` forms the two pupil images from the sums and bins them, when each
  detector line falls in one bin (an integer binning factor), in float64.

numba is imported on first use; its compiled code is cached on disk. Without numba, or with
``$AOCONTROL_NO_NUMBA`` set (:mod:`aocontrol.sim._fused`), :func:`kernels` returns ``None``
and the pyramid runs its numpy passes.
"""

from __future__ import annotations

import numpy as np

from aocontrol._jit import compile_once

#: [(tilt_rows, intensity_terms, front, bin_lines, bilinear_terms) compiled, or None], filled
#: on first use
_KERNELS: list = []


def kernels() -> tuple | None:
    """The compiled ``(tilt_rows, intensity_terms, front, bin_lines, bilinear_terms)``, or
    ``None`` (no numba, or disabled)."""
    return compile_once(
        _KERNELS,
        (tilt_rows, intensity_terms, front, bin_lines, bilinear_terms),
        "the pyramid runs its numpy passes",
    )


def front(phase, amp, tx0, tx1, col0, dx0, col1, dx1, a0, a1, gq0, gq1):
    """Step x's element-wise part for a phase map (plain Python; compiled by :func:`kernels`):
    the pupil field, its x tilts and step x's direct images in one pass over the rows.

    ``phase`` ``(n_pix, n_pix)`` [rad] float64; ``amp`` ``(n_pix, n_pix)`` complex: the
    field is ``amp e^{i phase}`` with the phase rounded to ``amp``'s real precision first (as
    :func:`._pyramid_propagation.pupil_field`), zero where ``amp`` is; ``tx_p`` ``(n_x,
    n_p)``: the x tilts on the columns of parity ``p``; ``a_p`` ``(2, n_m, n_x, n_p)``: the
    tilted field, rows by parity (the numpy path's ``a``); ``col_q`` ``(n_q,)`` and ``dx_q``
    ``(n_x, n_q)``: the pupil column of each class-``q`` line's direct image and its tilt times
    the direct image's value (0 for a line without one), so that ``gq_q[(p, y', t), l] =
    field[p + 2 y', col_q[l]] dx_q[t, l]`` (``gq_q`` ``(2 n_m n_x, n_q)``), to which the dense
    products add.
    """
    n_pix = phase.shape[0]
    n_x = tx0.shape[0]
    n_m = a0.shape[1]
    ftype = amp.dtype
    rtype = tx0.real.dtype
    row = np.empty(n_pix, dtype=ftype)
    for y in range(n_pix):
        py, yy = y % 2, y // 2
        for x in range(n_pix):
            av = amp[y, x]
            if av == 0:
                row[x] = 0
            else:
                ph = rtype.type(phase[y, x])
                row[x] = av * (np.cos(ph) + 1j * np.sin(ph))
        # complex products written with real arithmetic (numba's complex product does not
        # vectorise)
        for j in range(n_x):
            for xx in range(a0.shape[3]):
                s, t = row[2 * xx], tx0[j, xx]
                a0[py, yy, j, xx] = complex(
                    s.real * t.real - s.imag * t.imag, s.real * t.imag + s.imag * t.real
                )
            for xx in range(a1.shape[3]):
                s, t = row[2 * xx + 1], tx1[j, xx]
                a1[py, yy, j, xx] = complex(
                    s.real * t.real - s.imag * t.imag, s.real * t.imag + s.imag * t.real
                )
            r = (py * n_m + yy) * n_x + j
            for li in range(col0.size):
                s, t = row[col0[li]], dx0[j, li]
                gq0[r, li] = complex(
                    s.real * t.real - s.imag * t.imag, s.real * t.imag + s.imag * t.real
                )
            for li in range(col1.size):
                s, t = row[col1[li]], dx1[j, li]
                gq1[r, li] = complex(
                    s.real * t.real - s.imag * t.imag, s.real * t.imag + s.imag * t.real
                )


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


def bin_lines(s0, x0, s1, x1, row_bin, col_bin, out):
    """The detector frame from the intensity accumulators (plain Python; compiled by
    :func:`kernels`) when every detector line falls in one bin with weight 1.

    ``s_q`` ``(n_l, 2 n_lines)`` and ``x_q`` ``(n_l, n_lines)``: the accumulators of class
    ``q`` (:func:`._pyramid_propagation.bin_frame`: the first image's line is ``2 (s_re +
    s_im) + 4 x``, its partner's ``2 (s_re + s_im) - 4 x``); ``row_bin`` ``(4 n_l,)``: the bin
    of each image line (class 0 first then second image, then class 1), ``col_bin``
    ``(n_lines,)`` the bin of each column; ``out`` ``(n_b, n_b)`` float64, overwritten with
    the binned sums (in float64).
    """
    out[:, :] = 0.0
    n_off = 0
    for q in range(2):
        s = s0 if q == 0 else s1
        x = x0 if q == 0 else x1
        n_l, nl = x.shape
        for li in range(n_l):
            r1 = row_bin[n_off + li]
            r2 = row_bin[n_off + n_l + li]
            for c in range(nl):
                v = 2.0 * (np.float64(s[li, c]) + np.float64(s[li, nl + c]))
                d = 4.0 * np.float64(x[li, c])
                out[r1, col_bin[c]] += v + d
                out[r2, col_bin[c]] += v - d
        n_off += 2 * n_l


def bilinear_terms(of, xf, oh, xh, src, d_re, d_im, scale, s, x):
    """The bilinear terms of two fields' products (plain Python; compiled by :func:`kernels`):
    :func:`intensity_terms` for ``Re(conj(f) h)`` (a frame derivative).

    ``of``, ``oh`` ``(n_l, 2, n_g, 2 n_lines)`` float32: the products of the fields ``f`` and
    ``h`` without the direct images, which are ``x?[src + l] * (d_re, d_im)``; ``s`` += ``scale``
    times the sum over ``U, V`` and the groups of ``f h`` (real parts, then imaginary parts),
    ``x`` += ``scale`` times the symmetrised cross terms ``(Im(V_f conj U_h) + Im(V_h conj
    U_f)) / 2`` (:func:`._pyramid_propagation.accumulate`), in float64.
    """
    n_l, _, n_g, nc = of.shape
    nl = nc // 2
    acc_s = np.zeros(nc)
    acc_x = np.zeros(nl)
    for li in range(n_l):
        acc_s[:] = 0.0
        acc_x[:] = 0.0
        for g in range(n_g):
            for c in range(nl):
                fr, fi = xf[src + li, g, c], xf[src + li, g, nl + c]
                hr, hi = xh[src + li, g, c], xh[src + li, g, nl + c]
                fur = np.float64(of[li, 0, g, c] + fr * d_re)
                fui = np.float64(of[li, 0, g, nl + c] + fi * d_re)
                fvr = np.float64(of[li, 1, g, c] + fr * d_im)
                fvi = np.float64(of[li, 1, g, nl + c] + fi * d_im)
                hur = np.float64(oh[li, 0, g, c] + hr * d_re)
                hui = np.float64(oh[li, 0, g, nl + c] + hi * d_re)
                hvr = np.float64(oh[li, 1, g, c] + hr * d_im)
                hvi = np.float64(oh[li, 1, g, nl + c] + hi * d_im)
                acc_s[c] += fur * hur + fvr * hvr
                acc_s[nl + c] += fui * hui + fvi * hvi
                acc_x[c] += 0.5 * ((fvi * hur - fvr * hui) + (hvi * fur - hvr * fui))
        for c in range(nc):
            s[li, c] = np.float64(s[li, c]) + scale * acc_s[c]
        for c in range(nl):
            x[li, c] = np.float64(x[li, c]) + scale * acc_x[c]
