"""Science camera: PSF, perfect coronagraph, long exposure, Strehl and raw contrast.

The focal-plane field is the FFT of the pupil field ``P exp(i 2 pi opd / lambda)``, zero-padded
to ``n_fft = oversampling * n_pix`` points (rounded up to even), so one image pixel is
``pixel_scale = n_pix / n_fft`` lambda/D. Images are square with the optical axis on pixel
``(centre, centre)``, ``centre = n_image // 2``: odd-sized when cropped to a field of view,
``n_fft`` wide for the full field. Rows are ``y`` and columns ``x`` as on the
:class:`~aocontrol.sim.pupil.Pupil` grid; an optical path increasing along ``+x`` moves the image
towards ``+x``.

Perfect coronagraph (Cavarroc et al. 2006, A&A 447, 397; Sivaramakrishnan's "ideal
coronagraph"): each frame, the projection of the field on the aperture is removed before
propagation,

    E_c = P (exp(i phi) - c),   c = <P exp(i phi)> / <P>,

so an unaberrated (or piston-only) star vanishes and only the incoherent part (speckles) is
left. ``|c|^2`` is the frame's on-axis Strehl ratio; removing ``sqrt(exp(-sigma^2)) P`` instead,
as sometimes done, approximates this projection. By linearity the camera needs one FFT per
frame: ``FFT(E_c) = FFT(E) - c FFT(P)``.

Every image is normalised by the peak of the non-coronagraphic diffraction-limited PSF, so a
PSF peak is a Strehl ratio and a coronagraphic image is a raw contrast relative to the star's
peak. The sampled field is limited by the pupil sampling to ``|x|, |y| <= n_pix / 2`` lambda/D;
residual phase beyond that spatial frequency is not represented (and wraps at the edge).

References: Cavarroc, Boccaletti, Baudoz, Fusco, Rouan (2006), A&A 447, 397, "Fundamental
limitations on Earth-like planet detection with extremely large telescopes"; the "ideal
coronagraph" of Sivaramakrishnan and co-workers; Perrin et al. (2003), ApJ 596, 702, for the
small-aberration speckle oracle (a sine ripple of ``a`` rad gives two speckles of contrast
``(a/2)^2``).
"""

from __future__ import annotations

import logging
import numbers
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.fft

from aocontrol._validation import check_finite_array, check_positive
from aocontrol.sim.pupil import Pupil

__all__ = [
    "ScienceCamera",
    "LongExposure",
    "ScienceResult",
    "opd_to_phase",
    "opd_rms",
    "marechal_strehl",
    "strehl",
    "radial_profile",
    "mean_contrast",
]

logger = logging.getLogger(__name__)

#: Science wavelength of the SAXO+ study (H band) [m].
H_BAND = 1.65e-6
# Frames propagated together: bounds the temporary memory to ~ _CHUNK * n_fft * n_image * 8 B.
_CHUNK = 64
_PRECISIONS = {"single": (np.complex64, np.float32), "double": (np.complex128, np.float64)}


def opd_to_phase(opd: object, wavelength: float = H_BAND) -> np.ndarray:
    """Phase [rad] of an optical path difference [nm] at ``wavelength`` [m].

    ``phi = 2 pi opd / lambda``: an OPD of 1650 nm is 2 pi rad at 1.65 um.

    Parameters
    ----------
    opd : array_like, any shape
        Optical path difference [nm].
    wavelength : float
        Wavelength [m], > 0.

    Returns
    -------
    ndarray, same shape as ``opd``
        Phase [rad].

    Examples
    --------
    >>> float(opd_to_phase(1650.0, 1.65e-6) / np.pi)
    2.0
    """
    wavelength = _check_wavelength(wavelength)
    return check_finite_array("opd", opd) * (2.0 * np.pi / (wavelength * 1e9))


