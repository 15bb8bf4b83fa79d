"""The interface the optical wavefront-sensor models share (:class:`WavefrontSensor`; private
module, the class is public as :class:`aocontrol.sim.wfs.WavefrontSensor`).

An optical model takes optical path difference (OPD) maps ``(..., n_pix, n_pix)`` [nm] on a
:class:`~aocontrol.sim.pupil.Pupil` grid, forms noise-free detector frames ``(...,
*frame_shape)`` (fraction of the incoming flux per pixel) and turns frames into signal vectors
``(..., n_signals)``, minus the signals of a flat wavefront. The base class owns what every
detector does the same way:

* the valid subapertures: those of the ``n_sub x n_sub`` grid whose geometric illumination by
  the pupil (area-weighted rebinning of the pupil mask) is at least ``valid_threshold``;
* the checks of the shared parameters and of the OPD maps;
* the flat-wavefront reference, frame and signals, computed once and read-only;
* ``signals(opd) = signals_from_frame(detector_image(opd))`` and ``measure``: photon (Poisson)
  and read-out noise on the detector pixels (:func:`aocontrol.sim.noise.add_detector_noise`),
  then the signals;
* the matrix check of ``pixel_jacobian_product``;
* pickling: the cached attributes named in ``_unpickled`` (work buffers) are left out and
  rebuilt on first use.

A detector implements its optics and its signal processing: ``frame_shape``,
``_signals_per_subaperture``, ``_check_parameters``, ``_detector_frames(opd)``,
``_raw_signals(frames)``, ``pixel_values(frames)``, ``normalisation`` and
``_jacobian_product(frame, matrix)``. A configuration without a detector (the geometric
Shack-Hartmann) overrides ``_require_detector``.
"""

from __future__ import annotations

import abc
from functools import cached_property
from typing import ClassVar

import numpy as np

from aocontrol._validation import check_in_range, check_positive
from aocontrol.sim.noise import add_detector_noise
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.wfs._common import bin_matrix, check_opd

__all__ = ["WavefrontSensor"]


