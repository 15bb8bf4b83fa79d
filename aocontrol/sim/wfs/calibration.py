"""WFS calibration: interaction matrix, reconstructor, optical gains, noise propagation, and
the linear modal WFS model of the fast loop.

Modal conventions (DESIGN.md): a modal basis is ``modes`` of shape ``(n_modes, n_valid)``
over the valid pupil pixels, orthonormal over the pupil with a unit coefficient = 1 nm RMS
(``modes @ modes.T = n_valid I``). Every function accepts a ModalBasis-like object (with
``.modes`` and ``.pupil``) or a plain array together with the WFS's pupil.

Interaction matrix ``D`` (n_signals, n_modes): push-pull ``(s(+a m) - s(-a m)) / (2 a)``,
signals per nm of modal coefficient. Reconstructor ``R`` (n_modes, n_signals): truncated
pseudo-inverse, modal measurement ``m = R s`` [nm].

Optical gains: the sensitivity of a pyramid drops when the wavefront is not flat. Per mode,
``g_i = [R D_res]_ii`` with ``D_res`` the interaction matrix measured around residual phase
screens (averaged over the screens) and ``R`` the diffraction-limited reconstructor: the
factor by which a modal measurement underestimates the true coefficient in closed loop
(Korkiakoski et al. 2008; Deo et al. 2019; Chambouleyron et al. 2020).

Noise propagation: detector pixels with Poisson + read noise, linearised through the signal
processing (flux normalisation included) and the reconstructor, ``var_i = c_ph,i / N +
c_ro,i sigma_ro^2 / N^2`` [nm^2] for ``N`` photo-electrons per frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from aocontrol._validation import check_finite_array, check_int, check_nonnegative, check_positive
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.turbulence import von_karman_psd

__all__ = [
    "interaction_matrix",
    "reconstructor",
    "optical_gains",
    "noise_propagation",
    "fitting_residual_screens",
    "white_noise_propagation",
    "WFSCalibration",
    "calibrate",
    "LinearModalSensor",
    "LinearModalWFS",
]

logger = logging.getLogger(__name__)


def _modes_and_pupil(wfs: Any, basis: Any) -> tuple[np.ndarray, Pupil]:
    """``(modes (n_modes, n_valid), pupil)`` from a ModalBasis-like object or an array."""
    pupil = wfs.pupil
    if hasattr(basis, "modes"):
        b_pupil = getattr(basis, "pupil", None)
        if b_pupil is not None and b_pupil != pupil:
            raise ValueError(f"basis.pupil must equal wfs.pupil, got {b_pupil} and {pupil}")
        modes = np.asarray(basis.modes, dtype=float)
    else:
        modes = np.asarray(basis, dtype=float)
    if modes.ndim == 1:
        modes = modes[None, :]
    if modes.ndim != 2 or modes.shape[1] != pupil.n_valid:
        raise ValueError(
            f"modes must have shape (n_modes, n_valid={pupil.n_valid}), got {modes.shape}"
        )
    return modes, pupil


def interaction_matrix(
    wfs: Any,
    basis_or_modes: Any,
    amplitude: float = 10.0,
    *,
    offset_opd: np.ndarray | None = None,
    batch: int = 16,
    method: str = "push-pull",
) -> np.ndarray:
    """Interaction matrix by push-pull (or exact linearisation).

    Parameters
    ----------
    wfs : PyramidWFS or ShackHartmannWFS
        Any object with ``pupil``, ``n_signals`` and ``signals(opd)``.
    basis_or_modes : ModalBasis-like or array of shape (n_modes, n_valid)
        Modes (unit coefficient = 1 nm RMS).
    amplitude : float, default 10.0
        Push-pull amplitude [nm RMS]; small against lambda / (2 pi) for a linear response.
    offset_opd : array of shape (n_pix, n_pix), optional
        OPD [nm] around which to calibrate (e.g. a residual phase screen for optical gains).
    batch : int, default 16
        Modes per call to ``wfs.signals``.
    method : {"push-pull", "derivative"}
        ``"push-pull"``: ``(s(+a m) - s(-a m)) / (2 a)``, two frames per mode, error
        ``O(a^2)``. ``"derivative"``: the exact derivative of the signals (WFS with a
        ``signal_derivative`` method, e.g. :class:`PyramidWFS`), one propagation per mode;
        ``amplitude`` is then unused. They agree to ``O(a^2)`` (tested).

    Returns
    -------
    ndarray, shape (n_signals, n_modes)
        Signal per nm of modal coefficient.
    """
    modes, pupil = _modes_and_pupil(wfs, basis_or_modes)
    a = check_positive("amplitude", amplitude)
    check_int("batch", batch, minimum=1)
    if method not in ("push-pull", "derivative"):
        raise ValueError(f"method must be 'push-pull' or 'derivative', got {method!r}")
    if method == "derivative" and not hasattr(wfs, "signal_derivative"):
        raise ValueError(
            f"method='derivative' needs a WFS with signal_derivative, got {type(wfs).__name__}"
        )
    offset = 0.0
    if offset_opd is not None:
        offset = check_finite_array("offset_opd", offset_opd, ndim=2)
        if offset.shape != (pupil.n_pix, pupil.n_pix):
            raise ValueError(
                f"offset_opd must have shape ({pupil.n_pix}, {pupil.n_pix}), got {offset.shape}"
            )
    out = np.empty((wfs.n_signals, modes.shape[0]))
    if method == "derivative":
        base = np.zeros((pupil.n_pix, pupil.n_pix)) + offset
        for i0 in range(0, modes.shape[0], batch):
            maps = pupil.to_map(modes[i0 : i0 + batch])
            out[:, i0 : i0 + maps.shape[0]] = wfs.signal_derivative(base, maps).T
        return out
    for i0 in range(0, modes.shape[0], batch):
        maps = pupil.to_map(a * modes[i0 : i0 + batch])
        s = wfs.signals(np.concatenate([offset + maps, offset - maps]))
        k = maps.shape[0]
        out[:, i0 : i0 + k] = ((s[:k] - s[k:]) / (2 * a)).T
    return out


def reconstructor(
    imat: np.ndarray, *, n_modes: int | None = None, max_condition: float | None = None
) -> np.ndarray:
    """Truncated pseudo-inverse of an interaction matrix (signals -> modes).

    Parameters
    ----------
    imat : array, shape (n_signals, n_modes_cal)
    n_modes : int, optional
        Use only the first ``n_modes`` calibrated modes (default all).
    max_condition : float, optional
        Discard singular values below ``s_max / max_condition`` (default: keep all).

    Returns
    -------
    ndarray, shape (n_modes, n_signals)
        ``R`` with ``R @ imat[:, :n_modes] = I`` when nothing is discarded.
    """
    d = check_finite_array("imat", imat, ndim=2)
    if n_modes is not None:
        n_modes = check_int("n_modes", n_modes, minimum=1)
        if n_modes > d.shape[1]:
            raise ValueError(f"n_modes must be <= {d.shape[1]} calibrated modes, got {n_modes}")
        d = d[:, :n_modes]
    u, s, vt = np.linalg.svd(d, full_matrices=False)
    keep = s > 0
    if max_condition is not None:
        keep &= s >= s[0] / check_positive("max_condition", max_condition)
    n_cut = int(np.count_nonzero(~keep))
    if n_cut:
        logger.info("reconstructor: %d of %d singular values discarded", n_cut, s.size)
    inv = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    return (vt.T * inv) @ u.T


def noise_propagation(
    wfs: Any, recon: np.ndarray, frame: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-mode noise coefficients from photon and read noise on the detector pixels.

    Parameters
    ----------
    wfs : PyramidWFS or diffractive ShackHartmannWFS
        Needs ``reference_frame``, ``pixel_values`` and ``pixel_jacobian_product``.
    recon : array, shape (n_modes, n_signals)
    frame : array, optional
        Noise-free detector frame (fraction of the flux per pixel) around which to linearise;
        default the flat-wavefront reference.

    Returns
    -------
    photon_coeff : ndarray, shape (n_modes,)
        ``sum_j (R J)_ij^2 f_j`` [nm^2 e-]: photon-noise variance is ``photon_coeff / N``.
    read_coeff : ndarray, shape (n_modes,)
        ``sum_j (R J)_ij^2`` [nm^2 e-^2]: read-noise variance is
        ``read_coeff * sigma_ro^2 / N^2``.

    Here ``J`` is the Jacobian of the signals w.r.t. the pixels at unit total flux, ``f`` the
    pixel fluxes (fraction of ``N``) and ``N`` the photo-electrons per frame.
    """
    f = wfs.reference_frame if frame is None else np.asarray(frame, dtype=float)
    rj = wfs.pixel_jacobian_product(f, recon)
    p = wfs.pixel_values(f)
    rj2 = rj**2
    return rj2 @ p, rj2.sum(axis=1)


