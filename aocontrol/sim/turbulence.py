"""Von Kármán turbulence theory: spatial PSD, covariance, structure function, r0, tau0.

Phases are in radians at the reference wavelength 500 nm, where ``r0`` is defined; the
optical path (nm, wavelength independent) is ``phase * 500 / (2 pi)``. Spatial frequencies
``kappa`` are in cycles/m.

References: Roddier (1981), "The effects of atmospheric turbulence in optical astronomy";
Conan (2000), "Modélisation des effets de l'échelle externe de cohérence spatiale du front
d'onde" (closed-form von Kármán covariance); Sasiela (2007).
"""

from __future__ import annotations

import numpy as np
from scipy import special

from aocontrol._validation import check_finite_array, check_positive

__all__ = [
    "REFERENCE_WAVELENGTH",
    "ARCSEC",
    "r0_from_seeing",
    "seeing_from_r0",
    "r0_at_wavelength",
    "opd_per_radian",
    "von_karman_psd",
    "phase_covariance",
    "phase_variance",
    "structure_function",
    "effective_wind_speed",
    "tau0",
]

#: Wavelength at which r0 and seeing are quoted [m].
REFERENCE_WAVELENGTH = 500e-9
#: One arcsecond [rad].
ARCSEC = np.pi / (180.0 * 3600.0)

# 0.023 = (24/5 Gamma(6/5))^(5/6) Gamma(11/6)^2 / (2 pi^(11/3)) to the precision usually quoted.
_PSD_COEFF = (24.0 / 5.0 * special.gamma(6.0 / 5.0)) ** (5.0 / 6.0) * (
    special.gamma(11.0 / 6.0) ** 2 / (2.0 * np.pi ** (11.0 / 3.0))
)
# Covariance prefactor: B(r) = _COV_COEFF (L0/r0)^(5/3) x^(5/6) K_{5/6}(x), x = 2 pi r / L0.
_COV_COEFF = (
    special.gamma(11.0 / 6.0)
    / (2.0 ** (5.0 / 6.0) * np.pi ** (8.0 / 3.0))
    * (24.0 / 5.0 * special.gamma(6.0 / 5.0)) ** (5.0 / 6.0)
)


def r0_from_seeing(seeing_arcsec: float, wavelength: float = REFERENCE_WAVELENGTH) -> float:
    """Fried parameter [m] at ``wavelength`` from the seeing FWHM [arcsec] quoted there.

    ``r0 = 0.98 lambda / seeing``. For 1" at 500 nm, r0 = 0.101 m.

    Parameters
    ----------
    seeing_arcsec : float
        Seeing FWHM [arcsec] at ``wavelength``, > 0.
    wavelength : float, default 500e-9
        Wavelength at which the seeing is quoted [m].
    """
    seeing = check_positive("seeing_arcsec", seeing_arcsec)
    wavelength = check_positive("wavelength", wavelength)
    return 0.98 * wavelength / (seeing * ARCSEC)


def seeing_from_r0(r0: float, wavelength: float = REFERENCE_WAVELENGTH) -> float:
    """Seeing FWHM [arcsec] from r0 [m] at ``wavelength``; inverse of :func:`r0_from_seeing`.

    Parameters
    ----------
    r0 : float
        Fried parameter at ``wavelength`` [m], > 0.
    wavelength : float, default 500e-9
        Wavelength of ``r0`` [m].
    """
    r0 = check_positive("r0", r0)
    return 0.98 * check_positive("wavelength", wavelength) / r0 / ARCSEC


def r0_at_wavelength(
    r0: float, wavelength: float, reference: float = REFERENCE_WAVELENGTH
) -> float:
    """Scale r0 [m] from ``reference`` to ``wavelength``: ``r0 (lambda/ref)^(6/5)``.

    Parameters
    ----------
    r0 : float
        Fried parameter at ``reference`` [m], > 0.
    wavelength : float
        Target wavelength [m].
    reference : float, default 500e-9
        Wavelength at which ``r0`` is given [m].
    """
    return (
        check_positive("r0", r0)
        * (check_positive("wavelength", wavelength) / check_positive("reference", reference)) ** 1.2
    )


def opd_per_radian(wavelength: float = REFERENCE_WAVELENGTH) -> float:
    """Optical path [nm] of one radian of phase at ``wavelength`` [m].

    Parameters
    ----------
    wavelength : float, default 500e-9
        Wavelength [m].
    """
    return check_positive("wavelength", wavelength) * 1e9 / (2.0 * np.pi)


