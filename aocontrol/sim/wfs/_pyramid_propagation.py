"""The modulated pyramid's propagation as matrix products (private helper of :mod:`.pyramid`):
its plan (precomputed operators), work buffers, pair products, intensity terms and binning.

The pyramid mask and the tilts factor into x and y parts, so the propagation of one modulation
point is ``L diag(t_y) E diag(t_x) L^T`` with ``E`` the pupil field and ``L`` the 1-D line
operator (pad, FFT, one mask factor, inverse FFT, detector lines; the same along x and y),
applied as matrix products (no FFT per frame), exact rewrites of the discrete model:

* parity (:mod:`._pyramid_lines`): the mask factor is two linear phases, so a detector line
  sees the pupil samples of one parity through a dense kernel and, of the other parity, only
  its direct-image sample;
* conjugate images: the dense kernels of a line ``l`` of the first pupil image and of its
  partner ``l + n_fft/2`` in the second are ``u - i v + c0`` and ``u + i v + c0`` with ``u, v``
  real and ``c0`` one imaginary constant (the kernel is ``1/2 + i/2 cot`` for one face and
  ``1/2 - i/2 tan`` for the other, ``tan`` being ``cot`` shifted by ``n_fft/2``), and their
  direct images ``delta`` and ``conj(delta)``: with ``U = u Y + c0 sum(Y) + Re(delta) Y_d``
  and ``V = v Y - Im(delta) Y_d`` (real kernels), the two images are ``U - iV`` and ``U + iV``;
* mirror points: the points ``k`` and ``n_points - k`` have the same x tilt and opposite y
  tilts ``h e^{+-i beta}`` (``h`` the half-sample centring, folded into the pupil field), so
  with ``Y_c = cos(beta) G`` and ``Y_s = sin(beta) G`` (``G`` step x's output) the four fields
  of the pair are ``(U_c + V_s) +- i(U_s - V_c)`` and ``(U_c - V_s) +- i(U_s + V_c)``, and
  the pair's intensities are ``2 S + 4 X`` (first image) and ``2 S - 4 X`` (second) with
  ``S = |U_c|^2 + |U_s|^2 + |V_c|^2 + |V_s|^2`` and ``X = Im(V_s conj U_s) - Im(U_c conj V_c)``
  (the points on the x axis are their own mirror: weight 1/2, taken with ``beta = 0``).

Step x (complex ``L``, one product per parity class for all pairs) is shared by the two points
of a pair; step y is one real product ``[u 1; v 0] @ [Y_c, Y_s of every pair; constant row]``
per parity class for all points: half the FLOPs of complex per-point products
(``benchmarks/bench_pyramid.py --flops``). Single precision by default (``complex64`` /
``float32``; the difference from double precision is < 1e-5 of the largest pixel, tested
against reference frames). The element-wise passes before, between and after the products (pupil
field and x tilts, direct images, y tilts, constant row, intensity sums, binning; the bilinear
sums of the derivatives) are compiled loops (:mod:`._pyramid_fused`, numba; the numpy passes
without numba or with ``$AOCONTROL_NO_NUMBA``): the same frames to float32 rounding (the sums in
float64), in less CPU (``docs/benchmarks.md``).

The functions take the plan (:func:`build_plan`), the work buffers (:func:`work_buffers`) and
the chunks of modulation pairs explicitly; the sensor (:class:`.pyramid.PyramidWFS`) owns them
per instance and sets the BLAS threads around the calls.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import scipy.sparse

from aocontrol.sim.wfs import _pyramid_fused
from aocontrol.sim.wfs._pyramid_lines import (
    apply_runs,
    bin_permutation,
    gemm_acc,
    image_pairs,
    line_operator,
    parity_classes,
)

__all__ = [
    "accumulate",
    "bin_frame",
    "build_plan",
    "frame_derivatives",
    "intensities",
    "new_accumulators",
    "pair_fields",
    "pupil_field",
    "step_x",
    "step_x_from_phase",
    "work_buffers",
]

#: A chunk of modulation pairs: ``(first pair, end pair, two-point pairs)``.
Chunk = tuple[int, int, bool]


def build_plan(
    mask: np.ndarray,
    n_valid: int,
    n_points: int,
    n_fft: int,
    x_tilts: np.ndarray,
    y_tilts: np.ndarray,
    binning: np.ndarray,
    complex_dtype: type,
    real_dtype: type,
) -> dict:
    """Precomputed tilts, line operators, pair kernels and binning (module docstring).

    Parameters
    ----------
    mask : ndarray of bool, shape (n_pix, n_pix)
        Pupil mask.
    n_valid : int
        Pupil samples inside the pupil (the field's normalisation).
    n_points : int
        Modulation points (the field's normalisation).
    n_fft : int
        Padded size, a multiple of 4.
    x_tilts : ndarray, shape (n_pairs,)
        x tilt of each mirror pair of modulation points [focal samples], the two-point pairs
        first (:attr:`.pyramid.PyramidWFS._pairs`).
    y_tilts : ndarray, shape (n_ns,)
        y tilt ``+-b`` of each two-point pair [focal samples].
    binning : ndarray, shape (2 n_sub, n_fft)
        Crop-and-bin matrix of the detector lines (both pupil images).
    complex_dtype, real_dtype : type
        Precision of the operators: complex64 and float32, or complex128 and float64.

    Returns
    -------
    dict
        The read-only operators that :func:`pair_fields`, :func:`bin_frame` and
        :func:`work_buffers` use (``"amp"`` the pupil amplitude with the half-sample centring,
        ``"classes"``, ``"pairs"``, ``"tx"``, ``"dense_t"``, ``"w"``, ``"w1"``, ``"y0"``,
        ``"kern"``, ``"delta"``, ``"bin_rows"``, ``"bin_cols"``, ``"bin_perm"``, ``"n_ns"``,
        ``"n_m"``).
    """
    n, n_pix = n_fft, mask.shape[0]
    x = np.arange(n_pix)
    a, b = x_tilts, y_tilts
    n_ns = b.size
    c, r = complex_dtype, real_dtype
    tx = np.exp(2j * np.pi * (a[:, None] - 0.5) * x[None, :] / n)
    # one face of the pyramid per half line; the apex between samples -1 and 0; the ramp
    # places the pupil (transformed from the array corner) at r0 in the padded array
    u = np.fft.fftfreq(n) * n
    r0 = (n - n_pix) // 2
    m1 = np.exp(0.5j * np.pi * np.abs(u + 0.5) - 2j * np.pi * r0 * u / n)
    lines = np.flatnonzero(np.any(binning != 0, axis=0))
    op = line_operator(n, n_pix, m1, lines)
    classes = parity_classes(op)
    pairs = image_pairs(op, lines, n)
    order = np.concatenate([k.lines for k in classes])  # x lines, class by class
    rows = np.concatenate([np.r_[p.first, p.second] for p in pairs])  # y lines
    n_p = [len(range(p, n_pix, 2)) for p in (0, 1)]
    n_m = max(n_p)
    # column groups: (cos, sin) of the y tilt of each two-point pair, then the one-point
    # pairs (b = 0) weighted 1/sqrt(2): one formula for both (module docstring)
    n_one = a.size - n_ns
    w = np.zeros((2, n_m, n_ns, 2))
    for p in (0, 1):
        beta = 2 * np.pi * np.arange(p, n_pix, 2)[:, None] * b[None, :] / n
        w[p, : n_p[p], :, 0] = np.cos(beta)
        w[p, : n_p[p], :, 1] = np.sin(beta)
    w1 = np.zeros((2, n_m, n_one))
    for p in (0, 1):
        w1[p, : n_p[p]] = math.sqrt(0.5)
    kern = []
    for qy, pr in enumerate(pairs):
        kq = np.zeros((pr.first.size, 2, n_m + 1))  # rows (line, U/V)
        kq[:, 0, : n_p[1 - qy]] = pr.u
        kq[:, 1, : n_p[1 - qy]] = pr.v
        kq[:, 0, n_m] = 1.0  # the constant row c0 sum_y X[y] (U only)
        kern.append(np.ascontiguousarray(kq.reshape(-1, n_m + 1), dtype=r))
    plan = {
        "amp": (
            mask
            * np.exp(-1j * np.pi * x / n)[:, None]  # half-sample centring along y
            / math.sqrt(n_valid * n_points)
        ).astype(c),
        "classes": classes,
        "pairs": pairs,
        "n_ns": n_ns,
        "n_m": n_m,
        # tilts split by the parity of the pupil sample: tx (n_x, n_p)
        "tx": [np.ascontiguousarray(tx[:, p::2], dtype=c) for p in (0, 1)],
        "dense_t": [np.ascontiguousarray(k_.dense.T, dtype=c) for k_ in classes],
        # step x's direct images for the compiled front pass: per class, the pupil column of
        # each line's direct image and its x tilt times the image's value (0: no image)
        "direct_x": [_direct_x(k_, q, tx, c) for q, k_ in enumerate(classes)],
        "w": np.ascontiguousarray(w[..., None], dtype=r),
        "w1": np.ascontiguousarray(w1[..., None], dtype=r),
        # c0 of the class whose dense part reads the samples of parity p
        "y0": np.array([pairs[1].c0.imag, pairs[0].c0.imag]),
        "kern": kern,
        "delta": [
            np.array([p_.delta.real, -p_.delta.imag], dtype=r)[:, None, None] for p_ in pairs
        ],
        # sparse, not BLAS: small GEMMs stall in multi-threaded OpenBLAS on a busy machine
        "bin_rows": scipy.sparse.csr_matrix(binning[:, lines[rows]]),
        "bin_cols": scipy.sparse.csr_matrix(binning[:, lines[order]]),
        # an integer binning factor: each line in one bin, summed by a reshape
        "bin_perm": [bin_permutation(binning[:, lines[i]]) for i in (rows, order)],
        # and the bin of each line (the compiled binning), or None
        "bin_index": [
            None if bin_permutation(b_) is None else np.argmax(b_, axis=0)
            for b_ in (binning[:, lines[rows]], binning[:, lines[order]])
        ],
    }
    for v in plan.values():
        if isinstance(v, np.ndarray):
            v.setflags(write=False)
    return plan


def _direct_x(cls, q: int, tx: np.ndarray, dtype: type) -> tuple[np.ndarray, np.ndarray]:
    """``(col, dx)`` of the line class ``q`` (:func:`._pyramid_fused.front`): the pupil column
    ``col[l]`` of line ``l``'s direct image (a sample of parity ``q``) and ``dx[t, l] = tx[t,
    col[l]] value`` (the x tilts ``tx`` ``(n_x, n_pix)``; 0 for a line without one)."""
    n_q = cls.lines.size
    col = np.zeros(n_q, dtype=np.int64)
    val = np.zeros(n_q, dtype=complex)
    for r0, r1, s0, value in cls.runs:
        col[r0:r1] = q + 2 * np.arange(s0, s0 + r1 - r0)
        val[r0:r1] = value
    return col, np.ascontiguousarray(tx[:, col] * val[None, :], dtype=dtype)


def work_buffers(plan: dict, chunks: list[Chunk]) -> dict[str, list[np.ndarray]]:
    """Work buffers kept across frames (a few MB, allocated once; lists over the parity ``p``
    of the pupil samples or the class ``q`` of the detector lines).

    ``a[p]`` ``(2, n_m, n_x, n_p)``: the field times each pair's x tilt on the columns ``x =
    p, p+2, ...``, rows by parity (``n_m`` the larger count; spare rows zero); ``gq[q]`` ``(2
    n_m n_x, n_q)``: step x (complex, lines of class ``q``); ``xs`` (per parity ``p``, then
    per chunk of pairs) ``(n_m + 1, n_g, 2 n_lines)``: the rows of parity ``p`` times the
    cosine and sine of each pair's y tilt, real parts then imaginary parts, and the constant
    row; ``o[q]`` (flat, ``(n_l, 2, n_g, 2 n_lines)`` for a chunk): step y, the products ``U``
    and ``V`` of the chunk's column groups; ``s[q]`` ``(n_l, 2 n_lines)`` and ``x[q]`` ``(n_l,
    n_lines)``: intensity accumulators. Whoever holds them runs one propagation at a time (one
    set per thread).

    Parameters
    ----------
    plan : dict
        From :func:`build_plan`.
    chunks : list of (int, int, bool)
        Chunks of modulation pairs ``(j0, j1, two_point)`` of the y step.

    Returns
    -------
    dict
        ``{"a", "gq", "xs", "o", "s", "x"}``, each a list of arrays (zeros).
    """
    c, r = plan["tx"][0].dtype, plan["kern"][0].dtype
    n_x, n_m = plan["tx"][0].shape[0], plan["n_m"]
    n_q = [k.lines.size for k in plan["classes"]]
    n_l = [pr.first.size for pr in plan["pairs"]]
    n_px = [plan["tx"][p].shape[1] for p in (0, 1)]
    nl = sum(n_q)
    n_g = max(j1 - j0 + (j1 - j0 if two else 0) for j0, j1, two in chunks)
    return {
        "a": [np.zeros((2, n_m, n_x, n_px[p]), dtype=c) for p in (0, 1)],
        "gq": [np.zeros((2 * n_m * n_x, n_q[q]), dtype=c) for q in (0, 1)],
        "xs": [
            np.zeros((n_m + 1, (j1 - j0) * (2 if two else 1), 2 * nl), dtype=r)
            for _ in (0, 1)
            for j0, j1, two in chunks
        ],
        "o": [np.zeros(n_l[q] * 2 * n_g * 2 * nl, dtype=r) for q in (0, 1)],
        "s": [np.zeros((n_l[q], 2 * nl), dtype=r) for q in (0, 1)],
        "x": [np.zeros((n_l[q], nl), dtype=r) for q in (0, 1)],
    }


def pupil_field(plan: dict, phase: np.ndarray) -> np.ndarray:
    """Pupil field ``(n_pix, n_pix)`` of a phase map [rad]: ``plan["amp"] e^{i phase}`` (pupil
    amplitude, half-sample centring and normalisation), in the plan's precision."""
    real = plan["kern"][0].dtype
    return plan["amp"] * np.exp(1j * np.asarray(phase).astype(real))


