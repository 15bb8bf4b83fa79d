"""WFS calibration: interaction matrix, reconstructor, optical gains, noise propagation.

(The linear modal sensor of the fast loop is :class:`aocontrol.sim.wfs.LinearModalSensor`, in
:mod:`aocontrol.sim.wfs.sensors`.)

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
from dataclasses import dataclass
from typing import Any

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