def white_noise_propagation(recon: np.ndarray) -> np.ndarray:
    """Per-mode noise variance for unit white, uncorrelated signal noise: ``diag(R R^T)``.

    Parameters
    ----------
    recon : array, shape (n_modes, n_signals)

    Returns
    -------
    ndarray, shape (n_modes,)
        Modal variance [nm^2] per unit signal variance; multiply by the signal noise variance
        (e.g. a centroid-noise model for the geometric Shack-Hartmann).
    """
    r = check_finite_array("recon", recon, ndim=2)
    return np.einsum("ij,ij->i", r, r)


def fitting_residual_screens(
    pupil: Pupil,
    rms: float,
    n_screens: int,
    rng: np.random.Generator,
    *,
    cutoff_frequency: float,
    L0: float = 25.0,
) -> np.ndarray:
    """Random residual phase screens with a fitting-error-like spectrum.

    Von Kármán spectrum high-passed above ``cutoff_frequency`` (the DM's correction radius,
    ``n_act / (2 D)``), each screen scaled to exactly ``rms`` over the pupil with its piston
    removed: the uncorrectable part of an AO residual, which sets the pyramid's optical gains.

    Parameters
    ----------
    pupil : Pupil
    rms : float
        OPD RMS over the pupil [nm], >= 0.
    n_screens : int
    rng : numpy.random.Generator
    cutoff_frequency : float
        [cycles/m], > 0.
    L0 : float, default 25.0
        Outer scale [m].

    Returns
    -------
    ndarray, shape (n_screens, n_pix, n_pix)
        OPD [nm], 0 outside the pupil.
    """
    rms = check_nonnegative("rms", rms)
    n = check_int("n_screens", n_screens, minimum=1)
    fc = check_positive("cutoff_frequency", cutoff_frequency)
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    big = 2 * pupil.n_pix
    k = np.fft.fftfreq(big, d=pupil.pixel_scale)
    kappa = np.hypot(k[:, None], k[None, :])
    amp = np.sqrt(von_karman_psd(np.where(kappa > 0, kappa, 1.0), r0=0.1, L0=L0))
    amp = np.where(kappa > fc, amp, 0.0)
    noise = rng.standard_normal((n, big, big)) + 1j * rng.standard_normal((n, big, big))
    screens = np.fft.ifft2(noise * amp).real[:, : pupil.n_pix, : pupil.n_pix]
    vec = pupil.to_vector(screens)
    vec -= vec.mean(axis=-1, keepdims=True)
    norm = np.sqrt(np.mean(vec**2, axis=-1, keepdims=True))
    return pupil.to_map(vec * (rms / norm))