def step_x(plan: dict, work: dict, field: np.ndarray) -> None:
    """Step x into the work buffers: ``gq[q][(p, y', t), l] = sum_x field[p + 2 y', x] tx[t,
    x] L[l, x]`` for the lines ``l`` of class ``q`` (the x-tilted field ``a`` on the way).

    Parameters
    ----------
    plan, work
        :func:`build_plan` and :func:`work_buffers`.
    field : ndarray, shape (n_pix, n_pix)
        Pupil field (:func:`pupil_field`, or any field: a derivative's ``i dphi E``).
    """
    classes = plan["classes"]
    a, gq = work["a"], work["gq"]
    for px in (0, 1):
        for py in (0, 1):
            f = field[py::2, px::2]
            np.multiply(f[:, None], plan["tx"][px][None], out=a[px][py, : f.shape[0]])
    for q in (0, 1):
        apply_runs(classes[q].runs, a[q].reshape(-1, a[q].shape[-1]).T, gq[q].T)
    _dense_x(plan, work)


def _dense_x(plan: dict, work: dict) -> None:
    """Step x's dense products, added to the direct images in ``gq``."""
    a, gq = work["a"], work["gq"]
    for q in (0, 1):
        gemm_acc(a[1 - q].reshape(-1, a[1 - q].shape[-1]), plan["dense_t"][q], gq[q])


