"""Diffractive (Fourier-optics) pyramid wavefront sensor with circular modulation.

Optical model
-------------
The pupil field ``A exp(i 2 pi OPD / lambda)`` is zero-padded to ``n_fft x n_fft`` and Fourier
transformed to the focal plane (``n_fft / n_pix`` samples per lambda/D), multiplied by the
phase mask of a four-faced glass pyramid, ``exp(i pi/2 (|u| + |v|))`` (``u, v`` in focal
samples; each face is a tilt that shifts its pupil image by ``n_fft / 4`` samples), and
transformed back to the pupil plane where the detector sees four pupil images. The PSF is
centred on the corner of 4 samples, on the pyramid apex (OOPAO's ``psfCentering=True``).

Circular modulation of radius ``modulation`` lambda/D with ``n_modulation_points`` equally
spaced points (the first on the x axis) tilts the beam: the detector intensity is the sum over
the points of the propagated intensities (the discrete model of OOPAO: tilt, FFT, mask,
inverse FFT, per point; identical to rounding, tested).

Computation. The pyramid mask and the tilts factor into x and y parts, so the propagation of
one point is ``L diag(t_y) E diag(t_x) L^T`` with ``E`` the pupil field and ``L`` the 1-D line
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
per parity class for all points: half the FLOPs of the complex per-point products it replaced
(issue 15: 135 instead of 213 MFLOP per frame at SAXO+ sampling, ``benchmarks/bench_pyramid.py
--flops``). Single precision by default (``complex64`` / ``float32``; the difference from
double precision is < 1e-5 of the largest pixel, tested against frames of the former
propagation). Threads: ``workers`` BLAS threads during each call. The element-wise passes
between and after the products (y tilts, constant row, direct images, intensity sums) are two
compiled loops (:mod:`._pyramid_fused`, numba; the numpy passes without numba or with
``$AOCONTROL_NO_NUMBA``): the same frames to float32 rounding (the sums in float64); CPU per
frame at SAXO+ sampling (80 px, 40x40) 1.21x less at 40 points, 1.35x at 20, and 1.18x less
for the whole closed-loop frame of ``benchmarks/bench_pyramid.py`` (500 modes; issue 19,
alternating rounds in one process, load 17-24).

Detector and signals
--------------------
Each pupil image (``n_pix`` samples across) is rebinned (area weighting) to
``n_subapertures`` detector pixels across; the four images are cut out without the gap
(``pupil_separation`` detector pixels, as OOPAO's ``n_pix_separation``) into one frame of
shape ``(2 n_sub, 2 n_sub)``: quadrants ``[[I0, I1], [I2, I3]]``. Valid subapertures are those
whose geometric illumination by the pupil is at least ``valid_threshold``.

``signal_type="slopes"`` (OOPAO ``'slopesMaps'``, COMPASS ``pyrhr`` slopes): per valid
subaperture ``Sx = (I0 + I2 - I1 - I3) / n``, ``Sy = (I0 + I1 - I2 - I3) / n`` with ``n`` the
mean flux per valid subaperture (sum of the 4 images; global normalisation by the total flux);
signals ``[Sx, Sy]``, shape ``(2 n_valid_sub,)``, positive for an optical path increasing along
``+x`` (columns) / ``+y`` (rows). ``signal_type="full_frame"`` (OOPAO ``'fullFrame'``): the 4
images on the valid subapertures divided by ``n``, shape ``(4 n_valid_sub,)``. Both minus the
signals of a flat wavefront, dimensionless.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse

from aocontrol._validation import (
    check_finite_array,
    check_in_range,
    check_int,
    check_nonnegative,
    check_positive,
)
from aocontrol.sim.noise import add_detector_noise
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.wfs import _pyramid_fused
from aocontrol.sim.wfs._common import bin_matrix, blas_threads, check_opd, opd_to_phase
from aocontrol.sim.wfs._pyramid_lines import (
    apply_runs,
    bin_permutation,
    gemm_acc,
    image_pairs,
    line_operator,
    parity_classes,
)

__all__ = ["PyramidWFS", "default_modulation_points"]

logger = logging.getLogger(__name__)

#: Target size of the y step's products per chunk of modulation pairs [bytes]: large, one
#: chunk at SAXO+ sampling (smaller chunks measured slower: more, smaller calls).
_CHUNK_BYTES = 2**23


def default_modulation_points(modulation: float) -> int:
    """Default number of modulation points: ``4 ceil(pi r)``, i.e. ~2 points per lambda/D of
    the modulation circle's perimeter ``2 pi r`` rounded up to a multiple of 4 (1 when ``r=0``).

    Parameters
    ----------
    modulation : float
        Modulation radius [lambda/D], >= 0.
    """
    r = check_nonnegative("modulation", modulation)
    return 1 if r == 0 else 4 * math.ceil(math.pi * r)


@dataclass(frozen=True)
class PyramidWFS:
    """Modulated pyramid WFS, Fourier-optics model (see the module docstring).

    Parameters
    ----------
    pupil : Pupil
        Pupil grid; OPD maps have shape ``(..., n_pix, n_pix)`` [nm].
    wavelength : float
        Sensing wavelength [m] (1.04e-6 to 1.14e-6 for the SAXO+ second stage).
    n_subapertures : int, default 40
        Detector pixels across each pupil image; ``pupil.n_pix >= n_subapertures``.
    modulation : float, default 3.0
        Modulation radius [lambda/D], >= 0 and < ``n_pix / 4``.
    n_modulation_points : int, optional
        Points on the modulation circle; default :func:`default_modulation_points`.
    signal_type : {"slopes", "full_frame"}
        Signal post-processing (module docstring).
    pupil_separation : float, default 2.0
        Gap between adjacent pupil images [detector pixels] (sets the padding ``n_fft``).
    valid_threshold : float, default 0.5
        Minimum geometric illumination of a valid subaperture, in (0, 1].
    precision : {"single", "double"}
        FFT precision (complex64 or complex128).
    workers : int, default 1
        BLAS threads of the propagation's matrix products, set for the duration of each call
        (``threadpoolctl``; the setting is process-wide while the call runs). 1 by default:
        on a machine shared with other jobs a multi-threaded BLAS stalls on products of this
        size (measured: 5-10x slower).

    Examples
    --------
    >>> from aocontrol.sim.pupil import Pupil
    >>> wfs = PyramidWFS(Pupil(n_pix=16), wavelength=1.04e-6, n_subapertures=8, modulation=2.0)
    >>> wfs.n_points, wfs.n_fft, wfs.signals(np.zeros((16, 16))).shape
    (28, 40, (104,))
    """

    pupil: Pupil
    wavelength: float
    n_subapertures: int = 40
    modulation: float = 3.0
    n_modulation_points: int | None = None
    signal_type: str = "slopes"
    pupil_separation: float = 2.0
    valid_threshold: float = 0.5
    precision: str = "single"
    workers: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.pupil, Pupil):
            raise TypeError(f"pupil must be a Pupil, got {type(self.pupil).__name__}")
        check_positive("wavelength", self.wavelength)
        n_sub = check_int("n_subapertures", self.n_subapertures, minimum=2)
        if self.pupil.n_pix < n_sub:
            raise ValueError(
                f"pupil.n_pix must be >= n_subapertures={n_sub} (at least one pupil sample per "
                f"subaperture), got pupil.n_pix={self.pupil.n_pix}: sampling too coarse"
            )
        r = check_nonnegative("modulation", self.modulation)
        if r >= self.pupil.n_pix / 4:
            raise ValueError(
                f"modulation must be < pupil.n_pix / 4 = {self.pupil.n_pix / 4} lambda/D "
                f"(the modulated PSF must stay inside the focal field), got {r}"
            )
        if self.n_modulation_points is not None:
            check_int("n_modulation_points", self.n_modulation_points, minimum=1)
        if self.signal_type not in ("slopes", "full_frame"):
            raise ValueError(
                f"signal_type must be 'slopes' or 'full_frame', got {self.signal_type!r}"
            )
        check_nonnegative("pupil_separation", self.pupil_separation)
        check_in_range(
            "valid_threshold",
            self.valid_threshold,
            0.0,
            1.0,
            low_inclusive=False,
            high_inclusive=True,
        )
        if self.precision not in ("single", "double"):
            raise ValueError(f"precision must be 'single' or 'double', got {self.precision!r}")
        check_int("workers", self.workers, minimum=1)

    # ------------------------------------------------------------------ geometry
    @property
    def n_points(self) -> int:
        """Modulation points actually used."""
        if self.n_modulation_points is not None:
            return int(self.n_modulation_points)
        return default_modulation_points(self.modulation)

    @property
    def n_fft(self) -> int:
        """FFT size: ``2 n_pix`` plus the gaps and edges, rounded up to a multiple of 4."""
        n_pix = self.pupil.n_pix
        gap = self.pupil_separation * n_pix / self.n_subapertures
        return 4 * math.ceil((2 * n_pix + 2 * gap) / 4 - 1e-9)

    @property
    def samples_per_lambda_over_d(self) -> float:
        """Focal-plane sampling [samples per lambda/D]."""
        return self.n_fft / self.pupil.n_pix

    @property
    def _complex(self) -> type:
        return np.complex64 if self.precision == "single" else np.complex128

    @property
    def _real(self) -> type:
        return np.float32 if self.precision == "single" else np.float64

    @cached_property
    def modulation_offsets(self) -> np.ndarray:
        """Modulation points [lambda/D], shape ``(n_points, 2)`` as ``(x, y)``."""
        theta = 2 * np.pi * np.arange(self.n_points) / self.n_points
        out = self.modulation * np.stack([np.cos(theta), np.sin(theta)], axis=-1)
        out.setflags(write=False)
        return out

    @cached_property
    def _pairs(self) -> tuple[np.ndarray, int]:
        """Modulation points by mirror pairs ``(k, n_points - k)`` (the same x tilt, opposite y
        tilts): the ``k`` of the pairs, the ``n_ns`` two-point pairs first, then the points on
        the x axis (``k = 0`` and ``n_points / 2``), each its own mirror."""
        n = self.n_points
        two = [k for k in range(1, n) if k < n - k]
        one = [k for k in range(n // 2 + 1) if k == (n - k) % n]
        return np.array(two + one, dtype=int), len(two)

    @cached_property
    def _chunks(self) -> list[tuple[int, int, bool]]:
        """Chunks of pairs ``(j0, j1, two_point)`` for the y step: a few two-point pairs at a
        time (their products stay in the core's cache), then the one-point pairs."""
        k, n_ns = self._pairs
        n_q = 2 * self.pupil.n_pix  # detector lines
        per_pair = 2 * self.pupil.n_pix * 2 * 2 * n_q * np.dtype(self._real).itemsize
        step = max(1, _CHUNK_BYTES // per_pair)
        out = [(j0, min(j0 + step, n_ns), True) for j0 in range(0, n_ns, step)]
        if k.size > n_ns:
            out.append((n_ns, k.size, False))
        return out

    @cached_property
    def _plan(self) -> dict:
        """Precomputed tilts, line operators, pair kernels and binning (module docstring)."""
        n, n_pix = self.n_fft, self.pupil.n_pix
        q = self.samples_per_lambda_over_d
        x = np.arange(n_pix)
        k, n_ns = self._pairs
        # beam tilt of each pair [focal samples]: (a, +-b)
        a = self.modulation_offsets[k, 0] * q
        b = self.modulation_offsets[k[:n_ns], 1] * q
        tx = np.exp(2j * np.pi * (a[:, None] - 0.5) * x[None, :] / n)
        # one face of the pyramid per half line; the apex between samples -1 and 0; the ramp
        # places the pupil (transformed from the array corner) at r0 in the padded array
        u = np.fft.fftfreq(n) * n
        r0 = (n - n_pix) // 2
        m1 = np.exp(0.5j * np.pi * np.abs(u + 0.5) - 2j * np.pi * r0 * u / n)
        lines = np.flatnonzero(np.any(self._binning_full != 0, axis=0))
        op = line_operator(n, n_pix, m1, lines)
        classes = parity_classes(op)
        pairs = image_pairs(op, lines, n)
        order = np.concatenate([c.lines for c in classes])  # x lines, class by class
        rows = np.concatenate([np.r_[p.first, p.second] for p in pairs])  # y lines
        c, r = self._complex, self._real
        n_p = [len(range(p, n_pix, 2)) for p in (0, 1)]
        n_m = max(n_p)
        # column groups: (cos, sin) of the y tilt of each two-point pair, then the one-point
        # pairs (b = 0) weighted 1/sqrt(2): one formula for both (module docstring)
        n_one = k.size - n_ns
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
                self.pupil.mask
                * np.exp(-1j * np.pi * x / n)[:, None]  # half-sample centring along y
                / math.sqrt(self.pupil.n_valid * self.n_points)
            ).astype(c),
            "classes": classes,
            "pairs": pairs,
            "n_ns": n_ns,
            "n_m": n_m,
            # tilts split by the parity of the pupil sample: tx (n_x, n_p)
            "tx": [np.ascontiguousarray(tx[:, p::2], dtype=c) for p in (0, 1)],
            "dense_t": [np.ascontiguousarray(k_.dense.T, dtype=c) for k_ in classes],
            "w": np.ascontiguousarray(w[..., None], dtype=r),
            "w1": np.ascontiguousarray(w1[..., None], dtype=r),
            # c0 of the class whose dense part reads the samples of parity p
            "y0": np.array([pairs[1].c0.imag, pairs[0].c0.imag]),
            "kern": kern,
            "delta": [
                np.array([p_.delta.real, -p_.delta.imag], dtype=r)[:, None, None] for p_ in pairs
            ],
            # sparse, not BLAS: small GEMMs stall in multi-threaded OpenBLAS on a busy machine
            "bin_rows": scipy.sparse.csr_matrix(self._binning_full[:, lines[rows]]),
            "bin_cols": scipy.sparse.csr_matrix(self._binning_full[:, lines[order]]),
            # an integer binning factor: each line in one bin, summed by a reshape
            "bin_perm": [bin_permutation(self._binning_full[:, lines[i]]) for i in (rows, order)],
        }
        for v in plan.values():
            if isinstance(v, np.ndarray):
                v.setflags(write=False)
        return plan

    @cached_property
    def _binning_full(self) -> np.ndarray:
        """Crop-and-bin matrix ``(2 n_sub, n_fft)``: rows of both pupil images, rebinned."""
        n, n_pix, n_sub = self.n_fft, self.pupil.n_pix, self.n_subapertures
        b = bin_matrix(n_pix, n_sub)
        out = np.zeros((2 * n_sub, n))
        r0 = (n - n_pix) // 2
        for h, shift in enumerate((-n // 4, n // 4)):
            start = r0 + shift
            out[h * n_sub : (h + 1) * n_sub, start : start + n_pix] = b
        return out

    @cached_property
    def valid_subapertures(self) -> np.ndarray:
        """Boolean map ``(n_sub, n_sub)`` of the valid subapertures (geometric illumination)."""
        b = bin_matrix(self.pupil.n_pix, self.n_subapertures)
        area = (self.pupil.n_pix / self.n_subapertures) ** 2
        illum = b @ self.pupil.mask.astype(float) @ b.T / area
        valid = illum >= self.valid_threshold * (1 - 1e-9)
        valid.setflags(write=False)
        return valid

    @property
    def n_valid_subapertures(self) -> int:
        """Number of valid subapertures."""
        return int(np.count_nonzero(self.valid_subapertures))

    @property
    def n_signals(self) -> int:
        """Length of a signal vector."""
        k = 2 if self.signal_type == "slopes" else 4
        return k * self.n_valid_subapertures

    @property
    def frame_shape(self) -> tuple[int, int]:
        """Detector frame shape ``(2 n_sub, 2 n_sub)``."""
        return (2 * self.n_subapertures, 2 * self.n_subapertures)

    # ------------------------------------------------------------------ propagation
    @cached_property
    def _work(self) -> dict[str, list[np.ndarray]]:
        """Work buffers kept across frames (a few MB, allocated once; lists over the parity
        ``p`` of the pupil samples or the class ``q`` of the detector lines).

        ``a[p]`` ``(2, n_m, n_x, n_p)``: the field times each pair's x tilt on the columns ``x
        = p, p+2, ...``, rows by parity (``n_m`` the larger count; spare rows zero);
        ``gq[q]`` ``(2 n_m n_x, n_q)``: step x (complex, lines of class ``q``); ``xs`` (per
        parity ``p``, then per chunk of pairs, :attr:`_chunks`) ``(n_m + 1, n_g, 2 n_lines)``:
        the rows of parity ``p`` times the cosine and sine of each pair's y tilt, real parts
        then imaginary parts, and the constant row; ``o[q]`` (flat, ``(n_l, 2, n_g, 2
        n_lines)`` for a chunk): step y, the products ``U`` and ``V`` of the chunk's column
        groups; ``s[q]`` ``(n_l, 2 n_lines)`` and ``x[q]`` ``(n_l,
        n_lines)``: intensity accumulators. They make an instance not thread-safe (use one
        instance per thread) and are not pickled.
        """
        plan = self._plan
        c, r = self._complex, self._real
        n_x, n_m = plan["tx"][0].shape[0], plan["n_m"]
        n_q = [k.lines.size for k in plan["classes"]]
        n_l = [pr.first.size for pr in plan["pairs"]]
        n_px = [plan["tx"][p].shape[1] for p in (0, 1)]
        nl = sum(n_q)
        chunks = self._chunks
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

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_work", None)  # buffers, rebuilt on first use
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    def _fields(self, field: np.ndarray, fused: tuple | None = None):
        """Detector-plane fields of all modulation points, as pair products.

        Yields one tuple ``(o0, o1)``, ``o_q`` of shape ``(n_l, 2, n_g, 2 n_lines)`` (real
        parts, then imaginary parts): the products ``U`` and ``V`` of the class-``q`` lines
        (module docstring) for the column groups (cosine and sine of each two-point pair, then
        the one-point pairs) by all detector columns (class by class), from a pupil field
        ``(n_pix, n_pix)`` (amplitude and half-sample centring included). Step x (``L`` along
        x) is one complex product per class for all pairs; step y one real product per class
        for all pairs, after the direct images are written.

        The arrays are the work buffers (:attr:`_work`): valid until the generator advances
        (copy them to keep them).

        ``fused``: the compiled kernels of :mod:`._pyramid_fused`; the y tilts are then one
        compiled pass, the products are written without the direct images, and the tuples
        hold a fourth item, the chunk's step-y inputs ``[x0, x1]`` (the direct images are
        ``x_q[src + l] * delta_q``: :meth:`_frames` adds them while it sums the intensities).
        """
        plan, work = self._plan, self._work
        classes, dense_t = plan["classes"], plan["dense_t"]
        a, gq, xs, o = work["a"], work["gq"], work["xs"], work["o"]
        n_m, r = plan["n_m"], self._real
        n0 = classes[0].lines.size
        nl = n0 + classes[1].lines.size
        # step x: gq[q][(p, y', t), l] = sum_x field[p + 2 y', x] tx[t, x] L[l, x] (lines of
        # class q)
        for px in (0, 1):
            for py in (0, 1):
                f = field[py::2, px::2]
                np.multiply(f[:, None], plan["tx"][px][None], out=a[px][py, : f.shape[0]])
        for q in (0, 1):
            apply_runs(classes[q].runs, a[q].reshape(-1, a[q].shape[-1]).T, gq[q].T)
            gemm_acc(a[1 - q].reshape(-1, a[1 - q].shape[-1]), dense_t[q], gq[q])
        # (parity, y', pair, line, real/imaginary) views of step x's output
        gqv = [gq[q].view(r).reshape(2, n_m, -1, gq[q].shape[-1], 2) for q in (0, 1)]
        cols = (slice(0, n0), slice(n0, nl))
        # per chunk of pairs: the y tilts, xs[p][y', group] = (cos, sin)(beta y) g[p, y', pair]
        # (1/sqrt(2) for the one-point pairs) and the constant row; then step y, the direct
        # images and o[q] += [u 1; v 0] @ xs[1-q]
        chunks = self._chunks
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
                                out=x[p][:n_m].reshape(n_m, j1 - j0, 2, 2, nl)[
                                    :, :, :, c, cols[qx]
                                ],
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

    def _accumulate(self, acc: dict, f: tuple, h: tuple, scale: float = 1.0) -> None:
        """``acc`` += ``scale`` times the bilinear intensity terms of the fields ``f`` and ``h``
        (:meth:`_fields`; ``f = h`` gives the intensity): ``s[q]``, the sum of ``Re(conj(f)
        h)`` per real/imaginary part over all products, and ``x[q]``, the symmetrised cross
        terms ``Im(V_s conj(U_s)) - Im(U_c conj(V_c))`` (the first image is ``2 s + 4 x``,
        the second ``2 s - 4 x``; module docstring)."""
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

    def _bin(self, acc: dict) -> np.ndarray:
        """Accumulators (:meth:`_accumulate`) -> detector frame ``(2n_sub, 2n_sub)``."""
        parts = []
        for q in (0, 1):
            nl = acc["x"][q].shape[-1]
            s = 2.0 * (acc["s"][q][:, :nl] + acc["s"][q][:, nl:])
            parts += [s + 4.0 * acc["x"][q], s - 4.0 * acc["x"][q]]
        img = np.concatenate(parts).astype(np.float64)
        perm = self._plan["bin_perm"]
        if perm[0] is not None and perm[1] is not None:
            n_b = self._binning_full.shape[0]
            rows = img[perm[0]].reshape(n_b, -1, img.shape[1]).sum(axis=1)
            return rows[:, perm[1]].reshape(n_b, n_b, -1).sum(axis=2)
        rows = self._plan["bin_rows"] @ img
        return (self._plan["bin_cols"] @ rows.T).T

    def _new_acc(self) -> dict:
        return {k: [np.zeros_like(a) for a in self._work[k]] for k in ("s", "x")}

    def _field(self, phase: np.ndarray) -> np.ndarray:
        return self._plan["amp"] * np.exp(1j * phase.astype(self._real))

    def _frames(self, phase: np.ndarray) -> np.ndarray:
        """Detector frames ``(m, 2 n_sub, 2 n_sub)`` of phase maps ``(m, n_pix, n_pix)`` [rad]."""
        out = np.empty((phase.shape[0], *self.frame_shape))
        acc = {k: self._work[k] for k in ("s", "x")}
        fused = _pyramid_fused.kernels()
        delta = self._plan["delta"]
        with self._blas_threads():
            for i in range(phase.shape[0]):
                for a in acc["s"] + acc["x"]:
                    a.fill(0.0)
                for f in self._fields(self._field(phase[i]), fused):
                    if fused is None:
                        self._accumulate(acc, f, f)
                        continue
                    for q in (0, 1):
                        src = self._plan["pairs"][q].src
                        d = delta[q][:, 0, 0]
                        fused[1](f[q], f[3][q], src, d[0], d[1], acc["s"][q], acc["x"][q])
                out[i] = self._bin(acc)
        return out

    def _blas_threads(self):
        """Context: ``workers`` BLAS threads (the products of :meth:`_fields`)."""
        return blas_threads(self.workers)

    def frame_derivative(self, opd: np.ndarray, delta_opd: np.ndarray) -> np.ndarray:
        """Derivative of the detector frame at ``opd`` in the directions ``delta_opd``.

        ``dI = sum_k 2 Re(conj(P_k E) P_k(i dphi E))`` with ``P_k`` the (linear) propagation
        of modulation point ``k``: the exact linearisation, one propagation per direction.

        Parameters
        ----------
        opd : array, shape (n_pix, n_pix)
            OPD [nm] around which to linearise.
        delta_opd : array, shape (m, n_pix, n_pix)
            Directions [nm].

        Returns
        -------
        ndarray, shape (m, 2 n_sub, 2 n_sub)
            Frame change per unit of ``delta_opd`` (fraction of the flux per nm).
        """
        n_pix = self.pupil.n_pix
        opd = check_finite_array("opd", opd, ndim=2)
        delta = check_finite_array("delta_opd", delta_opd, ndim=3)
        if opd.shape != (n_pix, n_pix) or delta.shape[1:] != (n_pix, n_pix):
            raise ValueError(
                f"opd and delta_opd must end with shape ({n_pix}, {n_pix}), got "
                f"{opd.shape} and {delta.shape}"
            )
        field = self._field(opd_to_phase(opd, self.wavelength))
        dphase = opd_to_phase(delta, self.wavelength)
        out = np.empty((delta.shape[0], *self.frame_shape))
        with self._blas_threads():
            # copies of the base fields: the generator reuses its buffers
            base = [(f0.copy(), f1.copy(), n) for f0, f1, n in self._fields(field)]
            for i in range(delta.shape[0]):
                acc = self._new_acc()
                dfield = 1j * dphase[i].astype(self._real) * field
                for f0, f1 in zip(base, self._fields(dfield), strict=True):
                    self._accumulate(acc, f0, f1, 2.0)
                out[i] = self._bin(acc)
        return out

    def signal_derivative(self, opd: np.ndarray, delta_opd: np.ndarray) -> np.ndarray:
        """Derivative of the signals at ``opd`` in the directions ``delta_opd``.

        Parameters
        ----------
        opd : array, shape (n_pix, n_pix)
            OPD [nm] around which to linearise.
        delta_opd : array, shape (m, n_pix, n_pix)
            Directions [nm].

        Returns
        -------
        ndarray, shape (m, n_signals)
            Signal change per unit of ``delta_opd`` [per nm] (flux normalisation included).
        """
        frame = self.detector_image(opd)
        dframes = self.frame_derivative(opd, delta_opd)
        p = self.pixel_values(frame)
        dp = self.pixel_values(dframes)  # (m, 4 nv)
        nv = self.n_valid_subapertures
        norm = p.sum() / nv
        s_raw = self._raw_signals(frame)
        # s = A p / n(p) with n = sum(p) / nv: ds = (A dp - s_raw dn) / n
        q = dp.reshape(dp.shape[0], 4, nv)
        if self.signal_type == "slopes":
            a_dp = np.concatenate(
                [q[:, 0] + q[:, 2] - q[:, 1] - q[:, 3], q[:, 0] + q[:, 1] - q[:, 2] - q[:, 3]],
                axis=-1,
            )
        else:
            a_dp = dp
        dnorm = dp.sum(axis=-1, keepdims=True) / nv
        return (a_dp - s_raw[None, :] * dnorm) / norm

    def detector_image(self, opd: np.ndarray) -> np.ndarray:
        """Noise-free detector frames for OPD maps.

        Parameters
        ----------
        opd : array_like, shape (..., n_pix, n_pix)
            Optical path difference [nm] on the pupil grid.

        Returns
        -------
        ndarray, shape (..., 2 n_sub, 2 n_sub)
            Fraction of the incoming flux on each detector pixel (multiply by the photons per
            frame for photo-electrons); quadrants ``[[I0, I1], [I2, I3]]``.
        """
        n_pix = self.pupil.n_pix
        opd = check_opd(opd, n_pix)
        lead = opd.shape[:-2]
        phase = opd_to_phase(opd.reshape(-1, n_pix, n_pix), self.wavelength)
        return self._frames(phase).reshape(*lead, *self.frame_shape)

    # ------------------------------------------------------------------ signals
    def _quadrants(self, frames: np.ndarray) -> np.ndarray:
        """``(..., 2 n_sub, 2 n_sub)`` -> ``(..., 4, n_valid_sub)`` valid pixels per image."""
        n_sub = self.n_subapertures
        f = frames.reshape(*frames.shape[:-2], 2, n_sub, 2, n_sub)
        f = np.moveaxis(f, -2, -3)  # (..., 2, 2, n_sub, n_sub)
        f = f.reshape(*frames.shape[:-2], 4, n_sub, n_sub)
        return f[..., self.valid_subapertures]

    def pixel_values(self, frames: np.ndarray) -> np.ndarray:
        """Detector pixels used by the signals, ``(..., 4 n_valid_sub)`` (images I0..I3)."""
        q = self._quadrants(np.asarray(frames, dtype=float))
        return q.reshape(*q.shape[:-2], -1)

    def _raw_signals(self, frames: np.ndarray) -> np.ndarray:
        q = self._quadrants(np.asarray(frames, dtype=float))
        norm = q.sum(axis=(-1, -2))[..., None] / self.n_valid_subapertures
        norm = np.where(norm > 0, norm, np.inf)
        if self.signal_type == "slopes":
            sx = (q[..., 0, :] + q[..., 2, :] - q[..., 1, :] - q[..., 3, :]) / norm
            sy = (q[..., 0, :] + q[..., 1, :] - q[..., 2, :] - q[..., 3, :]) / norm
            return np.concatenate([sx, sy], axis=-1)
        return q.reshape(*q.shape[:-2], -1) / norm

    @cached_property
    def reference_frame(self) -> np.ndarray:
        """Detector frame of a flat wavefront, ``(2 n_sub, 2 n_sub)`` (fraction of flux)."""
        ref = self.detector_image(np.zeros((self.pupil.n_pix, self.pupil.n_pix)))
        ref.setflags(write=False)
        return ref

    @cached_property
    def reference_signals(self) -> np.ndarray:
        """Raw signals of a flat wavefront, ``(n_signals,)`` (subtracted by :meth:`signals`)."""
        ref = self._raw_signals(self.reference_frame)
        ref.setflags(write=False)
        return ref

    def signals_from_frame(self, frames: np.ndarray) -> np.ndarray:
        """Signals ``(..., n_signals)`` of detector frames ``(..., 2 n_sub, 2 n_sub)`` (any
        flux units: the signals are normalised by the flux)."""
        return self._raw_signals(frames) - self.reference_signals

    def signals(self, opd: np.ndarray) -> np.ndarray:
        """Noise-free signals ``(..., n_signals)`` (dimensionless) of OPD maps ``(..., n_pix,
        n_pix)`` [nm]."""
        return self.signals_from_frame(self.detector_image(opd))

    def measure(
        self, opd: np.ndarray, photons: float, read_noise: float, rng: np.random.Generator
    ) -> np.ndarray:
        """Noisy signals: Poisson + read noise on the detector pixels, then the signals.

        Parameters
        ----------
        opd : array_like, shape (..., n_pix, n_pix)
            OPD [nm].
        photons : float
            Photo-electrons per frame entering the WFS (whole pupil).
        read_noise : float
            Read-out noise [e- RMS per pixel].
        rng : numpy.random.Generator

        Returns
        -------
        ndarray, shape (..., n_signals)
        """
        n_ph = check_positive("photons", photons)
        frames = add_detector_noise(self.detector_image(opd) * n_ph, read_noise, rng)
        return self.signals_from_frame(frames)

    @property
    def normalisation(self) -> tuple[int, float]:
        """``(pixels, flux fraction)`` of the flux normalisation sum (all valid pixels)."""
        return 4 * self.n_valid_subapertures, float(self.pixel_values(self.reference_frame).sum())

    def pixel_jacobian_product(self, frame: np.ndarray, matrix: np.ndarray) -> np.ndarray:
        """``matrix @ J`` with ``J`` the derivative of the signals w.r.t. the pixel values.

        Parameters
        ----------
        frame : array_like, shape (2 n_sub, 2 n_sub)
            Noise-free detector frame in photo-electrons (any flux unit; ``J`` scales as 1/flux).
        matrix : array_like, shape (n_out, n_signals)
            E.g. a reconstructor.

        Returns
        -------
        ndarray, shape (n_out, 4 n_valid_sub)
            ``matrix @ (A - s_raw w^T) / (w . p)`` with ``s_raw = A p / (w . p)``, ``A`` the
            linear pixel combination of the signals, ``w = 1 / n_valid_sub`` and ``p`` the
            pixel values (the flux normalisation is differentiated too).
        """
        p = self.pixel_values(frame)
        m = np.atleast_2d(np.asarray(matrix, dtype=float))
        nv = self.n_valid_subapertures
        if m.shape[-1] != self.n_signals:
            raise ValueError(
                f"matrix must have n_signals={self.n_signals} columns, got shape {m.shape}"
            )
        if self.signal_type == "slopes":
            mx, my = m[:, :nv], m[:, nv:]
            ma = np.concatenate([mx + my, -mx + my, mx - my, -mx - my], axis=1)
        else:
            ma = m
        norm = p.sum() / nv
        s_raw = self._raw_signals(frame)
        return (ma - np.outer(m @ s_raw, np.full(p.size, 1.0 / nv))) / norm