def optical_gains(
    wfs: Any,
    basis_or_modes: Any,
    residual_opd: np.ndarray,
    *,
    amplitude: float = 10.0,
    recon: np.ndarray | None = None,
    method: str = "push-pull",
) -> np.ndarray:
    """Per-mode optical gains around residual phase screens.

    Parameters
    ----------
    wfs, basis_or_modes
        As for :func:`interaction_matrix`.
    residual_opd : array, shape (n_pix, n_pix) or (n_screens, n_pix, n_pix)
        Residual OPD [nm] (e.g. :func:`fitting_residual_screens` or closed-loop residuals).
        For a target Strehl ratio ``S`` at the WFS wavelength ``lambda``, Maréchal's
        approximation gives the RMS ``lambda / (2 pi) sqrt(-ln S)``.
    amplitude : float, default 10.0
        Push-pull amplitude [nm RMS].
    recon : array, shape (n_modes, n_signals), optional
        Diffraction-limited reconstructor; computed from a flat calibration if omitted.
    method : {"push-pull", "derivative"}
        How the interaction matrices are measured (:func:`interaction_matrix`).

    Returns
    -------
    ndarray, shape (n_modes,)
        ``diag(R D_res)`` averaged over the screens (1 for a flat wavefront).
    """
    res = check_finite_array("residual_opd", residual_opd, ndim=(2, 3))
    if res.ndim == 2:
        res = res[None]
    if recon is None:
        recon = reconstructor(interaction_matrix(wfs, basis_or_modes, amplitude, method=method))
    n_modes = recon.shape[0]
    gains = np.zeros(n_modes)
    for screen in res:
        d = interaction_matrix(wfs, basis_or_modes, amplitude, offset_opd=screen, method=method)[
            :, :n_modes
        ]
        gains += np.einsum("ij,ji->i", recon, d)
    return gains / res.shape[0]


