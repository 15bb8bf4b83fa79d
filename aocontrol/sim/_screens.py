"""Von Kármán phase-screen generators: FFT with subharmonics, and AR extrusion.

Private implementation of :mod:`aocontrol.sim.atmosphere`. Screens made here are phases in
radians at 500 nm for a Fried parameter of **1 m**; a layer with Fried parameter ``r0_l``
multiplies them by ``r0_l ** (-5/6)`` (the phase scales as ``r0^(-5/6)``).

Two generators:

- :func:`fft_screens`: the initial square screen. FFT of white noise filtered by the von
  Kármán PSD on an ``m x m`` periodic grid, plus three levels of Lane et al. (1992)
  subharmonics (3x3 frequency grids at ``df/3, df/9, df/27``) for the scales larger than the
  FFT grid, as in Schmidt (2010, "Numerical simulation of optical wave propagation",
  listing 9.3). Johansson & Gavel (1994) refine the subharmonic weights; with the FFT grid
  twice the screen and L0 = 25 m the plain version already gives the tip/tilt variance
  within about 2 % (tested). The real and imaginary parts of one complex screen are two
  independent screens (the PSD is even).
- :class:`Extruder`: the autoregressive extrusion of Assémat, Wilson & Gendron (2006, Opt.
  Express 14, 988): a new column ``x`` beyond the edge of the screen is drawn from its
  Gaussian distribution conditioned on a stencil ``z`` of existing pixels,
  ``x = A z + B w``, ``A = C_xz C_zz^-1``, ``B B^T = C_xx - A C_zx``, ``w ~ N(0, I)``,
  with the exact von Kármán covariances
  (:func:`aocontrol.sim.turbulence.phase_covariance`). The stencil is the last two columns
  in full, then columns at distances 3, 5, 9, 17, ... pixels with rows spaced in proportion
  to the distance (Assémat's dyadic stencil), and finally 3 pixels of the oldest column
  kept in the screen (about ``3 size`` pixels in all). The screen is square, so the same
  ``(A, B)`` extrudes in the four directions (the covariance is isotropic; flips and
  transposes are isometries of the grid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from aocontrol.sim.turbulence import phase_covariance, von_karman_psd

__all__ = ["fft_screens", "Extruder", "extrusion_stencil"]

#: Subharmonic levels added to an FFT screen (3 is the usual choice: scales up to 27 m).
N_SUBHARMONIC_LEVELS = 3


def fft_screens(
    n_screens: int,
    size: int,
    dx: float,
    L0: float,
    rng: np.random.Generator,
    *,
    oversampling: int = 2,
    subharmonics: int = N_SUBHARMONIC_LEVELS,
) -> np.ndarray:
    """Independent von Kármán screens [rad at 500 nm, r0 = 1 m], shape ``(n, size, size)``.

    Parameters
    ----------
    n_screens : int
        Number of screens.
    size : int
        Side of each (square) screen [pixels].
    dx : float
        Pixel size [m].
    L0 : float
        Outer scale [m].
    rng : numpy.random.Generator
        Source of randomness.
    oversampling : int
        The FFT grid has ``oversampling * size`` pixels a side; the screen is its corner
        (less periodicity at the largest scales).
    subharmonics : int
        Levels of Lane subharmonics (0 for none).

    Returns
    -------
    ndarray, shape (n_screens, size, size)
        Zero-mean screens (phase in rad at 500 nm for r0 = 1 m).
    """
    m = int(oversampling * size)
    df = 1.0 / (m * dx)
    fx = np.fft.fftfreq(m, d=dx)
    kappa = np.hypot(fx[:, None], fx[None, :])
    amp = np.sqrt(von_karman_psd(kappa, 1.0, L0)) * df
    amp[0, 0] = 0.0  # no piston
    # Subharmonic frequencies: 3x3 grids at df/3^p without the centre.
    coords = np.arange(size) * dx
    sub_f, sub_amp = [], []
    for p in range(1, subharmonics + 1):
        dfp = df / 3.0**p
        for a in (-1, 0, 1):
            for b in (-1, 0, 1):
                if a == 0 and b == 0:
                    continue
                sub_f.append((a * dfp, b * dfp))
                sub_amp.append(np.sqrt(von_karman_psd(np.hypot(a, b) * dfp, 1.0, L0)) * dfp)
    sub_f_arr = np.asarray(sub_f).reshape(-1, 2)
    sub_amp_arr = np.asarray(sub_amp, dtype=float).reshape(-1)
    # exp(2 pi i (fy y + fx x)) for each subharmonic, separable: (n_sub, size) each.
    ey = np.exp(2j * np.pi * sub_f_arr[:, 0:1] * coords[None, :])
    ex = np.exp(2j * np.pi * sub_f_arr[:, 1:2] * coords[None, :])

    out = np.empty((n_screens, size, size))
    for i in range(0, n_screens, 2):
        noise = rng.standard_normal((2, m, m))
        c = (noise[0] + 1j * noise[1]) * amp
        screen = np.fft.ifft2(c)[:size, :size] * (m * m)
        if sub_f_arr.size:
            sn = rng.standard_normal((2, sub_amp_arr.size))
            cs = (sn[0] + 1j * sn[1]) * sub_amp_arr
            screen = screen + np.einsum("k,ki,kj->ij", cs, ey, ex)
        screen -= screen.mean()
        out[i] = screen.real
        if i + 1 < n_screens:
            out[i + 1] = screen.imag
    return out


def extrusion_stencil(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Stencil of an extrusion to the right of a ``size x size`` screen.

    Returns
    -------
    rows, cols : ndarray of int, shape (n_stencil,)
        Pixels of the screen (row, column) on which a new column at index ``size`` is
        conditioned: the last column in full, columns at distances ``2^j + 1`` (2, 3, 5,
        9, ...) with about ``size / 2^j + 1`` rows each (so distance 2 in full), and the
        oldest column (distance ``size``) at 3 rows.
    """
    pts: set[tuple[int, int]] = set()
    for r in range(size):
        pts.add((r, size - 1))
    j = 0
    while True:
        d = 2**j + 1
        if d > size:
            break
        n_rows = max(2, size // 2**j + 1)
        for r in np.unique(np.round(np.linspace(0, size - 1, n_rows)).astype(int)):
            pts.add((int(r), size - d))
        j += 1
    for r in (0, size // 2, size - 1):
        pts.add((r, 0))
    arr = np.array(sorted(pts, key=lambda p: (-p[1], p[0])), dtype=np.intp)
    return arr[:, 0].copy(), arr[:, 1].copy()


@dataclass(frozen=True)
class Extruder:
    """Conditional-Gaussian extrusion of a square screen by one column at a time.

    Build with :meth:`build`. ``A`` has shape ``(size, n_stencil)`` and ``B`` ``(size, size)``
    (for r0 = 1 m, radians at 500 nm; the noise term of a layer is scaled by its amplitude,
    ``A`` is scale free).
    """

    size: int
    rows: np.ndarray
    cols: np.ndarray
    A: np.ndarray
    B: np.ndarray

    @classmethod
    def build(cls, size: int, dx: float, L0: float) -> Extruder:
        """Operators for a ``size x size`` screen of pixel ``dx`` [m], outer scale ``L0`` [m]."""
        rows, cols = extrusion_stencil(size)
        z = np.stack([rows, cols], axis=1)
        x = np.stack([np.arange(size), np.full(size, size)], axis=1)

        def cov(p: np.ndarray, q: np.ndarray) -> np.ndarray:
            # Squared grid distances are integers: evaluate the covariance once per value.
            d2 = (p[:, None, 0] - q[None, :, 0]) ** 2 + (p[:, None, 1] - q[None, :, 1]) ** 2
            values, inverse = np.unique(d2, return_inverse=True)
            b = phase_covariance(np.sqrt(values) * dx, 1.0, L0)
            return b[inverse].reshape(d2.shape)

        czz = cov(z, z)
        cxz = cov(x, z)
        cxx = cov(x, x)
        # A = C_xz C_zz^-1 by a Cholesky solve (C_zz is symmetric positive definite).
        factor = scipy.linalg.cho_factor(czz, lower=True)
        a = scipy.linalg.cho_solve(factor, cxz.T).T
        cond = cxx - a @ cxz.T
        cond = 0.5 * (cond + cond.T)
        w, v = np.linalg.eigh(cond)
        b = v * np.sqrt(np.clip(w, 0.0, None))
        # Column-major A: its matrix-vector products (one per new column) are ~1.4x faster.
        a = np.asfortranarray(a)
        for arr in (rows, cols, a, b):
            arr.setflags(write=False)
        return cls(size=size, rows=rows, cols=cols, A=a, B=b)

    def extrude(self, view: np.ndarray, white: np.ndarray, amplitude: float) -> None:
        """Extrude ``view`` (a writable ``(size, size)`` view) to the right, in place.

        Parameters
        ----------
        view : ndarray, shape (size, size)
            Screen, possibly a flipped/transposed view of the stored screen; after the call
            its columns are shifted left by ``k`` and the ``k`` new columns fill the right.
        white : ndarray, shape (k, size)
            Standard normal draws, one row per new column.
        amplitude : float
            Scale of the screen relative to r0 = 1 m, radians at 500 nm (e.g. nm per unit).

        Notes
        -----
        The conditional means ``A z`` are BLAS matrix-vector products, one per new column
        (each column conditions the next), cheaper than ``numpy.einsum``; small and
        sequential, they want one BLAS thread (a multithreaded BLAS waking its threads for
        each is slower on a loaded machine): the atmosphere extrudes under
        ``aocontrol._blas.blas_threads(1)``. The noise terms ``B w`` are matrix-vector
        products too, one per column (the same sums whatever ``k``). Figures in
        ``docs/benchmarks.md``.
        """
        k = white.shape[0]
        n = self.size
        buf = np.empty((n, n + k))
        buf[:, :n] = view
        a, b, rows, cols = self.A, self.B, self.rows, self.cols
        noise = np.empty(n)
        # The stencil of column j as flat indices into buf shifted by j (no 2-D fancy index).
        flat_buf = buf.reshape(-1)
        stencil = rows * (n + k) + cols
        for j in range(k):
            new = a @ flat_buf[j:].take(stencil)
            # The noise term of this column alone (a matrix-vector product: the same sums
            # whatever k; numpy.einsum over all k columns at once was ~10x slower).
            np.matmul(b, white[j], out=noise)
            noise *= amplitude
            new += noise
            buf[:, n + j] = new
        view[...] = buf[:, k:]