def von_karman_psd(kappa: object, r0: float, L0: float = 25.0) -> np.ndarray:
    """Von Kármán phase PSD [rad^2 m^2] at spatial frequency ``kappa`` [cycles/m].

    ``0.023 r0^(-5/3) (kappa^2 + 1/L0^2)^(-11/6)`` (phase at 500 nm).

    Parameters
    ----------
    kappa : array_like
        Spatial frequencies [cycles/m].
    r0 : float
        Fried parameter at 500 nm [m].
    L0 : float, default 25.0
        Outer scale [m].
    """
    r0 = check_positive("r0", r0)
    L0 = check_positive("L0", L0)
    k = check_finite_array("kappa", kappa)
    return _PSD_COEFF * r0 ** (-5.0 / 3.0) * (k**2 + 1.0 / L0**2) ** (-11.0 / 6.0)


def phase_covariance(r: object, r0: float, L0: float = 25.0) -> np.ndarray:
    """Von Kármán phase covariance [rad^2] at separation ``r`` [m] (phase at 500 nm).

    ``B(r) = c (L0/r0)^(5/3) x^(5/6) K_{5/6}(x)``, ``x = 2 pi r / L0``; the limit at r = 0 is
    the phase variance (:func:`phase_variance`).

    Parameters
    ----------
    r : array_like
        Separations [m] (absolute value taken).
    r0 : float
        Fried parameter at 500 nm [m].
    L0 : float, default 25.0
        Outer scale [m].
    """
    r0 = check_positive("r0", r0)
    L0 = check_positive("L0", L0)
    r = np.abs(check_finite_array("r", r))
    x = 2.0 * np.pi * r / L0
    out = np.empty_like(x)
    small = x < 1e-10
    xs = x[~small]
    out[~small] = xs ** (5.0 / 6.0) * special.kv(5.0 / 6.0, xs)
    # x^(5/6) K_{5/6}(x) -> 2^(-1/6) Gamma(5/6) as x -> 0.
    out[small] = 2.0 ** (-1.0 / 6.0) * special.gamma(5.0 / 6.0)
    return _COV_COEFF * (L0 / r0) ** (5.0 / 3.0) * out


def phase_variance(r0: float, L0: float = 25.0) -> float:
    """Total von Kármán phase variance [rad^2] at 500 nm: about ``0.0863 (L0/r0)^(5/3)``.

    Parameters
    ----------
    r0 : float
        Fried parameter at 500 nm [m].
    L0 : float, default 25.0
        Outer scale [m].
    """
    return float(phase_covariance(0.0, r0, L0))


def structure_function(r: object, r0: float, L0: float = 25.0) -> np.ndarray:
    """Phase structure function [rad^2]: ``2 (B(0) - B(r))``.

    Tends to the Kolmogorov ``6.88 (r/r0)^(5/3)`` for ``r << L0``.

    Parameters
    ----------
    r : array_like
        Separations [m].
    r0 : float
        Fried parameter at 500 nm [m].
    L0 : float, default 25.0
        Outer scale [m].
    """
    r = check_finite_array("r", r)
    return 2.0 * (phase_variance(r0, L0) - phase_covariance(r, r0, L0))


def effective_wind_speed(speeds: object, weights: object) -> float:
    """The 5/3-weighted mean wind speed ``(sum w_i v_i^(5/3) / sum w_i)^(3/5)`` [m/s].

    Parameters
    ----------
    speeds : array_like, shape (n_layers,)
        Wind speeds [m/s] (absolute values taken).
    weights : array_like, shape (n_layers,)
        Cn2 weights of the layers, >= 0, not all zero.
    """
    v = np.abs(check_finite_array("speeds", speeds, ndim=1))
    w = check_finite_array("weights", weights, ndim=1)
    if v.shape != w.shape or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be >= 0, not all zero, with the shape of speeds")
    return float((np.sum(w * v ** (5.0 / 3.0)) / w.sum()) ** 0.6)


def tau0(r0: float, speeds: object, weights: object) -> float:
    """Coherence time [s]: ``0.314 r0 / v_bar`` with the 5/3-weighted mean wind speed.

    Parameters
    ----------
    r0 : float
        Fried parameter at 500 nm [m].
    speeds : array_like, shape (n_layers,)
        Wind speeds [m/s].
    weights : array_like, shape (n_layers,)
        Cn2 fractions of the layers.
    """
    return 0.314 * check_positive("r0", r0) / effective_wind_speed(speeds, weights)