@dataclass(frozen=True, eq=False)
class WFSCalibration:
    """Result of :func:`calibrate`: interaction matrix, reconstructor, noise coefficients.

    Attributes
    ----------
    imat : ndarray, shape (n_signals, n_modes)
        Signals per nm of modal coefficient.
    recon : ndarray, shape (n_modes, n_signals)
        Reconstructor [nm per signal unit].
    photon_coeff, read_coeff : ndarray, shape (n_modes,)
        See :func:`noise_propagation`; None for a WFS without a pixel model.
    amplitude : float
        Push-pull amplitude used [nm RMS].
    norm_pixels : int
        Pixels summed in one flux normalisation (all valid pixels for the pyramid's global
        normalisation, one subaperture for the Shack-Hartmann); 0 disables the correction.
    norm_fraction : float
        Fraction of the frame's flux in one normalisation sum.
    """

    imat: np.ndarray
    recon: np.ndarray
    photon_coeff: np.ndarray | None
    read_coeff: np.ndarray | None
    amplitude: float = 10.0
    norm_pixels: int = 0
    norm_fraction: float = 1.0

    @property
    def n_modes(self) -> int:
        return int(self.recon.shape[0])

    def noise_variance(self, photons: float, read_noise: float) -> np.ndarray:
        """Per-mode measurement noise variance [nm^2], shape (n_modes,).

        ``(c_ph / N + c_ro sigma^2 / N^2) (1 + 3 cv^2)``: the linearised propagation times the
        second-order (delta-method) correction for the noisy flux normalisation,
        ``E[1/T^2] = (1 + 3 cv^2) / E[T]^2`` with ``cv^2 = (f N + n_pix sigma^2) / (f N)^2``
        the relative variance of the normalising flux ``T`` (``f = norm_fraction``,
        ``n_pix = norm_pixels``). It matters only at very low flux (a few per cent when the
        normalising flux has an SNR ~ 10) and assumes ``cv << 1``.

        Parameters
        ----------
        photons : float
            Photo-electrons per frame on the WFS (> 0).
        read_noise : float
            Read-out noise [e- RMS per pixel] (>= 0).
        """
        n = check_positive("photons", photons)
        r = check_nonnegative("read_noise", read_noise)
        if self.photon_coeff is None:
            raise ValueError("this calibration has no pixel noise model (geometric WFS)")
        var = self.photon_coeff / n + self.read_coeff * r**2 / n**2
        if self.norm_pixels:
            t = self.norm_fraction * n
            var = var * (1.0 + 3.0 * (t + self.norm_pixels * r**2) / t**2)
        return var


