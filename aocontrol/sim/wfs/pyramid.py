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

Computation: matrix products of the line operator, exact rewrites of this model (parity of
the pupil samples, conjugate pupil images, mirror modulation points), in single precision by
default, with compiled element-wise passes (:mod:`._pyramid_propagation`, which documents
them; the sensor keeps their plan and work buffers per instance).

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
signals of a flat wavefront, dimensionless. Both are ``s = A p / n(p)``, ``A`` a fixed
combination of the valid pixels ``p``: the pixel Jacobian
(:meth:`~PyramidWFS.pixel_jacobian_product`) and the signal derivative differentiate ``n`` too.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from aocontrol._validation import check_finite_array, check_int, check_nonnegative
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.wfs._common import bin_matrix, blas_threads, opd_to_phase
from aocontrol.sim.wfs._pyramid_propagation import (
    bin_frame,
    build_plan,
    frame_derivatives,
    intensities,
    pair_fields,
    pupil_field,
    work_buffers,
)
from aocontrol.sim.wfs._sensor import WavefrontSensor

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
class PyramidWFS(WavefrontSensor):
    """Modulated pyramid WFS, Fourier-optics model (see the module docstring).

    The shared interface (signals, noisy measurements, flat-wavefront reference, valid
    subapertures, pixel Jacobian) is :class:`~aocontrol.sim.wfs.WavefrontSensor`'s; this class
    adds the modulation geometry, the propagation's per-instance state and the derivatives.

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
        Propagation precision (complex64 / float32 or complex128 / float64).
    workers : int, default 1
        BLAS threads of the propagation's matrix products, set for the duration of each call
        (``threadpoolctl``; the setting is process-wide while the call runs). 1 by default:
        on a machine shared with other jobs a multi-threaded BLAS stalls on products of this
        size (``docs/benchmarks.md``).

    Notes
    -----
    An instance keeps work buffers across frames (:func:`._pyramid_propagation.work_buffers`):
    use one instance per thread. They are not pickled (rebuilt on first use).

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

    _unpickled = ("_work",)

    def _check_parameters(self) -> None:
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
        if self.precision not in ("single", "double"):
            raise ValueError(f"precision must be 'single' or 'double', got {self.precision!r}")
        check_int("workers", self.workers, minimum=1)

    # ------------------------------------------------------------------ modulation geometry
    @property
    def n_points(self) -> int:
        """Modulation points actually used."""
        if self.n_modulation_points is not None:
            return int(self.n_modulation_points)
        return default_modulation_points(self.modulation)

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

    # ------------------------------------------------------------------ detector geometry
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

    @property
    def frame_shape(self) -> tuple[int, int]:
        """Detector frame shape ``(2 n_sub, 2 n_sub)``: quadrants ``[[I0, I1], [I2, I3]]``."""
        return (2 * self.n_subapertures, 2 * self.n_subapertures)

    @property
    def _signals_per_subaperture(self) -> int:
        return 2 if self.signal_type == "slopes" else 4

    # ------------------------------------------------------------------ propagation
    @property
    def _complex(self) -> type:
        """Complex dtype of the propagation (:attr:`precision`)."""
        return np.complex64 if self.precision == "single" else np.complex128

    @property
    def _real(self) -> type:
        """Real dtype of the propagation (:attr:`precision`)."""
        return np.float32 if self.precision == "single" else np.float64

    @cached_property
    def _plan(self) -> dict:
        """The propagation's operators (:func:`._pyramid_propagation.build_plan`)."""
        k, n_ns = self._pairs
        q = self.samples_per_lambda_over_d
        return build_plan(
            self.pupil.mask,
            self.pupil.n_valid,
            self.n_points,
            self.n_fft,
            x_tilts=self.modulation_offsets[k, 0] * q,
            y_tilts=self.modulation_offsets[k[:n_ns], 1] * q,
            binning=self._binning_full,
            complex_dtype=self._complex,
            real_dtype=self._real,
        )

    @cached_property
    def _work(self) -> dict[str, list[np.ndarray]]:
        """The propagation's work buffers (:func:`._pyramid_propagation.work_buffers`), kept
        across frames; not pickled."""
        return work_buffers(self._plan, self._chunks)

    def _field(self, phase: np.ndarray) -> np.ndarray:
        """Pupil field ``(n_pix, n_pix)`` of a phase map [rad] (amplitude and centring)."""
        return pupil_field(self._plan, phase)

    def _fields(self, field: np.ndarray, fused: tuple | None = None):
        """Pair products of a pupil field (:func:`._pyramid_propagation.pair_fields`)."""
        return pair_fields(self._plan, self._work, self._chunks, field, fused)

    def _blas_threads(self):
        """Context: ``workers`` BLAS threads (the propagation's products)."""
        return blas_threads(self.workers)

    def _frames(self, phase: np.ndarray) -> np.ndarray:
        """Detector frames ``(m, 2 n_sub, 2 n_sub)`` of phase maps ``(m, n_pix, n_pix)`` [rad]."""
        out = np.empty((phase.shape[0], *self.frame_shape))
        plan, work, chunks = self._plan, self._work, self._chunks
        with self._blas_threads():
            for i in range(phase.shape[0]):
                out[i] = bin_frame(plan, intensities(plan, work, chunks, phase[i]))
        return out

    def _detector_frames(self, opd: np.ndarray) -> np.ndarray:
        n_pix = self.pupil.n_pix
        opd = self._check_opd(opd)
        lead = opd.shape[:-2]
        phase = opd_to_phase(opd.reshape(-1, n_pix, n_pix), self.wavelength)
        return self._frames(phase).reshape(*lead, *self.frame_shape)

    # ------------------------------------------------------------------ derivatives
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
        with self._blas_threads():
            return frame_derivatives(self._plan, self._work, self._chunks, field, dphase)

    def signal_derivative(self, opd: np.ndarray, delta_opd: np.ndarray) -> np.ndarray:
        """Derivative of the signals at ``opd`` in the directions ``delta_opd``.

        Parameters
        ----------
        opd, delta_opd : arrays
            As for :meth:`frame_derivative`.

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
        a_dp = self._combine(dp.reshape(dp.shape[0], 4, nv))
        dnorm = dp.sum(axis=-1, keepdims=True) / nv
        return (a_dp - s_raw[None, :] * dnorm) / norm

    # ------------------------------------------------------------------ signals
    def _quadrants(self, frames: np.ndarray) -> np.ndarray:
        """``(..., 2 n_sub, 2 n_sub)`` -> ``(..., 4, n_valid_sub)`` valid pixels per image."""
        n_sub = self.n_subapertures
        f = frames.reshape(*frames.shape[:-2], 2, n_sub, 2, n_sub)
        f = np.moveaxis(f, -2, -3)  # (..., 2, 2, n_sub, n_sub)
        f = f.reshape(*frames.shape[:-2], 4, n_sub, n_sub)
        return f[..., self.valid_subapertures]

    def _combine(self, q: np.ndarray) -> np.ndarray:
        """The signals' linear combination ``A`` of the valid pixels ``(..., 4, n_valid_sub)``
        of the four images: ``[Sx, Sy]`` (slopes) or the pixels (full frame), before the flux
        normalisation, ``(..., n_signals)``."""
        if self.signal_type == "slopes":
            sx = q[..., 0, :] + q[..., 2, :] - q[..., 1, :] - q[..., 3, :]
            sy = q[..., 0, :] + q[..., 1, :] - q[..., 2, :] - q[..., 3, :]
            return np.concatenate([sx, sy], axis=-1)
        return q.reshape(*q.shape[:-2], -1)

    def pixel_values(self, frames: np.ndarray) -> np.ndarray:
        """Detector pixels used by the signals, ``(..., 4 n_valid_sub)`` (images I0..I3)."""
        q = self._quadrants(np.asarray(frames, dtype=float))
        return q.reshape(*q.shape[:-2], -1)

    def _raw_signals(self, frames: np.ndarray) -> np.ndarray:
        q = self._quadrants(np.asarray(frames, dtype=float))
        norm = q.sum(axis=(-1, -2))[..., None] / self.n_valid_subapertures
        norm = np.where(norm > 0, norm, np.inf)
        return self._combine(q) / norm

    @property
    def normalisation(self) -> tuple[int, float]:
        """``(pixels, flux fraction)`` of the flux normalisation sum (all valid pixels)."""
        return 4 * self.n_valid_subapertures, float(self.pixel_values(self.reference_frame).sum())

    def _jacobian_product(self, frame: np.ndarray, matrix: np.ndarray) -> np.ndarray:
        """``matrix @ (A - s_raw w^T) / (w . p)`` with ``s_raw = A p / (w . p)``, ``A`` the
        linear pixel combination of the signals (:meth:`_combine`), ``w = 1 / n_valid_sub``
        and ``p`` the pixel values (the flux normalisation is differentiated too)."""
        p = self.pixel_values(frame)
        m = matrix
        nv = self.n_valid_subapertures
        if self.signal_type == "slopes":
            mx, my = m[:, :nv], m[:, nv:]
            ma = np.concatenate([mx + my, -mx + my, mx - my, -mx - my], axis=1)
        else:
            ma = m
        norm = p.sum() / nv
        s_raw = self._raw_signals(frame)
        return (ma - np.outer(m @ s_raw, np.full(p.size, 1.0 / nv))) / norm