def step_x_from_phase(plan: dict, work: dict, phase: np.ndarray, fused: tuple) -> None:
    """:func:`step_x` of the field of ``phase`` [rad] (:func:`pupil_field`) with the
    compiled front pass (:func:`._pyramid_fused.front`): field, x tilts and direct images in
    one pass, then the dense products."""
    fused[2](
        np.ascontiguousarray(phase, dtype=np.float64),
        plan["amp"],
        plan["tx"][0],
        plan["tx"][1],
        *plan["direct_x"][0],
        *plan["direct_x"][1],
        work["a"][0],
        work["a"][1],
        work["gq"][0],
        work["gq"][1],
    )
    _dense_x(plan, work)


def pair_fields(
    plan: dict, work: dict, chunks: list[Chunk], field: np.ndarray, fused: tuple | None = None
) -> Iterator[tuple]:
    """Detector-plane fields of all modulation points, as pair products.

    Yields one tuple ``(o0, o1, n_ns)`` per chunk of pairs, ``o_q`` of shape ``(n_l, 2, n_g, 2
    n_lines)`` (real parts, then imaginary parts): the products ``U`` and ``V`` of the
    class-``q`` lines (module docstring) for the column groups (cosine and sine of each
    two-point pair, then the one-point pairs) by all detector columns (class by class), and
    ``n_ns`` the chunk's two-point pairs (their groups first). Step x (``L`` along x) is one
    complex product per class for all pairs; step y one real product per class for all pairs,
    after the direct images are written.

    The arrays are the work buffers: valid until the generator advances (copy them to keep
    them).

    Parameters
    ----------
    plan, work, chunks
        :func:`build_plan`, :func:`work_buffers` and the chunks of modulation pairs.
    field : ndarray, shape (n_pix, n_pix), or None
        Pupil field, amplitude and half-sample centring included (:func:`pupil_field`);
        ``None``: step x's output is already in the work buffers (:func:`step_x_from_phase`).
    fused : tuple, optional
        The compiled kernels of :mod:`._pyramid_fused`; the y tilts are then one compiled
        pass, the products are written without the direct images, and the tuples hold a fourth
        item, the chunk's step-y inputs ``[x0, x1]`` (the direct images are ``x_q[src + l] *
        delta_q``: :func:`intensities` adds them while it sums the intensities).
    """
    if field is not None:
        step_x(plan, work, field)
    classes = plan["classes"]
    gq, xs, o = work["gq"], work["xs"], work["o"]
    n_m, r = plan["n_m"], plan["kern"][0].dtype
    n0 = classes[0].lines.size
    nl = n0 + classes[1].lines.size
    # (parity, y', pair, line, real/imaginary) views of step x's output
    gqv = [gq[q].view(r).reshape(2, n_m, -1, gq[q].shape[-1], 2) for q in (0, 1)]
    cols = (slice(0, n0), slice(n0, nl))
    # per chunk of pairs: the y tilts, xs[p][y', group] = (cos, sin)(beta y) g[p, y', pair]
    # (1/sqrt(2) for the one-point pairs) and the constant row; then step y, the direct
    # images and o[q] += [u 1; v 0] @ xs[1-q]
    for ci, (j0, j1, two) in enumerate(chunks):
        x = [xs[p * len(chunks) + ci] for p in (0, 1)]
        for p in (0, 1):
            if fused is not None:
                wp, w0 = (plan["w"][p][..., 0], j0) if two else (plan["w1"][p], 0)
                y0 = float(plan["y0"][p])
                fused[0](gqv[0][p], gqv[1][p], wp, w0, j0, j1, two, -y0, y0, x[p])
                continue
            # real and imaginary parts apart (columns [re | im]), one op per class and part
            for qx in (0, 1):
                for c in (0, 1):
                    if two:
                        np.multiply(
                            gqv[qx][p, :, j0:j1, None, :, c],
                            plan["w"][p][:, j0:j1],
                            out=x[p][:n_m].reshape(n_m, j1 - j0, 2, 2, nl)[:, :, :, c, cols[qx]],
                        )
                    else:
                        np.multiply(
                            gqv[qx][p, :, j0:j1, :, c],
                            plan["w1"][p],
                            out=x[p][:n_m].reshape(n_m, j1 - j0, 2, nl)[:, :, c, cols[qx]],
                        )
            sig = x[p][:n_m].sum(axis=0)  # c0 sum_y, c0 = i y0
            np.multiply(sig[:, nl:], -plan["y0"][p], out=x[p][n_m, :, :nl])
            np.multiply(sig[:, :nl], plan["y0"][p], out=x[p][n_m, :, nl:])
        n_g = x[0].shape[1]
        om = []
        for q in (0, 1):
            pr = plan["pairs"][q]
            n_l = pr.first.size
            oq = o[q][: n_l * 2 * n_g * 2 * nl].reshape(n_l, 2, n_g, 2 * nl)
            if fused is None:
                np.multiply(x[q][pr.src : pr.src + n_l, None], plan["delta"][q], out=oq)
            gemm_acc(
                plan["kern"][q],
                x[1 - q].reshape(n_m + 1, -1),
                oq.reshape(2 * n_l, -1),
                beta=1.0 if fused is None else 0.0,
            )
            om.append(oq)
        if fused is None:
            yield om[0], om[1], (j1 - j0 if two else 0)
        else:
            yield om[0], om[1], (j1 - j0 if two else 0), x


