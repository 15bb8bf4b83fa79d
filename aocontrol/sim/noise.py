"""Photon budget and detector noise for the wavefront sensors.

Photon flux from a guide-star magnitude (Vega system), Poisson photon noise and Gaussian
read-out noise on detector pixel intensities, and the SNR of the SAXO+ paper (section
"Noise"). Photon counts are photo-electrons: the quantum efficiency belongs in ``throughput``.

Band zero points (flux of a magnitude-0 star above the atmosphere, photons s^-1 m^-2 over the
band) are computed as ``F_lambda * bandwidth / (h c / lambda_eff)`` from the sources cited in
:data:`BANDS`; they are broad-band approximations (a flat spectrum across the band), good to a
few per cent for the photon budget of a wavefront sensor.

Randomness only through a passed :class:`numpy.random.Generator`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from aocontrol._validation import (
    check_finite_array,
    check_in_range,
    check_int,
    check_nonnegative,
    check_positive,
)

__all__ = [
    "Band",
    "BANDS",
    "STAGE1_READ_NOISE",
    "STAGE2_READ_NOISE",
    "STAGE1_THROUGHPUT",
    "STAGE2_THROUGHPUT",
    "band_zero_point",
    "photons_per_frame",
    "add_detector_noise",
    "snr",
]

logger = logging.getLogger(__name__)

_H = 6.62607015e-34  # Planck constant [J s] (exact, SI 2019)
_C = 299792458.0  # speed of light [m/s] (exact)

#: Read-out noise of the stage-1 (SAXO, EMCCD Shack-Hartmann) detector [e- RMS per pixel per
#: frame], published setting of the SAXO+ study (DESIGN.md).
STAGE1_READ_NOISE = 0.1
#: Read-out noise of the stage-2 (SAXO+, near-infrared e-APD pyramid) detector [e- RMS per
#: pixel per frame], published setting of the SAXO+ study (DESIGN.md).
STAGE2_READ_NOISE = 0.3
#: Sky-to-detector efficiency of stage 1 (telescope, SPHERE common path, visible WFS arm and
#: detector QE). ASSUMPTION: a round value of the order of the SPHERE/SAXO budgets; the paper
#: does not give it. Case files should override it when the consortium value is known.
STAGE1_THROUGHPUT = 0.15
#: Sky-to-detector efficiency of stage 2 (telescope, SPHERE, dichroic to the near-infrared
#: pyramid arm and e-APD QE). ASSUMPTION as for :data:`STAGE1_THROUGHPUT`.
STAGE2_THROUGHPUT = 0.25


@dataclass(frozen=True)
class Band:
    """Photometric band of the Vega system.

    Parameters
    ----------
    name : str
        Band name, e.g. ``"J"``.
    wavelength : float
        Effective (isophotal) wavelength [m].
    bandwidth : float
        Effective width [m].
    zero_point : float
        Photon flux of a magnitude-0 star above the atmosphere integrated over the band
        [photons s^-1 m^-2].
    source : str
        Where the numbers come from.
    """

    name: str
    wavelength: float
    bandwidth: float
    zero_point: float
    source: str


def _from_flambda(
    name: str, wavelength_um: float, bandwidth_um: float, flambda_si: float, source: str
) -> Band:
    """Band from F_lambda [W m^-2 m^-1] at ``wavelength_um`` over ``bandwidth_um`` [um]."""
    lam = wavelength_um * 1e-6
    photons = flambda_si * bandwidth_um * 1e-6 / (_H * _C / lam)
    return Band(name, lam, bandwidth_um * 1e-6, photons, source)


# Unit conversions: 1 erg s^-1 cm^-2 A^-1 = 1e7 W m^-2 m^-1; 1 W cm^-2 um^-1 = 1e10 W m^-2 m^-1.
_BESSELL = (
    "Bessell, Castelli & Plez (1998) A&A 333, 231, table A2 (F_lambda, lambda_eff); "
    "widths: Bessell (1990) PASP 102, 1181"
)
_COHEN = (
    "2MASS: Cohen, Wheaton & Megeath (2003) AJ 126, 1090, table 2 "
    "(isophotal lambda, F_lambda, bandwidth)"
)

#: Supported bands. Johnson-Cousins U B V R I from Bessell et al. (1998) [F_lambda in
#: 1e-11 erg s^-1 cm^-2 A^-1]; near-infrared J H K from the 2MASS calibration of Cohen et al.
#: (2003) [F_lambda in W cm^-2 um^-1]; Gaia G from the Gaia DR3 documentation (see below).
BANDS: dict[str, Band] = {
    "U": _from_flambda("U", 0.366, 0.066, 417.5e-11 * 1e7, _BESSELL),
    "B": _from_flambda("B", 0.438, 0.094, 632.0e-11 * 1e7, _BESSELL),
    "V": _from_flambda("V", 0.545, 0.088, 363.1e-11 * 1e7, _BESSELL),
    "R": _from_flambda("R", 0.641, 0.138, 217.7e-11 * 1e7, _BESSELL),
    "I": _from_flambda("I", 0.798, 0.149, 112.6e-11 * 1e7, _BESSELL),
    "J": _from_flambda("J", 1.235, 0.162, 3.129e-13 * 1e10, _COHEN),
    "H": _from_flambda("H", 1.662, 0.251, 1.133e-13 * 1e10, _COHEN),
    "K": _from_flambda("K", 2.159, 0.262, 4.283e-14 * 1e10, _COHEN),
    # Gaia G: Gaia (E)DR3 documentation, photometric zero point on the Vega scale
    # ZP_G = 25.6874 mag for fluxes in e-/s through Gaia's telescope pupil of 0.7278 m^2
    # (Riello et al. 2021, A&A 649, A3). 10**(0.4 * 25.6874) / 0.7278 = 2.59e10 e- s^-1 m^-2
    # for G = 0: detected photo-electrons, i.e. the Gaia instrument response (optics and CCD
    # QE, mean ~0.6 over the band) is folded in; `throughput` for G is then relative to Gaia's.
    # Effective wavelength 0.673 um and width 0.44 um from Jordi et al. (2010) A&A 523, A48.
    "G": Band(
        "G",
        0.673e-6,
        0.44e-6,
        10 ** (0.4 * 25.6874) / 0.7278,
        "Gaia DR3 documentation (Riello et al. 2021) ZP_G=25.6874 Vega; Jordi et al. 2010",
    ),
}
BANDS["Ks"] = BANDS["K"]


def band_zero_point(band: str) -> Band:
    """Return the :class:`Band` named ``band`` (case-sensitive names of :data:`BANDS`).

    Parameters
    ----------
    band : str
        Photometric band name, a key of :data:`BANDS` (e.g. ``"G"``, ``"J"``).

    Raises
    ------
    ValueError
        Unknown band name.
    """
    if not isinstance(band, str) or band not in BANDS:
        raise ValueError(f"band must be one of {sorted(BANDS)}, got {band!r}")
    return BANDS[band]


def photons_per_frame(
    magnitude: float,
    band: str,
    *,
    fs: float | None = None,
    frame_time: float | None = None,
    diameter: float = 8.0,
    obstruction: float = 0.14,
    area: float | None = None,
    throughput: float = 1.0,
    bandwidth: float | None = None,
) -> float:
    """Photo-electrons detected per frame from a star of Vega ``magnitude`` in ``band``.

    ``N = zero_point * 10**(-0.4 magnitude) * area * throughput * frame_time`` (with the
    zero point rescaled by ``bandwidth / band.bandwidth`` if a WFS bandwidth is given).

    Parameters
    ----------
    magnitude : float
        Vega magnitude in ``band`` (any sign).
    band : str
        One of :data:`BANDS` ("G" for stage 1, "J" for stage 2).
    fs : float, optional
        Frame rate [Hz]; give exactly one of ``fs`` and ``frame_time``.
    frame_time : float, optional
        Integration time per frame [s].
    diameter : float, default 8.0
        Telescope diameter [m] (VLT); ignored when ``area`` is given.
    obstruction : float, default 0.14
        Central obstruction (fraction of the diameter); ignored when ``area`` is given.
    area : float, optional
        Collecting area [m^2].
    throughput : float, default 1.0
        Sky-to-detector efficiency including QE, in (0, 1]; e.g. :data:`STAGE2_THROUGHPUT`.
    bandwidth : float, optional
        Width of the WFS spectral band [m] if it differs from the photometric band.

    Returns
    -------
    float
        Expected photo-electrons per frame over the whole pupil.

    Raises
    ------
    ValueError
        Non-positive rate, time, area, throughput or bandwidth; both or neither of ``fs`` and
        ``frame_time``; unknown band.

    Examples
    --------
    >>> n = photons_per_frame(0.0, "J", fs=1000.0, area=1.0)
    >>> round(n / 1e6, 2)  # 3.15e9 photons/s/m^2 for J = 0 (2MASS)
    3.15
    """
    if isinstance(magnitude, bool) or not isinstance(
        magnitude, (int, float, np.floating, np.integer)
    ):
        raise TypeError(f"magnitude must be a real number, got {magnitude!r}")
    if not math.isfinite(float(magnitude)):
        raise ValueError(f"magnitude must be finite, got {magnitude!r}")
    b = band_zero_point(band)
    if (fs is None) == (frame_time is None):
        raise ValueError(
            f"give exactly one of fs and frame_time, got fs={fs!r}, frame_time={frame_time!r}"
        )
    t = (
        1.0 / check_positive("fs", fs)
        if fs is not None
        else check_positive("frame_time", frame_time)
    )
    if area is None:
        d = check_positive("diameter", diameter)
        eps = check_in_range("obstruction", obstruction, 0.0, 1.0)
        area = math.pi * d**2 / 4.0 * (1.0 - eps**2)
    else:
        area = check_positive("area", area)
    throughput = check_in_range(
        "throughput", throughput, 0.0, 1.0, low_inclusive=False, high_inclusive=True
    )
    scale = 1.0
    if bandwidth is not None:
        scale = check_positive("bandwidth", bandwidth) / b.bandwidth
    return float(b.zero_point * scale * 10 ** (-0.4 * float(magnitude)) * area * throughput * t)


def add_detector_noise(
    intensity: np.ndarray,
    read_noise: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Noisy detector frame: Poisson photon noise plus Gaussian read-out noise.

    Parameters
    ----------
    intensity : array_like, any shape
        Expected photo-electrons per pixel (>= 0).
    read_noise : float
        Read-out noise [e- RMS per pixel per frame], >= 0.
    rng : numpy.random.Generator
        Source of randomness.

    Returns
    -------
    ndarray of float, same shape
        ``Poisson(intensity) + read_noise * N(0, 1)`` [e-]; no clipping, no quantisation.

    Raises
    ------
    ValueError
        Negative or non-finite intensities, negative read noise.
    TypeError
        ``rng`` not a numpy Generator.
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    arr = check_finite_array("intensity", intensity)
    if arr.size and arr.min() < 0:
        raise ValueError(f"intensity must be >= 0 (photo-electrons), found min {arr.min()!r}")
    sigma = check_nonnegative("read_noise", read_noise)
    out = rng.poisson(arr).astype(float)
    if sigma > 0:
        out += sigma * rng.standard_normal(arr.shape)
    return out


def snr(n_photons: float, read_noise: float, n_pixels: int = 4) -> float:
    """Signal-to-noise ratio of the SAXO+ paper, ``N_q / sqrt(N_q + n_pixels * N_r**2)``.

    The paper writes ``sigma_Nr^2 = 4 N_r^2``: the read noise of the 4 pixels of a quad-cell
    (4 pyramid pupils or a 2x2 Shack-Hartmann subaperture) per measurement; ``n_pixels``
    generalises it.

    Parameters
    ----------
    n_photons : float
        Incident photo-electrons per measurement per time step, ``N_q`` >= 0.
    read_noise : float
        Read-out noise ``N_r`` [e- RMS per pixel], >= 0.
    n_pixels : int, default 4
        Pixels read per measurement.

    Returns
    -------
    float
        SNR (0 when there is no photon).

    Examples
    --------
    >>> snr(100.0, 0.0)
    10.0
    """
    n = check_nonnegative("n_photons", n_photons)
    r = check_nonnegative("read_noise", read_noise)
    k = check_int("n_pixels", n_pixels, minimum=1)
    var = n + k * r**2
    return 0.0 if var == 0 else n / math.sqrt(var)