class WavefrontSensor(abc.ABC):
    """Base of the optical WFS models: OPD maps [nm] -> detector frames -> signals.

    Not instantiated itself: :class:`~aocontrol.sim.wfs.PyramidWFS` and
    :class:`~aocontrol.sim.wfs.ShackHartmannWFS` are frozen dataclasses deriving from it, with
    the attributes below among their fields (module docstring: what the base owns and what a
    detector implements). In the loop, :class:`~aocontrol.sim.wfs.DiffractiveSensor` runs one
    behind the loop's sensor protocol (:class:`~aocontrol.sim.wfs.Sensor`).

    Attributes
    ----------
    pupil : Pupil
        Pupil grid; OPD maps have shape ``(..., n_pix, n_pix)`` [nm].
    wavelength : float
        Sensing wavelength [m].
    n_subapertures : int
        Subapertures across the pupil (detector pixels across a pupil image for the pyramid,
        lenslets for the Shack-Hartmann).
    valid_threshold : float
        Minimum geometric illumination of a valid subaperture, in (0, 1].
    """

    pupil: Pupil
    wavelength: float
    n_subapertures: int
    valid_threshold: float

    #: Cached attributes left out of a pickle (work buffers, rebuilt on first use).
    _unpickled: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.pupil, Pupil):
            raise TypeError(f"pupil must be a Pupil, got {type(self.pupil).__name__}")
        check_positive("wavelength", self.wavelength)
        self._check_parameters()
        check_in_range(
            "valid_threshold",
            self.valid_threshold,
            0.0,
            1.0,
            low_inclusive=False,
            high_inclusive=True,
        )

    # ------------------------------------------------------------------ what a detector implements
    @abc.abstractmethod
    def _check_parameters(self) -> None:
        """Check the detector's own parameters (``ValueError`` naming the argument)."""

    @property
    @abc.abstractmethod
    def frame_shape(self) -> tuple[int, ...]:
        """Shape of one detector frame."""

    @property
    @abc.abstractmethod
    def _signals_per_subaperture(self) -> int:
        """Signals per valid subaperture."""

    @abc.abstractmethod
    def _detector_frames(self, opd: np.ndarray) -> np.ndarray:
        """Noise-free frames ``(..., *frame_shape)`` of OPD maps ``(..., n_pix, n_pix)`` [nm]
        (checked here), fraction of the incoming flux per pixel."""

    @abc.abstractmethod
    def _raw_signals(self, frames: np.ndarray) -> np.ndarray:
        """Signals ``(..., n_signals)`` of float frames ``(..., *frame_shape)``, before the
        flat-wavefront reference is subtracted."""

    @abc.abstractmethod
    def pixel_values(self, frames: np.ndarray) -> np.ndarray:
        """Detector pixels entering the signals, ``(..., n_pixels)``, of frames ``(...,
        *frame_shape)``."""

    @property
    @abc.abstractmethod
    def normalisation(self) -> tuple[int, float]:
        """``(pixels, flux fraction)`` of one flux-normalisation sum of the signals."""

    @abc.abstractmethod
    def _jacobian_product(self, frame: np.ndarray, matrix: np.ndarray) -> np.ndarray:
        """``matrix @ J`` (:meth:`pixel_jacobian_product`) for a float frame and a checked
        ``(n_out, n_signals)`` matrix."""

    def _require_detector(self, what: str) -> None:
        """Raise ``ValueError`` naming ``what`` if this configuration forms no detector frames
        (every configuration does, unless a detector says otherwise)."""
        return None

    # ------------------------------------------------------------------ subapertures
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
        return self._signals_per_subaperture * self.n_valid_subapertures

    def _check_opd(self, opd: object) -> np.ndarray:
        """Finite OPD maps [nm] of shape ``(..., n_pix, n_pix)``, or a ``ValueError``."""
        return check_opd(opd, self.pupil.n_pix)

    # ------------------------------------------------------------------ frames
    def detector_image(self, opd: np.ndarray) -> np.ndarray:
        """Noise-free detector frames of OPD maps.

        Parameters
        ----------
        opd : array_like, shape (..., n_pix, n_pix)
            Optical path difference [nm] on the pupil grid.

        Returns
        -------
        ndarray, shape (..., *frame_shape)
            Fraction of the incoming flux on each detector pixel (multiply by the photons per
            frame for photo-electrons).

        Raises
        ------
        ValueError
            OPD maps of another shape or not finite; a configuration without a detector.
        """
        self._require_detector("detector_image")
        return self._detector_frames(opd)

    @cached_property
    def _reference_frame(self) -> np.ndarray:
        """Frame of a flat wavefront (read-only), for any configuration."""
        n_pix = self.pupil.n_pix
        ref = self._detector_frames(np.zeros((n_pix, n_pix)))
        ref.setflags(write=False)
        return ref

    @property
    def reference_frame(self) -> np.ndarray:
        """Detector frame of a flat wavefront, shape ``frame_shape`` (fraction of the flux;
        read-only, computed once)."""
        self._require_detector("reference_frame")
        return self._reference_frame

    @cached_property
    def reference_signals(self) -> np.ndarray:
        """Raw signals of a flat wavefront, ``(n_signals,)`` (subtracted by :meth:`signals`;
        read-only, computed once)."""
        ref = self._raw_signals(self._reference_frame)
        ref.setflags(write=False)
        return ref

    # ------------------------------------------------------------------ signals
    def signals_from_frame(self, frames: np.ndarray) -> np.ndarray:
        """Signals of detector frames.

        Parameters
        ----------
        frames : array_like, shape (..., *frame_shape)
            Detector frames in any flux unit (the signals are normalised by the flux).

        Returns
        -------
        ndarray, shape (..., n_signals)
            Signals minus those of a flat wavefront.
        """
        return self._raw_signals(np.asarray(frames, dtype=float)) - self.reference_signals

    def signals(self, opd: np.ndarray) -> np.ndarray:
        """Noise-free signals of OPD maps.

        Parameters
        ----------
        opd : array_like, shape (..., n_pix, n_pix)
            Optical path difference [nm].

        Returns
        -------
        ndarray, shape (..., n_signals)
            Signals minus those of a flat wavefront.
        """
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
            Photo-electrons per frame entering the WFS (whole pupil), > 0.
        read_noise : float
            Read-out noise [e- RMS per pixel].
        rng : numpy.random.Generator
            Source of the detector noise.

        Returns
        -------
        ndarray, shape (..., n_signals)
        """
        n_ph = check_positive("photons", photons)
        frames = add_detector_noise(self.detector_image(opd) * n_ph, read_noise, rng)
        return self.signals_from_frame(frames)

    def pixel_jacobian_product(self, frame: np.ndarray, matrix: np.ndarray) -> np.ndarray:
        """``matrix @ J`` with ``J`` the derivative of the signals w.r.t. the pixel values.

        Parameters
        ----------
        frame : array_like, shape frame_shape
            Noise-free detector frame in photo-electrons (any flux unit; ``J`` scales as
            1/flux).
        matrix : array_like, shape (n_out, n_signals) or (n_signals,)
            E.g. a reconstructor.

        Returns
        -------
        ndarray, shape (n_out, n_pixels)
            Over the pixels of :meth:`pixel_values`; the flux normalisation of the signals is
            differentiated too.

        Raises
        ------
        ValueError
            If ``matrix`` does not have ``n_signals`` columns.
        """
        m = np.atleast_2d(np.asarray(matrix, dtype=float))
        if m.shape[-1] != self.n_signals:
            raise ValueError(
                f"matrix must have n_signals={self.n_signals} columns, got shape {m.shape}"
            )
        return self._jacobian_product(np.asarray(frame, dtype=float), m)

    # ------------------------------------------------------------------ pickling
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        for name in self._unpickled:
            state.pop(name, None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
