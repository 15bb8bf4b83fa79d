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
inverse FFT, per point; identical to rounding, tested). It is
computed in separable form (the pyramid mask and the tilts factor into x and y parts): a
convolution along x shared by the points with the same x offset, then one along y per point,
about one 2-D FFT per modulation point instead of two, with precomputed phasors and masks,
batched ``scipy.fft`` calls (``workers`` threads), single precision by default (``complex64``;
the difference from ``complex128`` is < 1e-4 of the signal, tested).

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
import scipy.fft
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
from aocontrol.sim.wfs._common import bin_matrix, check_opd, opd_to_phase

__all__ = ["PyramidWFS", "default_modulation_points"]

logger = logging.getLogger(__name__)

#: Target number of complex samples per batched inverse FFT call (memory/speed trade-off:
#: ~32 MB of complex64 working set).
_BATCH_SAMPLES = 4_000_000


def _fft_inplace(a: np.ndarray, axis: int, workers: int, *, forward: bool) -> None:
    """Complex FFT of ``a`` along ``axis``, written into ``a`` (no allocation).

    ``scipy.fft`` writes into its complex input with ``overwrite_x=True`` (pocketfft's ``out``
    argument; it returns a view of ``a``); the check keeps the result right should a version
    return a new array instead.
    """
    fn = scipy.fft.fft if forward else scipy.fft.ifft
    res = fn(a, axis=axis, workers=workers, overwrite_x=True)
    if not np.may_share_memory(res, a):  # pragma: no cover - a scipy that copied instead
        a[...] = res


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
        Threads for ``scipy.fft``.

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
    def _plan(self) -> dict[str, np.ndarray]:
        """Precomputed phasors and masks of the separable propagation (module docstring)."""
        n, n_pix = self.n_fft, self.pupil.n_pix
        q = self.samples_per_lambda_over_d
        x = np.arange(n_pix)
        # beam tilt of each modulation point (a q focal samples) and half-sample centring
        ax = np.round(self.modulation_offsets[:, 0] * q, 12)
        ay = self.modulation_offsets[:, 1] * q
        ux, x_index = np.unique(ax, return_inverse=True)
        tx = np.exp(2j * np.pi * (ux[:, None] - 0.5) * x[None, :] / n)
        ty = np.exp(2j * np.pi * (ay[:, None] - 0.5) * x[None, :] / n)
        # one face of the pyramid per half line; the apex between samples -1 and 0; the ramp
        # places the pupil (transformed from the array corner) at r0 in the padded array
        u = np.fft.fftfreq(n) * n
        r0 = (n - n_pix) // 2
        m1 = np.exp(0.5j * np.pi * np.abs(u + 0.5) - 2j * np.pi * r0 * u / n)
        cols = np.flatnonzero(np.any(self._binning_full != 0, axis=0))
        amp = self.pupil.mask / math.sqrt(self.pupil.n_valid * self.n_points)
        plan = {
            "amp": amp.astype(self._real),
            "tx": tx.astype(self._complex),
            "ty": ty.astype(self._complex),
            "x_index": x_index,
            "mask": m1.astype(self._complex),
            "cols": cols,
            # sparse, not BLAS: small GEMMs stall in multi-threaded OpenBLAS on a busy machine
            "bin_rows": scipy.sparse.csr_matrix(self._binning_full),
            "bin_cols": scipy.sparse.csr_matrix(self._binning_full[:, cols]),
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
    def _work(self) -> dict[str, np.ndarray]:
        """Work buffers kept across frames (about 13 MB at SAXO+ sampling, allocated once).

        ``hx`` ``(n_x, n_pix, n_fft)``: step x, in place; ``hc`` ``(n_x, n_pix, n_cols)``: its
        detector columns; ``y`` ``(step, n_fft, n_cols)``: step y per chunk of points, in place;
        ``acc`` ``(n_fft, 2 n_cols)``: the intensity accumulator. They make an instance not
        thread-safe (use one instance per thread) and are not pickled.
        """
        plan = self._plan
        n, n_pix = self.n_fft, self.pupil.n_pix
        nc, n_x = plan["cols"].size, plan["tx"].shape[0]
        step = max(1, min(self.n_points, _BATCH_SAMPLES // (n * nc)))
        return {
            "hx": np.zeros((n_x, n_pix, n), dtype=self._complex),
            "hc": np.zeros((n_x, n_pix, nc), dtype=self._complex),
            "y": np.zeros((step, n, nc), dtype=self._complex),
            "acc": np.zeros((n, 2 * nc), dtype=self._real),
        }

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_work", None)  # buffers, rebuilt on first use
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    def _fields(self, field: np.ndarray):
        """Pupil-plane fields after the pyramid, per chunk of modulation points.

        Yields arrays ``(k, n_fft, n_cols)`` (complex, detector columns only) for a pupil
        field ``(n_pix, n_pix)`` (amplitude included). The pyramid mask is separable,
        ``M(u, v) = m(u) m(v)``, and so is each modulation tilt: the propagation pupil ->
        focal plane -> mask -> pupil is a convolution along x followed by one along y. Step x
        (FFT, mask, inverse FFT along rows, only the ``n_pix`` non-zero rows) depends on the
        x-tilt only and is shared by the modulation points with the same x offset; step y is
        done per point, for the detector columns only. The result is the discrete beam-tilt
        propagation (tilt, 2-D FFT, mask, inverse 2-D FFT per point) to rounding, at the cost
        of about one 2-D FFT per point instead of two.

        The FFTs run in place in the work buffers (:attr:`_work`): each yielded array is a
        view of the same buffer, valid until the generator advances (copy it to keep it).
        """
        plan, work = self._plan, self._work
        w, n_pix = self.workers, self.pupil.n_pix
        mask, cols = plan["mask"], plan["cols"]
        n_pts = self.n_points
        x_index, ty = plan["x_index"], plan["ty"]
        hx, hc, buf = work["hx"], work["hc"], work["y"]
        step = buf.shape[0]
        # step x, per distinct x tilt: (n_x, n_pix, n) zero-padded along x, in place
        np.multiply(field[None], plan["tx"][:, None, :], out=hx[..., :n_pix])
        hx[..., n_pix:] = 0
        _fft_inplace(hx, -1, w, forward=True)
        hx *= mask
        _fft_inplace(hx, -1, w, forward=False)
        np.take(hx, cols, axis=-1, out=hc, mode="clip")  # detector columns; "clip": unbuffered
        for k0 in range(0, n_pts, step):
            k1 = min(k0 + step, n_pts)
            b = buf[: k1 - k0]
            for j, k in enumerate(range(k0, k1)):  # per point (not a fancy-index temporary)
                np.multiply(hc[x_index[k]], ty[k, :, None], out=b[j, :n_pix])
            b[:, n_pix:] = 0  # zero padding along y (overwritten by the previous chunk)
            _fft_inplace(b, -2, w, forward=True)
            b *= mask[:, None]
            _fft_inplace(b, -2, w, forward=False)
            yield b

    def _bin(self, acc: np.ndarray) -> np.ndarray:
        """``(n_fft, 2 n_cols)`` interleaved accumulator -> detector frame ``(2n_sub, 2n_sub)``."""
        plan = self._plan
        acc = acc[:, 0::2] + acc[:, 1::2]
        rows = plan["bin_rows"] @ acc.astype(np.float64)  # (2 n_sub, n_cols)
        return (plan["bin_cols"] @ rows.T).T

    def _field(self, phase: np.ndarray) -> np.ndarray:
        return self._plan["amp"] * np.exp(1j * phase.astype(self._real))

    def _frames(self, phase: np.ndarray) -> np.ndarray:
        """Detector frames ``(m, 2 n_sub, 2 n_sub)`` of phase maps ``(m, n_pix, n_pix)`` [rad]."""
        out = np.empty((phase.shape[0], *self.frame_shape))
        acc = self._work["acc"]
        for i in range(phase.shape[0]):
            acc.fill(0.0)
            for g in self._fields(self._field(phase[i])):
                gv = g.view(self._real)  # (k, n, 2 nc): interleaved real and imaginary parts
                acc += np.einsum("kij,kij->ij", gv, gv)
            out[i] = self._bin(acc)
        return out

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
        base = [g.copy() for g in self._fields(field)]  # the generator reuses its buffer
        dphase = opd_to_phase(delta, self.wavelength)
        nc = self._plan["cols"].size
        out = np.empty((delta.shape[0], *self.frame_shape))
        for i in range(delta.shape[0]):
            acc = np.zeros((self.n_fft, 2 * nc), dtype=self._real)
            dfield = 1j * dphase[i].astype(self._real) * field
            for g0, g1 in zip(base, self._fields(dfield), strict=True):
                acc += 2 * np.einsum("kij,kij->ij", g0.view(self._real), g1.view(self._real))
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