def accumulate(acc: dict, f: tuple, h: tuple, scale: float = 1.0) -> None:
    """``acc`` += ``scale`` times the bilinear intensity terms of the fields ``f`` and ``h``.

    ``f`` and ``h`` are tuples of :func:`pair_fields` (``f is h`` gives the intensity): ``s[q]``
    gets the sum of ``Re(conj(f) h)`` per real/imaginary part over all products, ``x[q]`` the
    symmetrised cross terms ``Im(V_s conj(U_s)) - Im(U_c conj(V_c))`` (the first image is ``2 s
    + 4 x``, the second ``2 s - 4 x``; module docstring).

    Parameters
    ----------
    acc : dict
        ``{"s": [s0, s1], "x": [x0, x1]}`` (:func:`new_accumulators`), updated in place.
    f, h : tuple
        Pair products of one chunk.
    scale : float, default 1.0
        Factor of the terms (2 for a derivative, ``2 Re(conj(f) h)``).
    """
    n_ns = f[2]  # two-point pairs of the chunk (their groups first, cosine and sine)
    for q in (0, 1):
        fq, hq = f[q], h[q]
        nl = fq.shape[-1] // 2
        s_term = np.einsum("lhgc,lhgc->lc", fq, hq)

        def im(a, b, nl=nl):  # sum over the groups of Im(a conj(b))
            return np.einsum("lgc,lgc->lc", a[..., nl:], b[..., :nl]) - np.einsum(
                "lgc,lgc->lc", a[..., :nl], b[..., nl:]
            )

        def cross(p, r):  # Im(Vs conj Us) - Im(Uc conj Vc) of the fields p, r
            t = im(p[:, 1, 1 : 2 * n_ns : 2], r[:, 0, 1 : 2 * n_ns : 2])
            t -= im(p[:, 0, 0 : 2 * n_ns : 2], r[:, 1, 0 : 2 * n_ns : 2])
            t -= im(p[:, 0, 2 * n_ns :], r[:, 1, 2 * n_ns :])
            return t

        x_term = cross(fq, fq) if f is h else 0.5 * (cross(fq, hq) + cross(hq, fq))
        if scale != 1.0:
            s_term *= scale
            x_term *= scale
        acc["s"][q] += s_term
        acc["x"][q] += x_term


