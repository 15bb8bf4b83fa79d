"""Shack-Hartmann wavefront sensor: diffractive (per-subaperture FFT, centre of gravity) or
geometric (average gradient per subaperture).

Signals are the average OPD gradient over each valid subaperture times the subaperture size,
i.e. the OPD difference across a subaperture [nm], ``[sx, sy]`` of shape
``(2 n_valid_sub,)``: ``sx`` along ``+x`` (columns), ``sy`` along ``+y`` (rows). A pure tilt
``OPD = a x`` gives ``sx = a d`` in both models (``d = D / n_sub``).

``model="geometric"`` (the fast model): the mean of the finite differences of the OPD between
neighbouring pupil samples that are both inside the pupil and inside the subaperture, one
sparse matrix product. It is exact for tilts and ignores diffraction, spot truncation and
aliasing through the spot shape.

``model="diffractive"``: each subaperture field (``p = n_pix / n_sub`` samples across) is
zero-padded to ``oversampling * p`` and Fourier transformed (one batched FFT for all
subapertures); the spot, sampled at ``lambda / (oversampling d)`` per pixel with a
field of view of ``p`` lambda/d, is centred on the corner of 4 pixels for a flat wavefront;
the slope is its centre of gravity minus the flat-wavefront reference, converted to nm. Needs
``p >= 4`` for a meaningful spot. The detector pixels are the spot pixels (no extra rebinning):
a frame is the spots of the valid subapertures, ``(n_valid_sub, m, m)``; the pixel Jacobian
(:meth:`~ShackHartmannWFS.pixel_jacobian_product`) is that of each spot's centroid, its flux
normalisation included.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import scipy.fft
import scipy.sparse

from aocontrol._validation import check_int
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.wfs._common import opd_to_phase
from aocontrol.sim.wfs._sensor import WavefrontSensor
from aocontrol.sim.wfs.calibration import WFSCalibration, calibrate

__all__ = ["ShackHartmannWFS", "shack_hartmann_calibration"]

# Signals per block when building the per-slope noise coefficients.
_SH_BLOCK = 128

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ShackHartmannWFS(WavefrontSensor):
    """Shack-Hartmann WFS (see the module docstring for the models and sign conventions).

    The shared interface (signals, noisy measurements, flat-wavefront reference, valid
    subapertures) is :class:`~aocontrol.sim.wfs.WavefrontSensor`'s; the detector frames are the
    spots of the valid subapertures, ``frame_shape = (n_valid_sub, m, m)``.

    Parameters
    ----------
    pupil : Pupil
        Pupil grid, OPD maps ``(..., n_pix, n_pix)`` [nm]; ``n_pix`` must be a multiple of
        ``n_subapertures`` (>= 2 samples per subaperture, >= 4 for the diffractive model).
    wavelength : float
        Sensing wavelength [m] (0.69e-6 for SAXO).
    n_subapertures : int, default 40
        Lenslets across the diameter.
    model : {"geometric", "diffractive"}
        The geometric model has no detector: :meth:`detector_image`, :attr:`reference_frame`
        and :meth:`measure` need the diffractive one.
    oversampling : int, default 2
        Spot sampling, pixels per lambda/d (diffractive model).
    valid_threshold : float, default 0.5
        Minimum geometric illumination of a valid subaperture, in (0, 1].
    """

    pupil: Pupil
    wavelength: float
    n_subapertures: int = 40
    model: str = "geometric"
    oversampling: int = 2
    valid_threshold: float = 0.5

    def _check_parameters(self) -> None:
        n_sub = check_int("n_subapertures", self.n_subapertures, minimum=1)
        if self.model not in ("geometric", "diffractive"):
            raise ValueError(f"model must be 'geometric' or 'diffractive', got {self.model!r}")
        min_p = 4 if self.model == "diffractive" else 2
        n_pix = self.pupil.n_pix
        if n_pix % n_sub or n_pix // n_sub < min_p:
            raise ValueError(
                f"pupil.n_pix must be a multiple of n_subapertures={n_sub} with >= {min_p} "
                f"samples per subaperture for the {self.model} model, got pupil.n_pix={n_pix}: "
                "sampling too coarse or not commensurate"
            )
        check_int("oversampling", self.oversampling, minimum=1)

    def _require_detector(self, what: str) -> None:
        if self.model != "diffractive":
            raise ValueError(
                f"{what} needs model='diffractive' (the geometric model has no detector), "
                f"got model={self.model!r}"
            )

    @property
    def samples_per_subaperture(self) -> int:
        """Pupil samples across a subaperture."""
        return self.pupil.n_pix // self.n_subapertures

    @property
    def subaperture_size(self) -> float:
        """Subaperture size ``d`` [m]."""
        return self.pupil.diameter / self.n_subapertures

    @property
    def _signals_per_subaperture(self) -> int:
        return 2

    # ------------------------------------------------------------------ geometric model
    @cached_property
    def _gradient_matrix(self) -> scipy.sparse.csr_matrix:
        """Sparse ``(n_signals, n_pix^2)``: mean finite difference per subaperture times d."""
        n_pix, p = self.pupil.n_pix, self.samples_per_subaperture
        mask = self.pupil.mask
        sub = np.arange(n_pix) // p
        valid = self.valid_subapertures
        vindex = -np.ones(valid.shape, dtype=int)
        vindex[valid] = np.arange(self.n_valid_subapertures)
        rows, cols, vals = [], [], []
        flat = np.arange(n_pix * n_pix).reshape(n_pix, n_pix)
        for axis, offset in ((1, 0), (0, self.n_valid_subapertures)):
            a = flat[:, :-1] if axis == 1 else flat[:-1, :]
            b = flat[:, 1:] if axis == 1 else flat[1:, :]
            ok = mask.ravel()[a] & mask.ravel()[b]
            ra, ca = np.divmod(a, n_pix)
            rb, cb = np.divmod(b, n_pix)
            same = (sub[ra] == sub[rb]) & (sub[ca] == sub[cb])
            ok &= same & valid[sub[ra], sub[ca]]
            idx = vindex[sub[ra[ok]], sub[ca[ok]]]
            counts = np.bincount(idx, minlength=self.n_valid_subapertures).astype(float)
            w = self.subaperture_size / self.pupil.pixel_scale / counts[idx]
            rows += [idx + offset, idx + offset]
            cols += [b[ok], a[ok]]
            vals += [w, -w]
        return scipy.sparse.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(self.n_signals, n_pix * n_pix),
        )

    def signals(self, opd: np.ndarray) -> np.ndarray:
        """Noise-free signals ``(..., n_signals)`` [nm of OPD across a subaperture, ``[sx,
        sy]``] of OPD maps ``(..., n_pix, n_pix)`` [nm]: the gradient matrix (geometric
        model) or the spots' centroids (diffractive model, :meth:`WavefrontSensor.signals`)."""
        if self.model == "geometric":
            opd = self._check_opd(opd)
            lead = opd.shape[:-2]
            flat = opd.reshape(-1, self.pupil.n_pix**2)
            out = (self._gradient_matrix @ flat.T).T
            return out.reshape(*lead, self.n_signals)
        return super().signals(opd)

    # ------------------------------------------------------------------ diffractive model
    @property
    def spot_size(self) -> int:
        """Pixels across a subaperture image (diffractive model)."""
        return self.oversampling * self.samples_per_subaperture

    @property
    def frame_shape(self) -> tuple[int, int, int]:
        """Detector frame shape ``(n_valid_sub, m, m)``: the spots, ``m`` = :attr:`spot_size`."""
        return (self.n_valid_subapertures, self.spot_size, self.spot_size)

    @cached_property
    def _centring(self) -> np.ndarray:
        m = self.spot_size
        x = np.arange(self.samples_per_subaperture)
        return np.exp(-1j * np.pi * (x[:, None] + x[None, :]) / m)

    def spots(self, opd: np.ndarray) -> np.ndarray:
        """Spot images ``(..., n_valid_sub, m, m)`` (fraction of the pupil flux; ``m`` =
        :attr:`spot_size`) of OPD maps ``(..., n_pix, n_pix)`` [nm], for either model."""
        opd = self._check_opd(opd)
        n_sub, p, m = self.n_subapertures, self.samples_per_subaperture, self.spot_size
        phase = opd_to_phase(opd, self.wavelength)
        field = self.pupil.mask * np.exp(1j * phase) / np.sqrt(self.pupil.n_valid)
        lead = field.shape[:-2]
        f = field.reshape(*lead, n_sub, p, n_sub, p).swapaxes(-3, -2)
        f = f[..., self.valid_subapertures, :, :] * self._centring
        g = scipy.fft.fftshift(scipy.fft.fft2(f, s=(m, m)), axes=(-2, -1))
        return (g.real**2 + g.imag**2) / m**2

    def _detector_frames(self, opd: np.ndarray) -> np.ndarray:
        return self.spots(opd)

    @property
    def reference_spots(self) -> np.ndarray:
        """Spots of a flat wavefront ``(n_valid_sub, m, m)``, for either model (read-only;
        the diffractive model's :attr:`reference_frame`)."""
        return self._reference_frame

    @cached_property
    def _coordinates(self) -> np.ndarray:
        m = self.spot_size
        return np.arange(m) - (m - 1) / 2.0

    def _raw_signals(self, spots: np.ndarray) -> np.ndarray:
        c = self._coordinates
        tot = spots.sum(axis=(-2, -1))
        tot = np.where(tot > 0, tot, np.inf)
        cx = np.einsum("...ij,j->...", spots, c) / tot
        cy = np.einsum("...ij,i->...", spots, c) / tot
        # centroid [pixel] * lambda / (oversampling d) [rad] * d [m] -> OPD difference [nm]
        scale = self.wavelength * 1e9 / self.oversampling
        return np.concatenate([cx, cy], axis=-1) * scale

    def pixel_values(self, frames: np.ndarray) -> np.ndarray:
        """Pixels entering the signals, ``(..., n_valid_sub * m * m)``."""
        f = np.asarray(frames, dtype=float)
        return f.reshape(*f.shape[:-3], -1)

    @property
    def normalisation(self) -> tuple[int, float]:
        """``(pixels, flux fraction)`` of one subaperture's normalisation (median subaperture)."""
        flux = self._reference_frame.sum(axis=(-2, -1))
        return self.spot_size**2, float(np.median(flux))

    def _jacobian_product(self, frame: np.ndarray, matrix: np.ndarray) -> np.ndarray:
        """For subaperture ``i``: ``dsx_i / dp_j = scale (c_j - cx_i) / N_i`` (``c_j`` the
        pixel's coordinate, ``cx_i`` the centroid, ``N_i`` the spot's flux)."""
        f, m_ = frame, matrix
        nv, m = self.n_valid_subapertures, self.spot_size
        scale = self.wavelength * 1e9 / self.oversampling
        c = self._coordinates
        tot = f.sum(axis=(-2, -1))
        cx = np.einsum("kij,j->k", f, c) / tot
        cy = np.einsum("kij,i->k", f, c) / tot
        jx = (c[None, None, :] - cx[:, None, None]) / tot[:, None, None] * scale
        jy = (c[None, :, None] - cy[:, None, None]) / tot[:, None, None] * scale
        jx = np.broadcast_to(jx, (nv, m, m))
        jy = np.broadcast_to(jy, (nv, m, m))
        out = m_[:, :nv, None, None] * jx + m_[:, nv:, None, None] * jy
        return out.reshape(m_.shape[0], -1)