def calibrate(
    wfs: Any,
    basis_or_modes: Any,
    amplitude: float = 10.0,
    *,
    n_modes: int | None = None,
    max_condition: float | None = None,
    batch: int = 16,
    method: str = "push-pull",
) -> WFSCalibration:
    """Interaction matrix, reconstructor and noise coefficients of ``wfs`` on a basis.

    ``method`` as for :func:`interaction_matrix`.

    Noise coefficients are computed when the WFS has a pixel model (pyramid, diffractive
    Shack-Hartmann), linearised around the flat-wavefront frame.

    Parameters
    ----------
    wfs : PyramidWFS or ShackHartmannWFS
    basis_or_modes : ModalBasis-like or ndarray (n_modes, n_valid)
        Modes to calibrate (unit coefficient = 1 nm RMS).
    amplitude : float
        Push-pull amplitude [nm RMS].
    n_modes, max_condition : optional
        Truncation of the reconstructor (see :func:`reconstructor`).
    batch : int
        Modes per call to the WFS model.
    method : {"push-pull", "derivative"}
    """
    d = interaction_matrix(wfs, basis_or_modes, amplitude, batch=batch, method=method)
    r = reconstructor(d, n_modes=n_modes, max_condition=max_condition)
    ph = ro = None
    n_norm, f_norm = 0, 1.0
    if hasattr(wfs, "pixel_jacobian_product") and getattr(wfs, "model", "") != "geometric":
        ph, ro = noise_propagation(wfs, r)
        n_norm, f_norm = wfs.normalisation
    return WFSCalibration(
        imat=d,
        recon=r,
        photon_coeff=ph,
        read_coeff=ro,
        amplitude=float(amplitude),
        norm_pixels=n_norm,
        norm_fraction=f_norm,
    )