def new_accumulators(work: dict) -> dict:
    """Zero accumulators ``{"s": [...], "x": [...]}`` shaped as the work buffers' (new
    arrays: they outlive a propagation)."""
    return {k: [np.zeros_like(a) for a in work[k]] for k in ("s", "x")}


def intensities(
    plan: dict, work: dict, chunks: list[Chunk], phase: np.ndarray
) -> dict[str, list[np.ndarray]]:
    """The intensity accumulators of one pupil phase map, summed over all modulation points.

    With the compiled kernels of :mod:`._pyramid_fused` (when numba is available and not
    disabled) the field, the x tilts and step x's direct images are one compiled pass, and so
    are the direct images of step y and the intensity sums over each product; else
    :func:`pupil_field`, :func:`pair_fields` and :func:`accumulate` with ``f = h``.

    Parameters
    ----------
    plan, work, chunks
        As for :func:`pair_fields`.
    phase : ndarray, shape (n_pix, n_pix)
        Pupil phase [rad].

    Returns
    -------
    dict
        ``{"s": [s0, s1], "x": [x0, x1]}``: the work buffers' accumulators (valid until the
        next propagation), for :func:`bin_frame`.
    """
    acc = {k: work[k] for k in ("s", "x")}
    fused = _pyramid_fused.kernels()
    delta = plan["delta"]
    for a in acc["s"] + acc["x"]:
        a.fill(0.0)
    if fused is None:
        for f in pair_fields(plan, work, chunks, pupil_field(plan, phase)):
            accumulate(acc, f, f)
        return acc
    step_x_from_phase(plan, work, phase, fused)
    for f in pair_fields(plan, work, chunks, None, fused):
        for q in (0, 1):
            src = plan["pairs"][q].src
            d = delta[q][:, 0, 0]
            fused[1](f[q], f[3][q], src, d[0], d[1], acc["s"][q], acc["x"][q])
    return acc


