"""Disturbance and noise PSDs from closed-loop modal telemetry (pseudo-open loop).

Loop conventions (those of :mod:`aocontrol.analysis`): the residual is ``e = d - DM(u)``,
the measurement ``m = z^-1 e + n`` (WFS integration of one frame plus noise) and the plant
``G = z^-1 z^-latency`` maps the command ``u`` to the measurement, so that
``S = 1/(1 + G K)`` with ``u = K m``. Then the pseudo-open-loop (POL) signal

    pol = m + G u = z^-1 d + n

is the one-frame-delayed disturbance plus the measurement noise, whatever the controller.
PSDs are one-sided [units^2/Hz] (``scipy.signal.welch(..., scaling="density")``); telemetry is
shaped ``(n_frames, n_modes)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import control
import numpy as np
from scipy import signal, stats

from aocontrol._validation import check_finite_array, check_in_range, check_int
from aocontrol.analysis import welch_psd
from aocontrol.plant import plant_fs, z_inverse_coefficients

__all__ = ["TelemetryPSD", "disturbance_from_telemetry", "pseudo_open_loop"]

logger = logging.getLogger(__name__)

# Noise band declared not flat (warning) when the median of its lower half exceeds that of
# its upper half by this factor (the chi-square scatter of the medians is a few %).
_FLATNESS_RATIO = 1.5
# Disturbance PSD after noise removal is clipped to this fraction of the noise level (of the
# POL PSD maximum if there is no noise), so that it stays strictly positive.
_PSD_FLOOR_FRACTION = 1e-6

# Fewest frames for a Welch estimate (the smallest segment accepted).
_MIN_FRAMES = 8


@dataclass(frozen=True)
class TelemetryPSD:
    """Disturbance and noise estimated from closed-loop telemetry.

    Attributes
    ----------
    freqs : ndarray, shape (n_freqs,)
        Welch frequencies [Hz], ``0 .. fs/2``.
    psd : ndarray, shape (n_modes, n_freqs)
        Disturbance PSD, one-sided [units^2/Hz]: POL PSD minus the white noise floor, clipped
        to stay > 0.
    noise_psd : ndarray, shape (n_modes,)
        White measurement-noise level, one-sided [units^2/Hz] (per-frame variance
        ``noise_psd * fs / 2``).
    pseudo_open_loop : ndarray, shape (n_frames, n_modes)
        ``m + G u`` = delayed disturbance + noise [units].
    pol_psd : ndarray, shape (n_modes, n_freqs)
        Welch PSD of ``pseudo_open_loop`` before noise removal [units^2/Hz].
    fs : float
        Loop rate [Hz].
    noise_band : tuple of float
        Band used for the noise floor, as fractions of the Nyquist frequency.
    """

    freqs: np.ndarray
    psd: np.ndarray
    noise_psd: np.ndarray
    pseudo_open_loop: np.ndarray
    pol_psd: np.ndarray
    fs: float
    noise_band: tuple[float, float]

    def __post_init__(self) -> None:
        n_f = self.freqs.shape[0]
        if self.psd.ndim != 2 or self.psd.shape[1] != n_f:
            raise ValueError(f"psd must have shape (n_modes, {n_f}), got {self.psd.shape}")
        if self.noise_psd.shape != (self.psd.shape[0],):
            raise ValueError(
                f"noise_psd must have shape ({self.psd.shape[0]},), got {self.noise_psd.shape}"
            )
        for arr in (self.freqs, self.psd, self.noise_psd, self.pseudo_open_loop, self.pol_psd):
            arr.setflags(write=False)

    @property
    def n_modes(self) -> int:
        """Number of modes."""
        return self.psd.shape[0]

    @property
    def noise_variance(self) -> np.ndarray:
        """Per-frame noise variance [units^2], shape ``(n_modes,)``."""
        return self.noise_psd * self.fs / 2


def _check_telemetry(name: str, value: object) -> np.ndarray:
    arr = check_finite_array(name, value, ndim=(1, 2))
    return arr[:, None] if arr.ndim == 1 else arr


def pseudo_open_loop(
    measurements: object,
    commands: object,
    plant: control.TransferFunction,
    *,
    fs: float | None = None,
) -> np.ndarray:
    """Pseudo-open-loop reconstruction ``m + G u`` [units], shape ``(n_frames, n_modes)``.

    ``G u`` is ``scipy.signal.lfilter`` of the plant's ``z^-1`` coefficients along the frame
    axis, zero initial state (the telemetry must start with the loop at rest, or the first
    few frames carry the transient of the unknown earlier commands).

    Parameters
    ----------
    measurements, commands : array_like, shape (n_frames, n_modes) or (n_frames,)
        Closed-loop modal measurements ``m`` and the commands ``u`` computed from them at the
        same frame (``u[k] = K m[k]``) [units].
    plant : control.TransferFunction
        Discrete plant (command to measurement), e.g. :func:`aocontrol.loop_plant`.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> m, u = np.array([1.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0])
    >>> pseudo_open_loop(m, u, loop_plant(1000.0, 0.0))[:, 0]    # m + u[k-1]
    array([1., 1., 1.])
    """
    if not isinstance(plant, control.TransferFunction):
        raise TypeError(
            "plant must be a control.TransferFunction to rebuild the pseudo open "
            f"loop (z^-1 coefficients), got {type(plant).__name__}"
        )
    plant_fs(plant, fs)
    m = _check_telemetry("measurements", measurements)
    u = _check_telemetry("commands", commands)
    if m.shape != u.shape:
        raise ValueError(
            f"measurements and commands must have the same shape (n_frames, "
            f"n_modes), got {m.shape} and {u.shape}"
        )
    b, a = z_inverse_coefficients(plant, "plant")
    return m + signal.lfilter(b, a, u, axis=0)


def _welch_dof(n_frames: int, nperseg: int) -> float:
    """Equivalent degrees of freedom of a Welch estimate (Hann, 50 % overlap).

    Percival & Walden (1993), eq. (292b): ``nu = 2 K / (1 + 2 sum_m (1 - m/K) c_m^2)`` with
    ``K`` segments and ``c_m`` the normalised overlap of the window with itself shifted by
    ``m`` segment steps (only ``m = 1`` overlaps at 50 %).
    """
    step = nperseg - nperseg // 2
    k = 1 + (n_frames - nperseg) // step
    w = signal.get_window("hann", nperseg)
    c1 = float(np.dot(w[step:], w[:-step]) / np.dot(w, w)) if k > 1 else 0.0
    return 2 * k / (1 + 2 * (1 - 1 / k) * c1 * c1)


def _median_to_mean(dof: float) -> float:
    """Mean / median of a chi-square variable with ``dof`` degrees of freedom."""
    return float(dof / stats.chi2.median(dof))


def disturbance_from_telemetry(
    measurements: object,
    commands: object,
    plant: control.TransferFunction,
    *,
    fs: float | None = None,
    nperseg: int | None = None,
    noise_band: tuple[float, float] = (0.8, 1.0),
) -> TelemetryPSD:
    """Disturbance PSD and white noise level per mode from closed-loop telemetry.

    1. Pseudo open loop ``pol = m + G u`` (:func:`pseudo_open_loop`) = ``z^-1 d + n``.
    2. Welch PSD of ``pol`` per mode (``scipy.signal.welch``: Hann window, 50 % overlap,
       ``scaling="density"``, one-sided; the record mean removed once, no per-segment
       detrend). The 0 and Nyquist bins, which scipy leaves two-sided, are doubled so that
       the PSD is the one-sided density [units^2/Hz] at every grid frequency.
    3. Noise: the POL PSD is flat at the noise level where the disturbance has died out. The
       level is the median of the POL PSD over ``noise_band`` (fractions of Nyquist, default
       the top 20 %, the Nyquist bin excluded), corrected from median to mean for the
       chi-square statistics of Welch estimates (``nu ~ 2 K / (1 + 2 c^2)`` degrees of
       freedom for ``K`` segments, ``c = 1/6`` the overlap correlation of Hann at 50 %).
       Robust to a few disturbance lines in the band; biased high if the disturbance is not
       negligible there (bright low-order modes at low ``fs``): then narrow the band or pass
       a known noise level to the synthesis instead.
    4. Disturbance: POL PSD minus the noise level, clipped at ``1e-6`` of the noise level
       (stays > 0).

    Parameters
    ----------
    measurements : array_like, shape (n_frames, n_modes) or (n_frames,)
        Closed-loop modal measurements ``m`` [units, e.g. nm].
    commands : array_like, same shape
        Modal commands ``u`` computed from ``m`` at the same frame [units].
    plant : control.TransferFunction
        Discrete loop plant (command to measurement), e.g. :func:`aocontrol.loop_plant`.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    nperseg : int, optional
        Welch segment length [frames]; default ``min(n_frames, 1024)``. At least 8 frames, at
        most ``n_frames``.
    noise_band : (float, float), default (0.8, 1.0)
        Band of the noise floor as fractions of the Nyquist frequency, ``0 <= lo < hi <= 1``.

    Returns
    -------
    TelemetryPSD

    Raises
    ------
    ValueError
        Telemetry with NaN/inf, of different shapes or not 1-D/2-D, fewer frames than
        ``nperseg``, a bad ``noise_band`` or one containing no Welch bin.
    TypeError
        If ``plant`` is not a transfer function.
    """
    fs_ = plant_fs(plant, fs)
    pol = pseudo_open_loop(measurements, commands, plant, fs=fs_)
    n_frames, n_modes = pol.shape
    # The telemetry is checked before the segment length it implies: a short or transposed
    # record is the telemetry's fault, not that of an nperseg the user never passed.
    if nperseg is not None:
        nperseg = check_int("nperseg", nperseg, minimum=_MIN_FRAMES)
    need = _MIN_FRAMES if nperseg is None else nperseg
    if n_frames < need:
        hint = " (transposed? frames go along the first axis)" if n_modes > n_frames else ""
        why = f"nperseg={nperseg}" if nperseg is not None else "a Welch estimate"
        raise ValueError(
            f"telemetry (measurements, commands) must have shape (n_frames, n_modes) with "
            f"n_frames >= {need} for {why}, got {np.shape(measurements)}{hint}"
        )
    if nperseg is None:
        nperseg = min(n_frames, 1024)
    try:
        lo, hi = (float(x) for x in noise_band)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"noise_band must be a pair of floats, got {noise_band!r}") from exc
    check_in_range("noise_band[0]", lo, 0.0, 1.0)
    check_in_range("noise_band[1]", hi, 0.0, 1.0, low_inclusive=False, high_inclusive=True)
    if not lo < hi:
        raise ValueError(f"noise_band must satisfy lo < hi, got {noise_band!r}")

    # Record mean removed once, one-sided at every bin (see aocontrol.analysis.welch_psd).
    freqs, pxx = welch_psd(pol, fs_, nperseg)
    nyq = fs_ / 2
    band = (freqs >= lo * nyq) & (freqs <= hi * nyq) & (freqs < nyq) & (freqs > 0)
    if not band.any():
        raise ValueError(
            f"noise_band {noise_band!r} contains no Welch frequency bin "
            f"(resolution {freqs[1]:.4g} Hz); widen it or increase nperseg"
        )
    noise = np.median(pxx[:, band], axis=1) * _median_to_mean(_welch_dof(n_frames, nperseg))
    idx = np.flatnonzero(band)
    if idx.size >= 8:
        # A floor that still falls across the band is not white noise: the disturbance is
        # not negligible there and the noise level is overestimated.
        lower = np.median(pxx[:, idx[: idx.size // 2]], axis=1)
        upper = np.median(pxx[:, idx[idx.size // 2 :]], axis=1)
        sloped = np.flatnonzero(lower > _FLATNESS_RATIO * upper)
        if sloped.size:
            logger.warning(
                "POL PSD not flat in the noise band %s of Nyquist for modes %s: "
                "noise level overestimated",
                (lo, hi),
                sloped[:10].tolist(),
            )
    floor = _PSD_FLOOR_FRACTION * np.where(noise > 0, noise, pxx.max(axis=1))
    floor = np.where(floor > 0, floor, np.finfo(float).tiny)
    psd = np.maximum(pxx - noise[:, None], floor[:, None])
    return TelemetryPSD(
        freqs=freqs,
        psd=psd,
        noise_psd=noise,
        pseudo_open_loop=pol,
        pol_psd=pxx,
        fs=fs_,
        noise_band=(lo, hi),
    )