@dataclass(frozen=True, eq=False)
class LinearModalSensor:
    """The linear modal WFS of the fast loop: ``measurement = optical_gain * residual + noise``.

    The one linear modal sensor class of the project (``LinearModalWFS`` is the same class):
    the simulator's stages take it directly, and :meth:`from_diffractive` /
    :meth:`from_calibration` derive it from a diffractive WFS model. It implements the sensor
    protocol of :mod:`aocontrol.sim.loop` (``measure(residual, rng)``, ``senses_phase``
    False: it senses modal coefficients, not phase maps).

    Parameters
    ----------
    optical_gain : float or array_like, shape (n_modes,)
        Per-mode optical gain (dimensionless, finite and > 0; 1 = diffraction-limited
        calibration). A scalar applies to every mode.
    noise_std : float or array_like, shape (n_modes,)
        Per-mode measurement noise standard deviation [nm RMS] (finite, >= 0), white,
        independent between modes and frames. A scalar applies to every mode.
    calibration : WFSCalibration, optional
        The calibration it was derived from (kept for reference, not compared).

    Raises
    ------
    ValueError
        If a value is not finite, an optical gain is <= 0, a noise level < 0, or both
        arguments are arrays of different lengths.

    Notes
    -----
    The modal noise of a real WFS is slightly correlated between modes; this model keeps its
    per-mode variance only.

    Examples
    --------
    >>> wfs = LinearModalSensor(optical_gain=[1.0, 0.5], noise_std=[0.0, 0.0])
    >>> wfs.measure(np.array([2.0, 2.0]), np.random.default_rng(0))
    array([2., 1.])
    """

    optical_gain: Any = 1.0
    noise_std: Any = 0.0
    calibration: WFSCalibration | None = field(default=None, repr=False, compare=False)

    #: Sensor protocol: this sensor measures modal residuals, not phase maps.
    senses_phase: ClassVar[bool] = False

    def __post_init__(self) -> None:
        g = check_finite_array("optical_gain", self.optical_gain, ndim=(0, 1)).copy()
        s = check_finite_array("noise_std", self.noise_std, ndim=(0, 1)).copy()
        if g.ndim == 1 and s.ndim == 1 and g.shape != s.shape:
            raise ValueError(
                f"optical_gain and noise_std must have the same shape (n_modes,), "
                f"got {g.shape} and {s.shape}"
            )
        if g.size == 0 or s.size == 0:
            raise ValueError("optical_gain and noise_std must not be empty")
        if np.any(g <= 0):
            raise ValueError(
                f"optical_gain must be finite and > 0 for every mode, found min {g.min()!r}"
            )
        if np.any(s < 0):
            raise ValueError(f"noise_std must be >= 0 [nm], found min {s.min()!r}")
        g.setflags(write=False)
        s.setflags(write=False)
        object.__setattr__(self, "optical_gain", g)
        object.__setattr__(self, "noise_std", s)

    @property
    def n_modes(self) -> int | None:
        """Number of modes, or ``None`` when both parameters are scalars (any count)."""
        sizes = {a.size for a in (self.optical_gain, self.noise_std) if a.ndim == 1}
        return sizes.pop() if sizes else None

    def arrays(self, n_modes: int) -> tuple[np.ndarray, np.ndarray]:
        """Optical gains and noise levels broadcast to ``n_modes``.

        Parameters
        ----------
        n_modes : int
            Modes of the stage using the sensor.

        Returns
        -------
        optical_gain, noise_std : ndarray, shape (n_modes,)
            Dimensionless gains and noise standard deviations [nm].

        Raises
        ------
        ValueError
            If the sensor has a different number of modes.
        """
        n_modes = check_int("n_modes", n_modes, minimum=1)
        if self.n_modes is not None and self.n_modes != n_modes:
            raise ValueError(f"the sensor has {self.n_modes} modes, the controller has {n_modes}")
        og = np.broadcast_to(self.optical_gain, (n_modes,))
        ns = np.broadcast_to(self.noise_std, (n_modes,))
        return og, ns

    def measure(self, residual: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Modal measurements [nm] of residual coefficients.

        Parameters
        ----------
        residual : array_like, shape (n_modes,) or (n_frames, n_modes)
            Residual modal coefficients [nm RMS].
        rng : numpy.random.Generator
            Source of the measurement noise.

        Returns
        -------
        ndarray, same shape as ``residual``
            ``optical_gain * residual + noise_std * N(0, 1)`` [nm].
        """
        x = np.asarray(residual, dtype=float)
        n = self.n_modes
        if x.ndim not in (1, 2) or (n is not None and x.shape[-1] != n):
            raise ValueError(
                f"residual must have shape (n_modes,) or (n_frames, n_modes) with "
                f"n_modes={n}, got {x.shape}"
            )
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        return self.optical_gain * x + self.noise_std * rng.standard_normal(x.shape)

    @classmethod
    def from_calibration(
        cls,
        calibration: WFSCalibration,
        photons_per_frame: float,
        read_noise: float,
        optical_gain: np.ndarray | None = None,
    ) -> LinearModalSensor:
        """Linear model from a :class:`WFSCalibration` at a given flux and read noise.

        ``photons_per_frame`` [e-] and ``read_noise`` [e- RMS per pixel] as for
        :meth:`WFSCalibration.noise_variance`; ``optical_gain`` defaults to 1 for every mode.
        """
        var = calibration.noise_variance(photons_per_frame, read_noise)
        g = np.ones(calibration.n_modes) if optical_gain is None else optical_gain
        return cls(optical_gain=g, noise_std=np.sqrt(var), calibration=calibration)

    @classmethod
    def from_diffractive(
        cls,
        wfs: Any,
        basis_or_modes: Any,
        photons_per_frame: float,
        read_noise: float,
        *,
        amplitude: float = 10.0,
        residual_opd: np.ndarray | None = None,
        n_modes: int | None = None,
        max_condition: float | None = None,
    ) -> LinearModalSensor:
        """Calibrate a diffractive WFS and return the equivalent linear modal model.

        Parameters
        ----------
        wfs : PyramidWFS or diffractive ShackHartmannWFS
        basis_or_modes : ModalBasis-like or array (n_modes, n_valid)
        photons_per_frame : float
            Photo-electrons per frame (e.g. :func:`aocontrol.sim.noise.photons_per_frame`).
        read_noise : float
            [e- RMS per pixel].
        amplitude : float
            Push-pull amplitude [nm RMS].
        residual_opd : array (n_screens, n_pix, n_pix), optional
            Residual screens for the optical gains (default: gains of 1).
        n_modes, max_condition
            Passed to :func:`reconstructor`.
        """
        cal = calibrate(
            wfs, basis_or_modes, amplitude, n_modes=n_modes, max_condition=max_condition
        )
        gains = None
        if residual_opd is not None:
            gains = optical_gains(
                wfs, basis_or_modes, residual_opd, amplitude=amplitude, recon=cal.recon
            )
        return cls.from_calibration(cal, photons_per_frame, read_noise, optical_gain=gains)


#: The same class under the name used by the WFS calibration code.
LinearModalWFS = LinearModalSensor