def bin_frame(plan: dict, acc: dict) -> np.ndarray:
    """Accumulators (:func:`accumulate`) -> detector frame ``(2 n_sub, 2 n_sub)`` [float64]:
    the two pupil images of each line class, cropped and rebinned."""
    fused = _pyramid_fused.kernels()
    rb, cb = plan["bin_index"]
    if fused is not None and rb is not None and cb is not None:
        n_b = plan["bin_rows"].shape[0]
        out = np.empty((n_b, n_b))
        fused[3](acc["s"][0], acc["x"][0], acc["s"][1], acc["x"][1], rb, cb, out)
        return out
    parts = []
    for q in (0, 1):
        nl = acc["x"][q].shape[-1]
        s = 2.0 * (acc["s"][q][:, :nl] + acc["s"][q][:, nl:])
        parts += [s + 4.0 * acc["x"][q], s - 4.0 * acc["x"][q]]
    img = np.concatenate(parts).astype(np.float64)
    perm = plan["bin_perm"]
    if perm[0] is not None and perm[1] is not None:
        n_b = plan["bin_rows"].shape[0]
        rows = img[perm[0]].reshape(n_b, -1, img.shape[1]).sum(axis=1)
        return rows[:, perm[1]].reshape(n_b, n_b, -1).sum(axis=2)
    rows = plan["bin_rows"] @ img
    return (plan["bin_cols"] @ rows.T).T