def opd_rms(opd_maps: object, pupil: Pupil, *, remove_piston: bool = True) -> np.ndarray:
    """RMS optical path over the pupil [nm], piston removed by default.

    Parameters
    ----------
    opd_maps : array_like, shape (..., n_pix, n_pix)
        Optical path difference maps [nm] on ``pupil``'s grid (values outside the mask ignored).
    pupil : Pupil
    remove_piston : bool
        Subtract the mean over the pupil first (piston does not affect the image).

    Returns
    -------
    ndarray, shape (...)
        RMS over the valid pixels [nm].
    """
    values = pupil.to_vector(check_finite_array("opd_maps", opd_maps))
    if remove_piston:
        values = values - values.mean(axis=-1, keepdims=True)
    return np.sqrt(np.mean(values**2, axis=-1))


def marechal_strehl(rms_nm: object, wavelength: float = H_BAND) -> np.ndarray | float:
    """Extended Maréchal approximation of the Strehl ratio, ``exp(-sigma^2)``.

    ``sigma = 2 pi rms / lambda`` is the phase RMS [rad] at ``wavelength``. Accurate to a few
    percent for ``sigma`` up to ~0.3 rad (Strehl > ~0.9); with modal coefficients orthonormal
    over the pupil, ``rms_nm`` is the norm of the (piston-free) coefficient vector.

    Parameters
    ----------
    rms_nm : float or array_like
        Piston-removed RMS optical path over the pupil [nm].
    wavelength : float
        Science wavelength [m].

    Returns
    -------
    float or ndarray, shape of ``rms_nm``
        Strehl ratio in (0, 1].

    Examples
    --------
    >>> round(float(marechal_strehl(1650.0 * 0.1 / (2 * np.pi))), 6)  # sigma = 0.1 rad
    0.99005
    """
    rms = check_finite_array("rms_nm", rms_nm)
    if np.any(rms < 0):
        raise ValueError(f"rms_nm must be >= 0 [nm], found min {rms.min()!r}")
    out = np.exp(-(opd_to_phase(rms, wavelength) ** 2))
    return float(out) if out.ndim == 0 else out


def strehl(psf: object, reference_peak: float = 1.0) -> float:
    """Strehl ratio: peak of ``psf`` over the diffraction-limited peak ``reference_peak``.

    Parameters
    ----------
    psf : array_like, shape (ny, nx)
        Non-coronagraphic image (long or short exposure). Images from :class:`ScienceCamera`
        are already normalised, so ``reference_peak = 1``.
    reference_peak : float
        Peak of the diffraction-limited PSF in the units of ``psf``.

    Returns
    -------
    float
        ``max(psf) / reference_peak`` (the peak, wherever a residual tilt puts it).
    """
    img = check_finite_array("psf", psf, ndim=2)
    return float(img.max()) / check_positive("reference_peak", reference_peak)