def shack_hartmann_calibration(
    pupil: Pupil,
    wavelength: float,
    n_subapertures: int,
    basis: Any,
    amplitude: float = 10.0,
) -> Any:
    """Reconstructor of the geometric Shack-Hartmann and modal noise of the diffractive one.

    The reconstructor is that of the geometric model on ``basis``
    (:func:`aocontrol.sim.wfs.calibrate`); the noise of each slope comes from the diffractive
    model (centre of gravity of a spot sampled at lambda/(2d) per pixel; the model needs >= 4
    pupil samples per subaperture, hence a pupil of ``4 n_subapertures`` samples for it)
    linearised around the flat-wavefront spots. Slopes of different subapertures are
    independent and x/y uncorrelated for a symmetric spot, so the modal variance is
    ``sum_j R_ij^2 var_j``, with the flux-normalisation correction of
    :meth:`aocontrol.sim.wfs.WFSCalibration.noise_variance`. The EMCCD excess-noise factor is
    not modelled (use an effective read noise).

    Parameters
    ----------
    pupil : Pupil
        Pupil of the basis.
    wavelength : float
        Sensing wavelength [m].
    n_subapertures : int
        Lenslets across the diameter.
    basis : ModalBasis-like
        Modes to reconstruct (``modes`` (n_modes, n_valid) on ``pupil``).
    amplitude : float
        Push-pull amplitude of the geometric calibration [nm RMS].

    Returns
    -------
    WFSCalibration
        With ``photon_coeff`` and ``read_coeff`` per mode.
    """
    geo = ShackHartmannWFS(pupil, wavelength, n_subapertures, model="geometric")
    cal = calibrate(geo, basis, amplitude)
    p = 4  # samples per subaperture of the diffractive model (its minimum)
    fine = Pupil(diameter=pupil.diameter, n_pix=p * n_subapertures, obstruction=pupil.obstruction)
    dif = ShackHartmannWFS(fine, wavelength, n_subapertures, model="diffractive", oversampling=2)
    frame = dif.reference_frame
    pix = dif.pixel_values(frame)
    ph = np.empty(dif.n_signals)
    ro = np.empty(dif.n_signals)
    eye = np.eye(dif.n_signals)
    for start in range(0, dif.n_signals, _SH_BLOCK):
        rows = eye[start : start + _SH_BLOCK]
        j2 = dif.pixel_jacobian_product(frame, rows) ** 2
        ph[start : start + rows.shape[0]] = j2 @ pix
        ro[start : start + rows.shape[0]] = j2.sum(axis=1)
    if dif.n_signals == geo.n_signals and np.array_equal(
        dif.valid_subapertures, geo.valid_subapertures
    ):
        ph_s, ro_s = ph, ro
    else:  # sampling changed the valid set at the edge: the median slope of the fine model
        logger.info("Shack-Hartmann: valid subapertures differ; median slope noise used")
        ph_s = np.full(geo.n_signals, np.median(ph))
        ro_s = np.full(geo.n_signals, np.median(ro))
    r2 = cal.recon**2
    n_norm, f_norm = dif.normalisation
    return WFSCalibration(
        imat=cal.imat,
        recon=cal.recon,
        photon_coeff=r2 @ ph_s,
        read_coeff=r2 @ ro_s,
        amplitude=float(amplitude),
        norm_pixels=n_norm,
        norm_fraction=f_norm,
    )
