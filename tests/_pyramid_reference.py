"""The pyramid's former propagation (FFTs), frozen as a reference for the matrix-product one.

``FFTPyramid`` is :class:`aocontrol.sim.wfs.PyramidWFS` with the detector frames computed by
the separable FFT propagation the library used before the line-operator products (issue 15,
pyramid speed): the same floating-point operations in the same order, so the golden
diffractive loop (recorded with it) stays bit for bit, and the new propagation is compared
with it to a stated tolerance (``tests/test_pyramid_products.py``).
"""

from __future__ import annotations

import math
from functools import cached_property

import numpy as np
import scipy.fft
import scipy.sparse

from aocontrol.sim.wfs import PyramidWFS

_BATCH_SAMPLES = 4_000_000


def _fft_inplace(a: np.ndarray, axis: int, *, forward: bool) -> None:
    fn = scipy.fft.fft if forward else scipy.fft.ifft
    res = fn(a, axis=axis, workers=1, overwrite_x=True)
    if not np.may_share_memory(res, a):  # pragma: no cover
        a[...] = res


class FFTPyramid(PyramidWFS):
    """:class:`PyramidWFS` with the former FFT propagation (detector frames only)."""

    @cached_property
    def _fft_plan(self) -> dict:
        n, n_pix = self.n_fft, self.pupil.n_pix
        q = self.samples_per_lambda_over_d
        x = np.arange(n_pix)
        ax = np.round(self.modulation_offsets[:, 0] * q, 12)
        ay = self.modulation_offsets[:, 1] * q
        ux, x_index = np.unique(ax, return_inverse=True)
        tx = np.exp(2j * np.pi * (ux[:, None] - 0.5) * x[None, :] / n)
        ty = np.exp(2j * np.pi * (ay[:, None] - 0.5) * x[None, :] / n)
        u = np.fft.fftfreq(n) * n
        r0 = (n - n_pix) // 2
        m1 = np.exp(0.5j * np.pi * np.abs(u + 0.5) - 2j * np.pi * r0 * u / n)
        cols = np.flatnonzero(np.any(self._binning_full != 0, axis=0))
        amp = self.pupil.mask / math.sqrt(self.pupil.n_valid * self.n_points)
        return {
            "amp": amp.astype(self._real),
            "tx": tx.astype(self._complex),
            "ty": ty.astype(self._complex),
            "x_index": x_index,
            "mask": m1.astype(self._complex),
            "cols": cols,
            "bin_rows": scipy.sparse.csr_matrix(self._binning_full),
            "bin_cols": scipy.sparse.csr_matrix(self._binning_full[:, cols]),
        }

    def _fft_fields(self, field: np.ndarray):
        plan = self._fft_plan
        n, n_pix = self.n_fft, self.pupil.n_pix
        mask, cols = plan["mask"], plan["cols"]
        n_pts, nc, n_x = self.n_points, plan["cols"].size, plan["tx"].shape[0]
        x_index, ty = plan["x_index"], plan["ty"]
        step = max(1, min(n_pts, _BATCH_SAMPLES // (n * nc)))
        hx = np.zeros((n_x, n_pix, n), dtype=self._complex)
        hc = np.zeros((n_x, n_pix, nc), dtype=self._complex)
        buf = np.zeros((step, n, nc), dtype=self._complex)
        np.multiply(field[None], plan["tx"][:, None, :], out=hx[..., :n_pix])
        _fft_inplace(hx, -1, forward=True)
        hx *= mask
        _fft_inplace(hx, -1, forward=False)
        np.take(hx, cols, axis=-1, out=hc, mode="clip")
        for k0 in range(0, n_pts, step):
            k1 = min(k0 + step, n_pts)
            b = buf[: k1 - k0]
            for j, k in enumerate(range(k0, k1)):
                np.multiply(hc[x_index[k]], ty[k, :, None], out=b[j, :n_pix])
            b[:, n_pix:] = 0
            _fft_inplace(b, -2, forward=True)
            b *= mask[:, None]
            _fft_inplace(b, -2, forward=False)
            yield b

    def _frames(self, phase: np.ndarray) -> np.ndarray:
        plan = self._fft_plan
        out = np.empty((phase.shape[0], *self.frame_shape))
        acc = np.zeros((self.n_fft, 2 * plan["cols"].size), dtype=self._real)
        for i in range(phase.shape[0]):
            acc.fill(0.0)
            field = plan["amp"] * np.exp(1j * phase[i].astype(self._real))
            for g in self._fft_fields(field):
                gv = g.view(self._real)
                acc += np.einsum("kij,kij->ij", gv, gv)
            a = acc[:, 0::2] + acc[:, 1::2]
            rows = plan["bin_rows"] @ a.astype(np.float64)
            out[i] = (plan["bin_cols"] @ rows.T).T
        return out