def _radii(
    shape: tuple[int, int], centre: tuple[float, float] | None, pixel_scale: float
) -> np.ndarray:
    ny, nx = shape
    cy, cx = (ny // 2, nx // 2) if centre is None else centre
    y, x = np.ogrid[:ny, :nx]
    return np.hypot(y - float(cy), x - float(cx)) * pixel_scale


def radial_profile(
    image: object,
    centre: tuple[float, float] | None = None,
    bins: float | object = 0.5,
    *,
    pixel_scale: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Azimuthal mean of an image in annuli [lambda/D].

    Parameters
    ----------
    image : array_like, shape (ny, nx)
    centre : (row, col) in pixels, optional
        Centre of the annuli; default ``(ny // 2, nx // 2)``, the centre of
        :class:`ScienceCamera` images.
    bins : float or array_like
        A bin width [lambda/D] (annuli from 0 to the largest circle inside the image), or the
        increasing bin edges [lambda/D], shape (n_bins + 1,). A pixel at radius ``r`` falls in
        bin ``i`` when ``edges[i] <= r < edges[i + 1]``.
    pixel_scale : float
        Image pixel size [lambda/D] (:attr:`ScienceCamera.pixel_scale`).

    Returns
    -------
    radii_ld : ndarray, shape (n_bins,)
        Mean radius of the pixels of each bin [lambda/D] (NaN for an empty bin).
    profile : ndarray, shape (n_bins,)
        Mean of ``image`` over each annulus (NaN for an empty bin).
    """
    img = check_finite_array("image", image, ndim=2)
    pixel_scale = check_positive("pixel_scale", pixel_scale)
    r = _radii(img.shape, centre, pixel_scale)
    if np.ndim(bins) == 0:
        width = check_positive("bins", bins)
        cy, cx = (img.shape[0] // 2, img.shape[1] // 2) if centre is None else centre
        r_max = min(cy, cx, img.shape[0] - 1 - cy, img.shape[1] - 1 - cx) * pixel_scale
        edges = np.arange(0.0, r_max + 0.5 * width, width)
        if edges.size < 2:
            raise ValueError(f"bins={width!r} lambda/D is wider than the image radius {r_max}")
    else:
        edges = check_finite_array("bins", bins, ndim=1)
        if edges.size < 2 or np.any(np.diff(edges) <= 0) or edges[0] < 0:
            raise ValueError(f"bins must be >= 2 increasing edges >= 0 [lambda/D], got {edges}")
    which = np.digitize(r.ravel(), edges) - 1
    inside = (which >= 0) & (which < edges.size - 1)
    n_bins = edges.size - 1
    counts = np.bincount(which[inside], minlength=n_bins).astype(float)
    sums = np.bincount(which[inside], weights=img.ravel()[inside], minlength=n_bins)
    rsum = np.bincount(which[inside], weights=r.ravel()[inside], minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        return rsum / counts, sums / counts


def mean_contrast(
    image: object,
    r_in: float = 4.0,
    r_out: float = 6.0,
    *,
    pixel_scale: float,
    centre: tuple[float, float] | None = None,
) -> float:
    """Mean of ``image`` over the annulus ``r_in <= r < r_out`` [lambda/D].

    With a coronagraphic image from :class:`ScienceCamera` this is the raw contrast of the
    paper (mean over 4-6 lambda/D).

    Parameters
    ----------
    image : array_like, shape (ny, nx)
    r_in, r_out : float
        Inner and outer radius [lambda/D], ``0 <= r_in < r_out``.
    pixel_scale : float
        Image pixel size [lambda/D].
    centre : (row, col) in pixels, optional
        Default ``(ny // 2, nx // 2)``.

    Raises
    ------
    ValueError
        If the annulus is empty or not fully inside the image.
    """
    img = check_finite_array("image", image, ndim=2)
    pixel_scale = check_positive("pixel_scale", pixel_scale)
    r_out = check_positive("r_out", r_out)
    if not (0.0 <= float(r_in) < r_out):
        raise ValueError(f"r_in must be in [0, r_out={r_out}) lambda/D, got {r_in!r}")
    cy, cx = (img.shape[0] // 2, img.shape[1] // 2) if centre is None else centre
    r_edge = min(cy, cx, img.shape[0] - 1 - cy, img.shape[1] - 1 - cx) * pixel_scale
    if r_out > r_edge * (1.0 + 1e-12):
        raise ValueError(
            f"r_out={r_out} lambda/D does not fit in the image (radius {r_edge} lambda/D)"
        )
    r = _radii(img.shape, centre, pixel_scale)
    sel = (r >= r_in) & (r < r_out)
    if not np.any(sel):
        raise ValueError(f"annulus [{r_in}, {r_out}) lambda/D contains no pixel")
    return float(img[sel].mean())


def _check_wavelength(wavelength: object) -> float:
    wavelength = check_positive("wavelength", wavelength)
    if wavelength > 1e-3:
        raise ValueError(
            f"wavelength is in metres (e.g. 1.65e-6), got {wavelength!r}; was it in nm?"
        )
    return wavelength


@dataclass(frozen=True)
class ScienceCamera:
    """Imaging camera with an optional perfect coronagraph, at one wavelength.

    Parameters
    ----------
    pupil : Pupil
        Pupil and grid of the OPD maps ``(n_pix, n_pix)``.
    wavelength : float, default 1.65e-6
        Science wavelength [m] (H band in the SAXO+ study).
    oversampling : float, default 2
        Image pixels per lambda/D, >= 2 (Nyquist). ``n_fft = oversampling * n_pix`` is rounded
        up to an even integer; :attr:`pixel_scale` gives the exact sampling.
    field_of_view : float or None, default None
        Half-width of the square image [lambda/D], in (0, n_pix / 2]; ``None`` keeps the whole
        field the pupil sampling supports (``n_pix / 2``). Set it a little beyond the DM control
        radius (e.g. 24 for ~20 lambda/D) to save time.
    coronagraph : bool, default True
        Also form the perfect-coronagraph image (one FFT serves both images).
    precision : {"single", "double"}, default "single"
        FFT precision: complex64 (about twice as fast; the 4-6 lambda/D mean contrast agrees
        with complex128 to ~1e-6 relative, single pixels to ~1e-4, see the tests) or
        complex128. Sums over frames are always float64.
    workers : int or None, default None
        Threads for :func:`scipy.fft.fft` (None: scipy's default, 1; -1: all cores).

    Attributes
    ----------
    n_fft : int
        FFT size (pupil zero-padded to ``n_fft x n_fft``).
    n_image : int
        Image side [pixels]: ``2 ceil(field_of_view / pixel_scale) + 1`` (odd) when cropped,
        ``n_fft`` for the full field.
    centre : int
        Index of the optical axis in both image axes, ``n_image // 2``.
    pixel_scale : float
        Image pixel size [lambda/D] (``n_pix / n_fft``).

    Examples
    --------
    >>> from aocontrol.sim.pupil import vlt_pupil
    >>> cam = ScienceCamera(vlt_pupil(32), field_of_view=8.0)
    >>> exposure = cam.long_exposure()
    >>> exposure.add(np.zeros((2, 32, 32)))
    >>> round(exposure.result().strehl, 12), exposure.result().mean_contrast_4_6 < 1e-10
    (1.0, True)
    """

    pupil: Pupil
    wavelength: float = H_BAND
    oversampling: float = 2.0
    field_of_view: float | None = None
    coronagraph: bool = True
    precision: str = "single"
    workers: int | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.pupil, Pupil):
            raise TypeError(f"pupil must be a Pupil, got {type(self.pupil).__name__}")
        _check_wavelength(self.wavelength)
        q = check_positive("oversampling", self.oversampling)
        if q < 2.0:
            raise ValueError(
                f"oversampling must be >= 2 pixels per lambda/D (Nyquist sampling of the "
                f"intensity), got {q!r}"
            )
        if self.field_of_view is not None:
            fov = check_positive("field_of_view", self.field_of_view)
            if fov > self.pupil.n_pix / 2:
                raise ValueError(
                    f"field_of_view must be <= n_pix / 2 = {self.pupil.n_pix / 2} lambda/D "
                    f"(the pupil sampling limit), got {fov!r}"
                )
        if self.precision not in _PRECISIONS:
            raise ValueError(f"precision must be 'single' or 'double', got {self.precision!r}")
        if self.workers is not None and (
            isinstance(self.workers, bool) or not isinstance(self.workers, numbers.Integral)
        ):
            raise TypeError(f"workers must be an integer or None, got {self.workers!r}")

    # -- geometry ------------------------------------------------------------------------
    @cached_property
    def n_fft(self) -> int:
        """FFT size [pixels], even."""
        return 2 * int(np.ceil(self.oversampling * self.pupil.n_pix / 2 - 1e-9))

    @property
    def pixel_scale(self) -> float:
        """Image pixel size [lambda/D]."""
        return self.pupil.n_pix / self.n_fft

    @cached_property
    def _crop(self) -> tuple[int, int]:
        """Rows/columns ``[lo, hi)`` of the (zero-frequency-centred) FFT kept in the image."""
        mid = self.n_fft // 2
        if self.field_of_view is not None:
            half = int(np.ceil(self.field_of_view / self.pixel_scale - 1e-9))
            if half < mid:
                return mid - half, mid + half + 1
        return 0, self.n_fft

    @property
    def n_image(self) -> int:
        """Image side [pixels]: ``2 half + 1`` when cropped, ``n_fft`` for the full field."""
        lo, hi = self._crop
        return hi - lo

    @property
    def centre(self) -> int:
        """Pixel index of the optical axis along both image axes (``n_image // 2``)."""
        return self.n_fft // 2 - self._crop[0]

    @cached_property
    def radius_map(self) -> np.ndarray:
        """Distance of each image pixel from the optical axis [lambda/D], (n_image, n_image)."""
        r = _radii((self.n_image, self.n_image), (self.centre, self.centre), self.pixel_scale)
        r.setflags(write=False)
        return r

    @property
    def _dtypes(self) -> tuple[type, type]:
        return _PRECISIONS[self.precision]

    @cached_property
    def _shifted_mask(self) -> np.ndarray:
        # Multiplying by (-1)^(i + j) moves the FFT's zero frequency to n_fft / 2, so a crop is
        # a contiguous slice (no fftshift, no gather).
        n = self.pupil.n_pix
        sign = 1.0 - 2.0 * (np.add.outer(np.arange(n), np.arange(n)) % 2)
        return (self.pupil.mask * sign).astype(self._dtypes[1])

    @cached_property
    def _aperture_field(self) -> np.ndarray:
        """Cropped focal field of the unaberrated aperture, FFT(P), (n_image, n_image)."""
        field_ = self._propagate(self._shifted_mask[None].astype(self._dtypes[0]))[0]
        field_.setflags(write=False)
        return field_

    @property
    def _norm(self) -> float:
        # Diffraction-limited peak |sum P|^2 = n_valid^2 (P binary).
        return float(self.pupil.n_valid) ** 2

    @cached_property
    def diffraction_psf(self) -> np.ndarray:
        """Non-coronagraphic diffraction-limited PSF, peak 1, shape (n_image, n_image)."""
        psf = np.abs(self._aperture_field.astype(np.complex128)) ** 2 / self._norm
        psf.setflags(write=False)
        return psf

    # -- propagation ---------------------------------------------------------------------
    def _propagate(self, pupil_field: np.ndarray) -> np.ndarray:
        """(m, n_pix, n_pix) sign-shifted pupil fields -> (m, n_image, n_image) focal fields.

        ``pupil_field`` may also be given zero-padded along its last axis, ``(m, n_pix,
        n_fft)`` (it is then overwritten): the first transform needs no padded copy.
        """
        lo, hi = self._crop
        n, n_fft = self.pupil.n_pix, self.n_fft
        # Pruned 2-D FFT: rows first (only n_pix rows are non-zero), keep the cropped columns,
        # then along columns, both on zero-padded arrays (the transforms of the same values
        # as scipy's padding with n=, without its copies).
        if pupil_field.shape[-1] != n_fft:
            padded = np.zeros(pupil_field.shape[:-1] + (n_fft,), dtype=pupil_field.dtype)
            padded[..., :n] = pupil_field
            pupil_field = padded
        f = scipy.fft.fft(pupil_field, axis=-1, workers=self.workers, overwrite_x=True)
        g = np.zeros(f.shape[:-2] + (n_fft, hi - lo), dtype=f.dtype)
        g[..., :n, :] = f[..., lo:hi]
        return scipy.fft.fft(g, axis=-2, workers=self.workers, overwrite_x=True)[..., lo:hi, :]

    def _check_opd(self, opd: object) -> np.ndarray:
        """Validated OPD, shape (n_frames, n_pix, n_pix) or (n_frames, n_valid)."""
        arr = check_finite_array("opd_maps", opd)
        n, n_valid = self.pupil.n_pix, self.pupil.n_valid
        if arr.shape in ((n, n), (n_valid,)):
            arr = arr[None]
        if not (arr.shape[1:] == (n, n) or (arr.ndim == 2 and arr.shape[1] == n_valid)):
            raise ValueError(
                f"opd_maps must have shape (n_frames, {n}, {n}) (maps [nm]) or "
                f"(n_frames, {n_valid}) (values on valid pixels [nm]), got {arr.shape}"
            )
        return arr

    @cached_property
    def _valid_sign(self) -> np.ndarray:
        return self.pupil.to_vector(self._shifted_mask)

    def _fields(self, opd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """OPD [nm] (m, n_pix, n_pix) or (m, n_valid) -> focal fields (m, n_image, n_image) and
        the coherent amplitude c = <P exp(i phi)> / <P>, shape (m,)."""
        cdtype, rdtype = self._dtypes
        if opd.ndim == 3:
            opd = self.pupil.to_vector(opd)
        phase = (opd * (2.0 * np.pi / (self.wavelength * 1e9))).astype(rdtype, copy=False)
        values = np.empty(phase.shape, dtype=cdtype)
        values.real = np.cos(phase)
        values.imag = np.sin(phase)
        c = values.sum(axis=-1, dtype=np.complex128) / self.pupil.n_valid
        m, n = phase.shape[0], self.pupil.n_pix
        # The pupil fields zero-padded for the first transform, filled row run by row run.
        pupil_field = np.zeros((m, n, self.n_fft), dtype=cdtype)
        values *= self._valid_sign
        for row, a, b, c0 in self.pupil.runs:
            pupil_field[:, row, c0 : c0 + b - a] = values[:, a:b]
        return self._propagate(pupil_field), c

    def images(self, opd_maps: object) -> tuple[np.ndarray, np.ndarray | None]:
        """Instantaneous images of each frame, normalised to the diffraction-limited peak.

        Parameters
        ----------
        opd_maps : array_like, shape (n_frames, n_pix, n_pix) or (n_frames, n_valid)
            Residual optical path [nm] (one 2-D map is one frame).

        Returns
        -------
        psf : ndarray, shape (n_frames, n_image, n_image)
            Non-coronagraphic PSF; its peak is the frame's Strehl ratio.
        coronagraphic : ndarray, shape (n_frames, n_image, n_image) or None
            Perfect-coronagraph image (raw contrast); None if ``coronagraph`` is False.
        """
        opd = self._check_opd(opd_maps)
        psf = np.empty((opd.shape[0], self.n_image, self.n_image))
        coro = np.empty_like(psf) if self.coronagraph else None
        for s in range(0, opd.shape[0], _CHUNK):
            f, c = self._fields(opd[s : s + _CHUNK])
            # Same arithmetic as LongExposure.add (|f|^2 in the FFT precision, then float64).
            psf[s : s + _CHUNK] = _intensity(f)
            if coro is not None:
                coro[s : s + _CHUNK] = _intensity(self._coronagraph(f, c))
        psf /= self._norm
        if coro is not None:
            coro /= self._norm
        return psf, coro

    def _coronagraph(self, f: np.ndarray, c: np.ndarray) -> np.ndarray:
        f -= c.astype(f.dtype)[:, None, None] * self._aperture_field
        return f

    def long_exposure(self) -> LongExposure:
        """A new, empty :class:`LongExposure` accumulator for this camera."""
        return LongExposure(self)

    def radial_profile(
        self, image: object, bin_width: float = 0.5
    ) -> tuple[np.ndarray, np.ndarray]:
        """:func:`radial_profile` of one of this camera's images, bins of ``bin_width`` lambda/D."""
        return radial_profile(
            image, (self.centre, self.centre), bin_width, pixel_scale=self.pixel_scale
        )

    def mean_contrast(self, image: object, r_in: float = 4.0, r_out: float = 6.0) -> float:
        """:func:`mean_contrast` of one of this camera's images over ``[r_in, r_out)`` lambda/D."""
        return mean_contrast(
            image, r_in, r_out, pixel_scale=self.pixel_scale, centre=(self.centre, self.centre)
        )


def _intensity(f: np.ndarray) -> np.ndarray:
    """|f|^2 in the real dtype of ``f``."""
    return f.real * f.real + f.imag * f.imag


class LongExposure:
    """Long-exposure accumulator: feed OPD frames in chunks, read the mean images.

    Frames are not stored; only float64 sums of the instantaneous images. Equivalent to
    averaging :meth:`ScienceCamera.images` over all frames added.

    Parameters
    ----------
    camera : ScienceCamera

    Attributes
    ----------
    n_frames : int
        Frames accumulated so far.

    Examples
    --------
    >>> from aocontrol.sim.pupil import vlt_pupil
    >>> exposure = ScienceCamera(vlt_pupil(32)).long_exposure()
    >>> exposure.add(np.zeros((3, 32, 32)))
    >>> exposure.n_frames, round(float(exposure.psf.max()), 12)
    (3, 1.0)
    """

    def __init__(self, camera: ScienceCamera) -> None:
        if not isinstance(camera, ScienceCamera):
            raise TypeError(f"camera must be a ScienceCamera, got {type(camera).__name__}")
        self.camera = camera
        shape = (camera.n_image, camera.n_image)
        self._psf_sum = np.zeros(shape)
        self._coro_sum = np.zeros(shape) if camera.coronagraph else None
        self._n = 0

    @property
    def n_frames(self) -> int:
        """Number of frames accumulated."""
        return self._n

    def add(self, opd_maps: object) -> None:
        """Accumulate frames.

        Parameters
        ----------
        opd_maps : array_like, shape (n_frames, n_pix, n_pix) or (n_frames, n_valid)
            Residual optical path [nm] on the camera's pupil grid, or on its valid pixels
            (row-major order of the mask). A single ``(n_pix, n_pix)`` map is one frame.

        Raises
        ------
        ValueError
            Wrong shape or non-finite values.
        """
        cam = self.camera
        opd = cam._check_opd(opd_maps)
        for s in range(0, opd.shape[0], _CHUNK):
            f, c = cam._fields(opd[s : s + _CHUNK])
            self._psf_sum += _intensity(f).sum(axis=0, dtype=np.float64)
            if self._coro_sum is not None:
                self._coro_sum += _intensity(cam._coronagraph(f, c)).sum(axis=0, dtype=np.float64)
        self._n += opd.shape[0]
        logger.debug("LongExposure: %d frames added (total %d)", opd.shape[0], self._n)

    def _mean(self, total: np.ndarray) -> np.ndarray:
        if self._n == 0:
            raise RuntimeError("no frame accumulated yet: call add(opd_maps) first")
        return total / (self._n * self.camera._norm)

    @property
    def psf(self) -> np.ndarray:
        """Long-exposure PSF normalised to the diffraction-limited peak, (n_image, n_image)."""
        return self._mean(self._psf_sum)

    @property
    def coronagraphic(self) -> np.ndarray | None:
        """Long-exposure perfect-coronagraph image (raw contrast), (n_image, n_image).

        None if the camera has no coronagraph.
        """
        return None if self._coro_sum is None else self._mean(self._coro_sum)

    def reset(self) -> None:
        """Discard all accumulated frames."""
        self._psf_sum[...] = 0.0
        if self._coro_sum is not None:
            self._coro_sum[...] = 0.0
        self._n = 0

    def result(self, bin_width: float = 0.5) -> ScienceResult:
        """Figures of merit of the exposure so far.

        Parameters
        ----------
        bin_width : float
            Width of the annuli of the contrast profile [lambda/D].

        Returns
        -------
        ScienceResult
            Strehl (PSF peak), mean contrast over 4-6 and 1-2 lambda/D and the radial profile,
            of the coronagraphic image (of the PSF if the camera has no coronagraph).
        """
        cam = self.camera
        psf = self.psf
        image = psf if self._coro_sum is None else self.coronagraphic
        radii, profile = cam.radial_profile(image, bin_width)
        return ScienceResult(
            strehl=strehl(psf),
            mean_contrast_4_6=cam.mean_contrast(image, 4.0, 6.0),
            radii_ld=radii,
            contrast_profile=profile,
            n_frames=self._n,
            wavelength=cam.wavelength,
            coronagraph=cam.coronagraph,
            mean_contrast_1_2=cam.mean_contrast(image, 1.0, 2.0),
        )


@dataclass(frozen=True, eq=False)
class ScienceResult:
    """Science figures of merit of one run (long exposure).

    Parameters
    ----------
    strehl : float
        Peak of the long-exposure PSF over the diffraction-limited peak, at ``wavelength``.
    mean_contrast_4_6 : float
        Mean raw contrast over 4 <= r < 6 lambda/D (coronagraphic image / star peak).
    radii_ld : ndarray, shape (n_bins,)
        Mean radius of each annulus [lambda/D].
    contrast_profile : ndarray, shape (n_bins,)
        Azimuthal mean raw contrast in each annulus.
    n_frames : int
        Frames in the long exposure.
    wavelength : float
        Science wavelength [m].
    coronagraph : bool
        True if the contrast is after the perfect coronagraph (else the raw PSF).
    mean_contrast_1_2 : float
        Mean raw contrast over 1 <= r < 2 lambda/D, where prediction matters most (``nan``
        in results written before it was recorded).

    Notes
    -----
    Compared by identity (``eq=False``): it holds arrays. Arrays are stored read-only.
    """

    strehl: float
    mean_contrast_4_6: float
    radii_ld: np.ndarray = field(repr=False)
    contrast_profile: np.ndarray = field(repr=False)
    n_frames: int
    wavelength: float = H_BAND
    coronagraph: bool = True
    mean_contrast_1_2: float = float("nan")

    def __post_init__(self) -> None:
        radii = np.array(self.radii_ld, dtype=float)
        prof = np.array(self.contrast_profile, dtype=float)
        if radii.ndim != 1 or radii.shape != prof.shape:
            raise ValueError(
                f"radii_ld and contrast_profile must be 1-D of equal length, got shapes "
                f"{radii.shape} and {prof.shape}"
            )
        if (
            isinstance(self.n_frames, bool)
            or not isinstance(self.n_frames, numbers.Integral)
            or self.n_frames < 1
        ):
            raise ValueError(f"n_frames must be an integer >= 1, got {self.n_frames!r}")
        _check_wavelength(self.wavelength)
        radii.setflags(write=False)
        prof.setflags(write=False)
        object.__setattr__(self, "radii_ld", radii)
        object.__setattr__(self, "contrast_profile", prof)
        object.__setattr__(self, "strehl", float(self.strehl))
        object.__setattr__(self, "mean_contrast_4_6", float(self.mean_contrast_4_6))
        object.__setattr__(self, "mean_contrast_1_2", float(self.mean_contrast_1_2))
        object.__setattr__(self, "n_frames", int(self.n_frames))
        object.__setattr__(self, "wavelength", float(self.wavelength))
        object.__setattr__(self, "coronagraph", bool(self.coronagraph))

    def to_dict(self) -> dict:
        """Plain-Python dict (lists and numbers), e.g. for JSON; an empty bin is NaN."""
        return {
            "strehl": self.strehl,
            "mean_contrast_4_6": self.mean_contrast_4_6,
            "radii_ld": self.radii_ld.tolist(),
            "contrast_profile": self.contrast_profile.tolist(),
            "n_frames": self.n_frames,
            "wavelength": self.wavelength,
            "coronagraph": self.coronagraph,
            "mean_contrast_1_2": self.mean_contrast_1_2,
        }

    @classmethod
    def from_dict(cls, data: dict) -> ScienceResult:
        """Inverse of :meth:`to_dict`."""
        return cls(**data)
