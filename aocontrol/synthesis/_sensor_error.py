"""The sensor's error beyond its linear response, and the residual it costs a loop.

A wavefront sensor read by a reconstructor (a pyramid above all) measures

    m = og z^-1 e + v

with ``e`` the modal residual, ``og`` the optical gains (1 once compensated) and ``v`` the
sensor's error beyond its linear response: aliasing of the residual outside the modal basis
(the fitting error), the non-linearity around the loop's residual, photon and read noise.
Only the last is white. With the pseudo-open loop ``pol = m / og + G u = z^-1 d + v / og`` of
the telemetry (:func:`aocontrol.synthesis.pseudo_open_loop`) and ``u = K m``, the identity
``m = S og pol`` gives the residual of any linear controller exactly:

    z^-1 e = S pol - v / og,    P_e = |S|^2 (P_pol - P_v) + |T|^2 P_v   (v, d uncorrelated)

where ``S = 1 / (1 + og G K)``, ``T = 1 - S``: the sensor's error enters through ``T`` (the loop
re-injects it), the disturbance through ``S``. The telemetry alone estimates ``P_pol``, and
:func:`aocontrol.synthesis.disturbance_from_telemetry` splits it into a disturbance and a
white floor; a coloured ``v`` (the aliasing follows the turbulence's temporal spectrum) is
then counted as disturbance, weighted by ``|S|^2 ~ 0`` at the low frequencies where ``|T|^2
~ 1``, and the residual predicted too low (for a diffractive pyramid: ``docs/benchmarks.md``).

Why not from telemetry alone (a gain scan): for a linear time-invariant controller ``m`` and
``u`` are filters of ``pol`` (``m = S og pol``, ``u = K m``), and ``pol = z^-1 d + v / og``
does not depend on the controller when ``v`` does not (aliasing of the fitting error, which no
DM shape in the basis changes; photon and read noise). Every closed-loop record, whatever
the gain, is a function of the one signal ``pol``: runs at two gains give the same equation
twice, and ``d`` and ``v`` are not separable (``tests/test_sensor_error.py`` checks it on a
synthetic loop). Only a loop-dependent error (the non-linearity, a mismatch of the optical
gains) leaves a trace in a gain scan. So the error's PSD comes from a model of the sensor:
:func:`sensor_error_psd` estimates it from a record of the sensor's output and of the modal
residual it was looking at (in a simulator, the calibration run's own residual; on an
instrument, the sensor model applied to residual phase screens of the loop's statistics),
with the estimator of the disturbance (same grid), and :func:`split_sensor_error` moves it
from the telemetry's disturbance PSD to a coloured noise PSD that
:func:`aocontrol.analysis.residual_variance` sends through ``T``.

Assumptions: ``v`` uncorrelated with the disturbance (checked on the comparison's quick
scenes, ``docs/benchmarks.md``), and not changed by the
controller (the error is the sensor's at the residual level of the calibration run; the
non-linear part grows with the residual).
"""

from __future__ import annotations

from dataclasses import dataclass

import control
import numpy as np

from aocontrol._validation import check_finite_array
from aocontrol.plant import plant_fs
from aocontrol.synthesis._telemetry import (
    TelemetryPSD,
    _check_optical_gain,
    disturbance_from_telemetry,
)

__all__ = ["SensorErrorPSD", "sensor_error_psd", "split_sensor_error"]


@dataclass(frozen=True)
class SensorErrorPSD:
    """PSD of a sensor's error beyond its linear response (module docstring).

    Attributes
    ----------
    freqs : ndarray, shape (n_freqs,)
        Frequencies [Hz], ascending from 0 to ``fs/2`` (the grid of
        :func:`aocontrol.synthesis.disturbance_from_telemetry` for the record's length).
    psd : ndarray, shape (n_modes, n_freqs)
        One-sided PSD of ``v / og`` [units^2/Hz] (referred to the residual).
    variance : ndarray, shape (n_modes,)
        Per-frame variance of ``v / og`` [units^2].
    fs : float
        Loop rate [Hz].
    """

    freqs: np.ndarray
    psd: np.ndarray
    variance: np.ndarray
    fs: float

    def __post_init__(self) -> None:
        n_f = self.freqs.shape[0]
        if self.psd.ndim != 2 or self.psd.shape[1] != n_f:
            raise ValueError(f"psd must have shape (n_modes, {n_f}), got {self.psd.shape}")
        if self.variance.shape != (self.psd.shape[0],):
            raise ValueError(
                f"variance must have shape ({self.psd.shape[0]},), got {self.variance.shape}"
            )
        for arr in (self.freqs, self.psd, self.variance):
            arr.setflags(write=False)

    @property
    def n_modes(self) -> int:
        """Number of modes."""
        return self.psd.shape[0]

    def on(self, freqs: object) -> np.ndarray:
        """The PSD interpolated on other frequencies [Hz], shape ``(n_modes, n_freqs)``
        (linear; constant beyond the ends)."""
        f = np.asarray(freqs, dtype=float)
        return np.array([np.interp(f, self.freqs, row) for row in self.psd])


