"""The pyramid's 1-D line operator, split by parity (private helper of
:mod:`._pyramid_propagation`).

Along one axis, the propagation "zero-pad the ``n_pix`` pupil samples to ``n_fft``, FFT,
multiply by one factor of the pyramid mask, inverse FFT, keep the detector lines" is a linear
map ``L`` from ``n_pix`` pupil samples to ``n_lines`` detector lines: the circulant matrix of
the kernel ``k = IFFT(m)`` restricted to those rows and columns, ``L[l, y] = k(l - y)``.

The mask factor is two linear phases (the two faces), ``m(u) = e^{+i pi/4} w^{u s1}`` for
``u >= 0`` and ``e^{-i pi/4} w^{u s2}`` for ``u < 0`` (``w = e^{2 i pi / n}``, integer shifts
``s1 = n/4 - r0``, ``s2 = s1 - n/2``). Summing the two geometric series,

    k(d) = (e^{i pi/4} [d + s1 = 0 mod n] + e^{-i pi/4} [d + s2 = 0 mod n]) / 2       (d + s1 even)
    k(d) = (2/n) (e^{i pi/4} / (1 - w^{d+s1}) - e^{-i pi/4} / (1 + w^{d+s1}))        (d + s1 odd)

(``n`` even, so ``d + s1`` and ``d + s2`` have one parity): a detector line sees the pupil
samples of one parity through the dense Hilbert-like kernel and, of the other parity, only the
one sample of its direct image (the delta). So ``L @ v`` costs half a dense product:
``H_q @ v[1-q::2]`` for the lines of class ``q`` plus the deltas, an exact rewrite of the
FFT-mask-FFT propagation (the zero entries are zero in exact arithmetic; here they are below
1e-12 of the largest entry and dropped, which :func:`line_operator` checks).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg.blas as _blas

# Entries of the line operator below this fraction of its largest one are the exact zeros of
# the parity structure (double-precision FFT rounding is ~1e-16).
_ZERO = 1e-12


@dataclass(frozen=True)
class LineClass:
    """The detector lines of one parity class ``q`` and their operator.

    ``lines``: positions among the detector lines ``(n_q,)``; ``dense``: ``(n_q, n_{1-q})``,
    acting on the pupil samples ``y = 1-q, 3-q, ...``; ``runs``: the deltas as
    ``(first line, end line, first source sample in y = q, q+2, ..., value)``, consecutive
    lines reading consecutive samples with one value (one run per pupil image).
    """

    lines: np.ndarray
    dense: np.ndarray
    runs: tuple[tuple[int, int, int, complex], ...]


def line_operator(n_fft: int, n_pix: int, mask: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """``L`` ``(n_lines, n_pix)`` [complex128]: pad, FFT, ``mask``, inverse FFT, ``lines``."""
    eye = np.zeros((n_fft, n_pix))
    eye[np.arange(n_pix), np.arange(n_pix)] = 1.0
    return np.fft.ifft(mask[:, None] * np.fft.fft(eye, axis=0), axis=0)[lines]


def parity_classes(op: np.ndarray) -> tuple[LineClass, LineClass]:
    """Split ``op`` (from :func:`line_operator`) into its two parity classes (module docstring).

    Raises
    ------
    RuntimeError
        If ``op`` does not have the structure (a mask that is not two integer linear phases).
    """
    mag = np.abs(op)
    tol = _ZERO * mag.max()
    nonzero = [np.count_nonzero(mag[:, p::2] > tol, axis=1) for p in (0, 1)]
    # class q: at most one non-zero (the delta) on the samples of parity q
    q_of_line = np.where(nonzero[0] <= 1, 0, 1)
    bad = (nonzero[0] > 1) & (nonzero[1] > 1)
    if np.any(bad):
        raise RuntimeError(
            f"the pyramid line operator lacks its parity structure on {np.count_nonzero(bad)} "
            "lines (the mask must be two linear phases with integer shifts)"
        )
    out = []
    for q in (0, 1):
        lines = np.flatnonzero(q_of_line == q)
        delta = op[lines][:, q::2]
        src = np.argmax(np.abs(delta), axis=1)
        val = delta[np.arange(lines.size), src]
        val = np.where(np.abs(val) > tol, val, 0.0)
        runs: list[tuple[int, int, int, complex]] = []
        for i in range(lines.size):
            if val[i] == 0:
                continue
            if runs and runs[-1][1] == i and src[i] == runs[-1][2] + i - runs[-1][0]:
                if abs(val[i] - runs[-1][3]) <= tol:
                    runs[-1] = (runs[-1][0], i + 1, runs[-1][2], runs[-1][3])
                    continue
            runs.append((i, i + 1, int(src[i]), complex(val[i])))
        dense = op[lines][:, 1 - q :: 2]
        out.append(LineClass(lines, np.where(np.abs(dense) > tol, dense, 0.0), tuple(runs)))
    return out[0], out[1]


_GEMM = {
    np.dtype(np.complex64): _blas.cgemm,
    np.dtype(np.complex128): _blas.zgemm,
    np.dtype(np.float32): _blas.sgemm,
    np.dtype(np.float64): _blas.dgemm,
}


def gemm_acc(a: np.ndarray, b: np.ndarray, c: np.ndarray, beta: float = 1.0) -> None:
    """``c = beta c + a @ b`` in place (C-contiguous 2-D arrays, real or complex, one dtype;
    BLAS ``gemm``; ``beta = 1`` accumulates, ``0`` overwrites)."""
    gemm = _GEMM[c.dtype]
    # in Fortran order the C-contiguous arrays are the transposes: c.T += b.T @ a.T
    res = gemm(1.0, b.T, a.T, beta=beta, c=c.T, overwrite_c=True)
    if not np.may_share_memory(res, c):  # pragma: no cover - a BLAS wrapper that copied
        c[...] = res.T


def apply_runs(runs, src: np.ndarray, out: np.ndarray) -> None:
    """Write the deltas of ``runs`` (:class:`LineClass`) from ``src`` rows into ``out`` rows
    (``out`` rows not covered by a run are set to zero)."""
    covered = 0
    for r0, r1, s0, value in runs:
        np.multiply(src[s0 : s0 + r1 - r0], value, out=out[r0:r1])
        covered += r1 - r0
    if covered < out.shape[0]:
        mask = np.ones(out.shape[0], dtype=bool)
        for r0, r1, _, _ in runs:
            mask[r0:r1] = False
        out[mask] = 0


@dataclass(frozen=True)
class ImagePairs:
    """The detector lines of one parity class ``q`` in the two pupil images, as conjugate pairs.

    A line ``l`` of the first image and its partner ``l + n/2`` of the second see the pupil
    samples of parity ``1-q`` through ``u - i v + c0`` and ``u + i v + c0`` (``u, v`` real,
    ``c0`` one imaginary constant: the kernel's DC term, the same for both faces) and their one
    direct-image sample of parity ``q`` through ``delta`` and ``conj(delta)``: the two faces
    are complex conjugate up to the constant (module docstring: the kernel is ``1/2 + i/2
    cot`` and ``1/2 - i/2 tan``, and ``tan`` is ``cot`` shifted by ``n/2``).

    ``first``, ``second``: positions in the line list ``(n_l,)``; ``u``, ``v``: ``(n_l,
    n_{1-q})`` real; ``c0``: complex; ``src``: index of the first line's direct-image sample
    among the samples of parity ``q`` (consecutive lines read consecutive samples); ``delta``:
    complex, the same for every line (one face's direct image: one value).
    """

    first: np.ndarray
    second: np.ndarray
    u: np.ndarray
    v: np.ndarray
    c0: complex
    src: int
    delta: complex


def image_pairs(op: np.ndarray, lines: np.ndarray, n_fft: int) -> tuple[ImagePairs, ImagePairs]:
    """Split ``op`` (:func:`line_operator` on ``lines``) into the conjugate pairs of both parity
    classes (:class:`ImagePairs`); every structural assumption is checked.

    Raises
    ------
    RuntimeError
        If the lines do not pair up (``l`` and ``l + n_fft/2``) or the operator lacks the
        conjugate structure.
    """
    half = n_fft // 2
    mag = np.abs(op)
    tol = _ZERO * mag.max()
    first_all = np.flatnonzero(lines < half)
    pos = np.searchsorted(lines, lines[first_all] + half)
    if (
        pos.max(initial=0) >= lines.size
        or np.any(lines[np.minimum(pos, lines.size - 1)] != lines[first_all] + half)
        or 2 * first_all.size != lines.size
    ):
        raise RuntimeError("the detector lines do not pair up between the two pupil images")
    out = []
    for q in (0, 1):
        dense_par = np.count_nonzero(mag[first_all][:, 1 - q :: 2] > tol, axis=1) > 1
        keep = np.flatnonzero(dense_par)
        first, second = first_all[keep], pos[keep]
        d1, d2 = op[first][:, 1 - q :: 2], op[second][:, 1 - q :: 2]
        c0 = 0.5j * float(np.mean((d2 - np.conj(d1)).imag))
        k = d1 - c0
        l1, l2 = op[first][:, q::2], op[second][:, q::2]
        src = np.argmax(np.abs(l1), axis=1)
        delta = l1[np.arange(first.size), src]
        bad = (
            np.abs(d2 - c0 - np.conj(k)).max(initial=0) > tol
            or np.abs(l2 - np.conj(l1)).max(initial=0) > tol
            or np.count_nonzero(np.abs(l1) > tol) > first.size
            or np.any(np.abs(delta) <= tol)
            or np.any(src - np.arange(first.size) != src[0])
            or np.abs(delta - delta[0]).max() > tol
        )
        if bad:
            raise RuntimeError(
                "the pyramid line operator lacks its conjugate structure between the two "
                "pupil images (the mask must be two opposite linear phases, n_fft >= 2 n_pix)"
            )
        out.append(
            ImagePairs(first, second, k.real.copy(), -k.imag, c0, int(src[0]), complex(delta[0]))
        )
    if out[0].first.size + out[1].first.size != first_all.size:
        raise RuntimeError("the pyramid line operator lacks its parity structure")
    return out[0], out[1]


def bin_permutation(b: np.ndarray) -> np.ndarray | None:
    """Order of the lines (columns of the binning matrix ``b``) by bin when every line falls
    in one bin with weight 1 and every bin holds the same number of lines, else ``None``."""
    one = (b == 1.0).sum(axis=0) == 1
    counts = (b != 0).sum(axis=0)
    per_bin = (b != 0).sum(axis=1)
    if not (np.all(one) and np.all(counts == 1) and np.all(per_bin == per_bin[0])):
        return None
    return np.argsort(np.argmax(b, axis=0), kind="stable")