def frame_derivatives(
    plan: dict, work: dict, chunks: list[Chunk], field: np.ndarray, dphase: np.ndarray
) -> np.ndarray:
    """Derivatives of the detector frame of a pupil field along phase directions.

    ``dI = sum_k 2 Re(conj(P_k E) P_k(i dphi E))`` with ``P_k`` the (linear) propagation of
    modulation point ``k``: the exact linearisation, one propagation per direction.

    Parameters
    ----------
    plan, work, chunks
        As for :func:`pair_fields`.
    field : ndarray, shape (n_pix, n_pix)
        Pupil field ``E`` around which to linearise (:func:`pair_fields`).
    dphase : ndarray, shape (m, n_pix, n_pix)
        Phase directions [rad].

    Returns
    -------
    ndarray, shape (m, 2 n_sub, 2 n_sub)
        Frame change per radian along each direction.
    """
    real = plan["kern"][0].dtype
    n_b = plan["bin_rows"].shape[0]
    out = np.empty((dphase.shape[0], n_b, n_b))
    fused = _pyramid_fused.kernels()
    if fused is not None:
        # copies of the base products and step-y inputs: the generator reuses its buffers
        base = [
            (f0.copy(), f1.copy(), n, [x_.copy() for x_ in xq])
            for f0, f1, n, xq in pair_fields(plan, work, chunks, field, fused)
        ]
        acc = {k: work[k] for k in ("s", "x")}
        for i in range(dphase.shape[0]):
            for a in acc["s"] + acc["x"]:
                a.fill(0.0)
            dfield = 1j * dphase[i].astype(real) * field
            for f, h in zip(base, pair_fields(plan, work, chunks, dfield, fused), strict=True):
                for q in (0, 1):
                    d = plan["delta"][q][:, 0, 0]
                    src = plan["pairs"][q].src
                    fused[4](
                        f[q], f[3][q], h[q], h[3][q], src, d[0], d[1], 2.0, acc["s"][q], acc["x"][q]
                    )
            out[i] = bin_frame(plan, acc)
        return out
    # copies of the base fields: the generator reuses its buffers
    base = [(f0.copy(), f1.copy(), n) for f0, f1, n in pair_fields(plan, work, chunks, field)]
    for i in range(dphase.shape[0]):
        acc = new_accumulators(work)
        dfield = 1j * dphase[i].astype(real) * field
        for f0, f1 in zip(base, pair_fields(plan, work, chunks, dfield), strict=True):
            accumulate(acc, f0, f1, 2.0)
        out[i] = bin_frame(plan, acc)
    return out