def sensor_error_psd(
    measurements: object,
    residuals: object,
    plant: control.TransferFunction,
    *,
    fs: float | None = None,
    optical_gain: object = None,
    nperseg: int | None = None,
) -> SensorErrorPSD:
    """PSD of the sensor's error ``v = m - og z^-1 e`` from its output and its input.

    ``v / og = m[k] / og - e[k-1]`` (one frame of WFS integration: the measurement of frame
    ``k`` sees the residual of frame ``k-1``), estimated with
    :func:`aocontrol.synthesis.disturbance_from_telemetry` (pre-whitened, the same grid as
    a telemetry estimate of the same length); the PSD is the estimate's disturbance plus its
    white floor, i.e. the whole spectrum of ``v / og``.

    Parameters
    ----------
    measurements : array_like, shape (n_frames, n_modes)
        The sensor's modal output ``m`` [units], as the controller received it.
    residuals : array_like, shape (n_frames, n_modes)
        The modal residual ``e`` the sensor looked at, same frames [units].
    plant : control.TransferFunction
        Loop plant (its rate; the estimator's argument).
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    optical_gain : float or array_like of shape (n_modes,), optional
        Optical gains ``m`` carries uncompensated (default 1).
    nperseg : int, optional
        Welch segment [frames] (default that of the estimator).

    Returns
    -------
    SensorErrorPSD

    Raises
    ------
    ValueError
        Records not finite, not 2-D, of different shapes, or too short; a bad
        ``optical_gain``.
    """
    m = check_finite_array("measurements", measurements, ndim=2)
    e = check_finite_array("residuals", residuals, ndim=2)
    if m.shape != e.shape:
        raise ValueError(
            f"measurements and residuals must have the same shape (n_frames, n_modes), got "
            f"{m.shape} and {e.shape}"
        )
    fs_ = plant_fs(plant, fs)
    og = _check_optical_gain(optical_gain, m.shape[1])
    v = m[1:] / og - e[:-1]
    est = disturbance_from_telemetry(v, np.zeros_like(v), plant, fs=fs_, nperseg=nperseg)
    psd = est.psd + est.noise_psd[:, None]
    return SensorErrorPSD(freqs=est.freqs, psd=psd, variance=v.var(axis=0), fs=fs_)


def split_sensor_error(tel: TelemetryPSD, error: SensorErrorPSD) -> tuple[np.ndarray, np.ndarray]:
    """Disturbance and coloured noise PSDs of a telemetry estimate, the sensor's error apart.

    The telemetry's pseudo-open loop holds ``z^-1 d + v`` (``P_pol = tel.psd +
    tel.noise_psd``); the disturbance is ``P_pol - P_v`` (clipped at the estimator's floor,
    ``1e-6`` of the noise level) and the noise is ``P_v`` itself, coloured, not the white
    floor: ``residual_variance(plant, K, tel.freqs, psd, noise)`` then gives ``|S|^2 P_d +
    |T|^2 P_v`` (module docstring).

    Parameters
    ----------
    tel : TelemetryPSD
        Estimate from the loop's telemetry.
    error : SensorErrorPSD
        The sensor's error, same modes and rate (interpolated on ``tel.freqs``).

    Returns
    -------
    psd, noise_psd : ndarray, shape (n_modes, n_freqs)
        One-sided [units^2/Hz] on ``tel.freqs``.

    Raises
    ------
    ValueError
        Different numbers of modes or rates.
    """
    if error.n_modes != tel.n_modes:
        raise ValueError(
            f"error has {error.n_modes} modes, the telemetry estimate tel has {tel.n_modes}"
        )
    if abs(error.fs - tel.fs) > 1e-9 * tel.fs:
        raise ValueError(f"error.fs = {error.fs!r} Hz differs from tel.fs = {tel.fs!r} Hz")
    p_v = error.on(tel.freqs)
    p_pol = tel.psd + tel.noise_psd[:, None]
    floor = 1e-6 * np.where(tel.noise_psd > 0, tel.noise_psd, p_pol.max(axis=1))
    psd = np.maximum(p_pol - p_v, np.maximum(floor, np.finfo(float).tiny)[:, None])
    return psd, p_v
