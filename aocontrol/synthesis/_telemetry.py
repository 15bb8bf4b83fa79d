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

import dataclasses
import logging
import math
import os
from dataclasses import dataclass

import control
import numpy as np
from scipy import signal

from aocontrol._validation import (
    check_finite_array,
    check_in_range,
    check_int,
    check_nonnegative,
    check_positive,
)
from aocontrol.analysis import welch_psd
from aocontrol.plant import plant_fs, z_inverse_coefficients
from aocontrol.synthesis._telemetry_lowfreq import (
    _below_finest_bin,
    _below_second_bin,
    _welch_differenced,
    _whitening,
)
from aocontrol.synthesis._welch_stats import (
    _EXTEND_MIN,
    _debias,
    _flatness_threshold,
    _floor,
    _welch_dof,
    extended_noise_level,
)

__all__ = [
    "ESTIMATORS",
    "LoopTelemetry",
    "TelemetryPSD",
    "default_nperseg",
    "disturbance_from_telemetry",
    "pseudo_open_loop",
]

logger = logging.getLogger(__name__)

# Fewest frames for a Welch estimate (the smallest segment accepted).
_MIN_FRAMES = 8

#: Estimators of :func:`disturbance_from_telemetry` (the first is the default).
ESTIMATORS = ("prewhitened", "welch")


@dataclass(frozen=True)
class TelemetryPSD:
    """Disturbance and noise estimated from closed-loop telemetry.

    Attributes
    ----------
    freqs : ndarray, shape (n_freqs,)
        Frequencies [Hz], ascending from 0 to ``fs/2``: the Welch grid ``k fs / nperseg``;
        for ``"prewhitened"``, below its second bin, the dyadic points of the longer
        segments and, below their first bin, log-spaced points down to the record's
        resolution (steps 6-7 of :func:`disturbance_from_telemetry`), so not uniform.
    psd : ndarray, shape (n_modes, n_freqs)
        Disturbance PSD, one-sided [units^2/Hz]: the estimate of ``method`` (POL PSD, plain or
        pre-whitened, minus the white noise floor), clipped to stay > 0.
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
    method : str
        Estimator of ``psd``: ``"prewhitened"`` (Welch PSD of the differenced pseudo-open
        loop divided by ``|1 - z^-1|^2``, the default of every telemetry entry point) or
        ``"welch"`` (plain Welch); see :func:`disturbance_from_telemetry`.
    """

    freqs: np.ndarray
    psd: np.ndarray
    noise_psd: np.ndarray
    pseudo_open_loop: np.ndarray
    pol_psd: np.ndarray
    fs: float
    noise_band: tuple[float, float]
    method: str = "welch"

    def __post_init__(self) -> None:
        n_f = self.freqs.shape[0]
        if self.psd.ndim != 2 or self.psd.shape[1] != n_f:
            raise ValueError(f"psd must have shape (n_modes, {n_f}), got {self.psd.shape}")
        if self.noise_psd.shape != (self.psd.shape[0],):
            raise ValueError(
                f"noise_psd must have shape ({self.psd.shape[0]},), got {self.noise_psd.shape}"
            )
        if self.method not in ESTIMATORS:
            raise ValueError(f"method must be one of {list(ESTIMATORS)}, got {self.method!r}")
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


@dataclass(frozen=True, eq=False)
class LoopTelemetry:
    """Closed-loop modal telemetry of one loop, and what a design must know of the loop.

    What :func:`aocontrol.io.read_aot` returns and
    :func:`aocontrol.synthesis.design_from_telemetry` takes.

    Attributes
    ----------
    measurements : ndarray, shape (n_frames, n_modes)
        Modal measurements ``m`` [units, e.g. nm], frames along the first axis.
    commands : ndarray, shape (n_frames, n_modes)
        Modal commands ``u`` computed from ``m`` at the same frame [units].
    fs : float
        Loop rate [Hz].
    latency_frames : float or None
        RTC latency beyond the one-frame WFS integration [frames] (``None``: unknown, to be
        given to the design).
    source : str
        Where the telemetry came from (file and loop), for messages.
    unit : str or None, default "nm"
        Unit of :attr:`measurements` and :attr:`commands` (and of every figure designed from
        them: RMS in ``unit``, PSDs in ``unit^2/Hz``). The project's convention is nm (modal
        coefficients of 1 nm RMS); :func:`aocontrol.io.read_aot` converts a file's length
        unit to nm and keeps any other (``"rad"``, ``"V"``), or ``None`` when neither the file
        nor the user states it (figures then labelled ``"a.u."``, never nm).
    """

    measurements: np.ndarray
    commands: np.ndarray
    fs: float
    latency_frames: float | None = None
    source: str = ""
    unit: str | None = "nm"

    def __post_init__(self) -> None:
        where = f" of {self.source}" if self.source else ""
        m = check_finite_array(f"measurements{where}", self.measurements, ndim=2)
        u = check_finite_array(f"commands{where}", self.commands, ndim=2)
        if m.shape != u.shape:
            raise ValueError(
                f"measurements and commands{where} must have the same shape (n_frames, "
                f"n_modes), got {m.shape} and {u.shape}"
            )
        if self.unit is not None and (not isinstance(self.unit, str) or not self.unit.strip()):
            raise ValueError(
                f"unit{where} must be a non-empty string (e.g. 'nm') or None (unknown), got "
                f"{self.unit!r}"
            )
        object.__setattr__(self, "fs", check_positive(f"fs{where}", self.fs))
        if self.latency_frames is not None:
            lat = check_nonnegative(f"latency_frames{where}", self.latency_frames)
            object.__setattr__(self, "latency_frames", lat)
        for name, arr in (("measurements", m), ("commands", u)):
            if arr is getattr(self, name):  # the caller's array: keep it writeable
                arr = arr.copy()
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def n_frames(self) -> int:
        """Number of frames."""
        return self.measurements.shape[0]

    @property
    def n_modes(self) -> int:
        """Number of modes."""
        return self.measurements.shape[1]


def _check_telemetry_pair(measurements: object, commands: object) -> tuple[np.ndarray, np.ndarray]:
    """Both records checked (:func:`_check_telemetry`) and of the same shape."""
    m = _check_telemetry("measurements", measurements)
    u = _check_telemetry("commands", commands)
    if m.shape != u.shape:
        raise ValueError(
            f"measurements and commands must have the same shape (n_frames, "
            f"n_modes), got {m.shape} and {u.shape}"
        )
    return m, u


def _check_telemetry(name: str, value: object) -> np.ndarray:
    arr = check_finite_array(name, value, ndim=(1, 2))
    return arr[:, None] if arr.ndim == 1 else arr


def pseudo_open_loop(
    measurements: object,
    commands: object,
    plant: control.TransferFunction,
    *,
    fs: float | None = None,
    optical_gain: object = None,
) -> np.ndarray:
    """Pseudo-open-loop reconstruction ``m / og + G u`` [units], shape ``(n_frames, n_modes)``.

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
    optical_gain : float or array_like of shape (n_modes,), optional
        Optical gains ``og`` the measurements carry and the reconstructor did not compensate
        (a pyramid read with its raw, flat-wavefront reconstructor: ``m = og z^-1 e + n``);
        default 1, measurements in residual units (gains compensated, or a linear sensor).
        See :func:`disturbance_from_telemetry`.

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
    m, u = _check_telemetry_pair(measurements, commands)
    b, a = z_inverse_coefficients(plant, "plant")
    return m / _check_optical_gain(optical_gain, m.shape[1]) + signal.lfilter(b, a, u, axis=0)


def _check_optical_gain(optical_gain: object, n_modes: int) -> np.ndarray:
    """Optical gains as an array of shape ``(n_modes,)``, all > 0 (1 if None)."""
    if optical_gain is None:
        return np.ones(n_modes)
    og = check_finite_array("optical_gain", optical_gain, ndim=(0, 1))
    og = np.broadcast_to(og, (n_modes,)) if og.ndim == 0 else og
    if og.shape != (n_modes,) or np.any(og <= 0):
        raise ValueError(
            f"optical_gain must be a positive scalar or {n_modes} positive values (one per "
            f"mode), got shape {og.shape} with min {float(np.min(og)) if og.size else None!r}"
        )
    return np.asarray(og, dtype=float)


# Default Welch segment of the pre-whitened estimate: the largest power of 2 giving at least
# _MIN_SEGMENTS half-overlapped segments, within [_MIN_NPERSEG, _MAX_NPERSEG] frames (a PSD
# of one segment is a chi-square(2) scatter that the designs would fit; pre-whitening makes
# long segments unnecessary for the sub-hertz turbulence).
_MIN_SEGMENTS, _MAX_NPERSEG, _MIN_NPERSEG = 8, 1024, 64


def default_nperseg(n_frames: int, method: str = "prewhitened") -> int:
    """Default Welch segment length [frames] of :func:`disturbance_from_telemetry`.

    ``"welch"``: ``min(n_frames, 1024)``. ``"prewhitened"``: the largest power of 2 giving at
    least 8 half-overlapped segments, clipped to [64, 1024] and below ``n_frames`` (the
    differenced record has ``n_frames - 1`` frames).

    Parameters
    ----------
    n_frames : int
        Frames of the record.
    method : {"prewhitened", "welch"}, default "prewhitened"
        Estimator.

    Returns
    -------
    int
        Segment length [frames].
    """
    n_frames = check_int("n_frames", n_frames, minimum=1)
    if method == "welch":
        return min(n_frames, _MAX_NPERSEG)
    n = 2 ** int(math.floor(math.log2(max(n_frames, 2) * 2 / (_MIN_SEGMENTS + 1))))
    return int(min(_MAX_NPERSEG, max(_MIN_NPERSEG, n), max(n_frames - 1, _MIN_FRAMES)))


def _check_method(method: object) -> str:
    if method not in ESTIMATORS:
        raise ValueError(f"method must be one of {list(ESTIMATORS)}, got {method!r}")
    return str(method)


def disturbance_from_telemetry(
    measurements: object,
    commands: object,
    plant: control.TransferFunction,
    *,
    fs: float | None = None,
    nperseg: int | None = None,
    noise_band: tuple[float, float] = (0.8, 1.0),
    method: str = "prewhitened",
    optical_gain: object = None,
    n_jobs: int | None = None,
) -> TelemetryPSD:
    """Disturbance PSD and white noise level per mode from closed-loop telemetry.

    1. Pseudo open loop ``pol = m + G u`` (:func:`pseudo_open_loop`) = ``z^-1 d + n``.
    2. Welch PSD of ``pol`` per mode (``scipy.signal.welch``: Hann window, 50 % overlap,
       ``scaling="density"``, one-sided; the record mean removed once, no per-segment
       detrend). The 0 and Nyquist bins, which scipy leaves two-sided, are doubled so that
       the PSD is the one-sided density [units^2/Hz] at every grid frequency.
    3. Noise: the POL PSD is flat at the noise level where the disturbance has died out. The
       level is the median of the POL PSD over ``noise_band`` (fractions of Nyquist, default
       the top 20 %, the Nyquist bin excluded), extended down per mode over the contiguous
       bins where no disturbance is detected (one-octave means within 3 standard deviations
       of the band's level, down to 0.1 Nyquist: :func:`~aocontrol.synthesis._welch_stats.
       extended_noise_level`), corrected from median to mean for the
       chi-square statistics of Welch estimates (``nu ~ 2 K / (1 + 2 c^2)`` degrees of
       freedom for ``K`` segments, ``c = 1/6`` the overlap correlation of Hann at 50 %).
       The extension cuts the level's per-mode scatter (several per cent on the top 20 % of
       a short record), which steps 4-5 would turn into a positive bias of the disturbance
       (a low level leaves its excess over the whole noise-dominated band, a high one is
       clipped; ``docs/benchmarks.md``). Robust to a few
       disturbance lines in the band; biased high if the disturbance is not negligible in
       the band itself (bright low-order modes at low ``fs``): then narrow the band or pass
       a known noise level to the synthesis instead.
    4. Disturbance, ``method="welch"``: POL PSD minus the noise level, clipped at ``1e-6`` of
       the noise level (stays > 0). Where the noise dominates, the excess ``POL - noise`` is
       the Welch scatter of the noise (relative standard deviation ``sqrt(2 / nu)``, 27 % for
       15 segments) around a disturbance far below it; clipping each bin at zero keeps the
       positive half of that scatter, a bias of ~10 % of the noise level in every such bin,
       which a loop's ``|S|^2 ~ 1-2`` there turns into a predicted residual well above the
       true one in noise-limited loops (``tests/test_telemetry_prediction.py``,
       ``docs/benchmarks.md``). So the excess of each bin
       below 3 standard deviations of the scatter (disturbance not detected) is first
       replaced by the mean excess of such bins within one octave around it (the scatter
       averaged away, the local disturbance level kept); bins where the disturbance is
       detected (vibration lines, turbulence) are kept as measured.
    5. Disturbance, ``method="prewhitened"`` (default): turbulence puts most of its variance
       below the first Welch bin (1-6 Hz for segments of 512-1024 frames at 1-3 kHz); the
       Hann window leaks it into the first bins, where a loop's ``|S|^2`` is no longer small,
       and the plain PSD predicts (and the designs fight) a residual several times the real
       one (``docs/benchmarks.md``). The classic cure is pre-whitening: the Welch PSD of the
       first difference
       ``Delta pol = Delta m + G Delta u``, flat at low frequency, divided by the expected
       Welch estimate of differenced unit white noise, ``2 (1 - rho cos(2 pi f / fs))``
       (``rho`` the Hann window's lag-1 autocorrelation; ``|1 - z^-1|^2`` up to the window's
       leakage, which is +33 % at the first bin), minus the noise level of step 3 (from the
       undifferenced record: its estimator assumes a white floor), smoothed and clipped as in
       step 4. The differenced record's mean is not removed
       (:func:`aocontrol.synthesis._telemetry_lowfreq._welch_differenced`).
    6. Below the second Welch bin (``2 fs / nperseg``, 12 Hz for 512 frames at 3 kHz) a
       loop's ``|S|^2`` is not small when its gain is low, and a disturbance seen whole
       (tip/tilt in stage 2 of dCAO) has most of its variance there: segments twice, four
       times ... as long, up to 4,096 frames or the whole record if shorter, each give their
       bins 2 and 3 below what
       the shorter segments cover (a dyadic multi-resolution grid, each interval covered
       once; the finest level also gives its bin 1). Left in the 0-Hz bin, where
       ``|S|^2 = 0``, that variance would be missing from the predicted residual
       (:func:`aocontrol.synthesis._telemetry_lowfreq._below_second_bin`).
    7. Below the finest bin ``f1`` (0 Hz to ``fs / 4096`` or the finest level's first bin):
       the variance the differenced record cannot see there (the pseudo-open loop's variance
       minus the noise's, minus the PSD's integral from ``f1`` up) is spread with the
       spectrum's own low-frequency slope, flat below a corner, variance conserved
       (:func:`aocontrol.synthesis._telemetry_lowfreq._below_finest_bin`; the PSD integrates
       to at least the pseudo-open loop's variance minus the noise, more when the trapezoid
       between the dyadic points overestimates a steep spectrum's integral: up to 6-12 % for
       ``f^-2`` spectra with corners at 0.3-1 Hz on 4,096 frames). As a spike in the 0-Hz
       bin it would be weighted by ``|S(0)|^2 = 0`` with integral action, and be a line the
       Wiener bound's FFT grid does not resolve (``tests/test_telemetry_prediction.py``
       checks a low-gain integrator's predicted residual on an ``f^-4`` spectrum within
       10 %).

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
        Welch segment length [frames]; default :func:`default_nperseg` (``min(n_frames,
        1024)`` for ``"welch"``, at least 8 segments for ``"prewhitened"``). At least 8
        frames, at most ``n_frames`` (``n_frames - 1`` for ``"prewhitened"``).
    noise_band : (float, float), default (0.8, 1.0)
        Band of the noise floor as fractions of the Nyquist frequency, ``0 <= lo < hi <= 1``,
        where the level is first measured (then extended down where flat, step 3).
    method : {"prewhitened", "welch"}, default "prewhitened"
        Disturbance estimator (steps 4-5).
    optical_gain : float or array_like of shape (n_modes,), optional
        Optical gains the measurements carry, uncompensated (default 1). With a pyramid
        read by its flat-wavefront reconstructor (optical-gain setting ``"none"``) the
        measurement is ``m = og z^-1 e + n``, so ``m + G u = og z^-1 d + (1 - og) G u + n``
        is not the disturbance: ``m / og + G u = z^-1 d + n / og`` is. The estimate is then
        the disturbance in residual units and the noise referred to the residual
        (``n / og``); the loop's own plant is ``og G`` (an integrator of gain ``g`` acts as
        one of gain ``og g`` on a unit-gain plant): predict its residual with that. With
        compensated measurements (``"calibrated"``: divided by calibrated gains ``og_c``)
        the default 1 assumes the true gains equal ``og_c``; pass ``og_true / og_c`` when
        known. The gains are assumed constant over the record (not ``"tracked"``) and the
        sensor linear around the loop's residual.
    n_jobs : int or None, default None
        Threads over blocks of modes (``None``: every core; 1: this thread; negative:
        joblib's convention). Every step is per mode: a mode's estimate is the same bits
        whatever the threads, and the same to rounding whatever the blocks (numpy sums one
        column and a block of columns in different orders). Blocks of
        :data:`_BLOCK_MODES` modes also keep a 15,000-frame record's work in the cache:
        ~2x faster on one thread than the whole record at once.

    Returns
    -------
    TelemetryPSD
        ``psd`` is the disturbance estimate of ``method``; ``pol_psd`` the plain Welch PSD of
        the pseudo-open loop; ``method`` says which estimator made ``psd``.

    Raises
    ------
    ValueError
        Telemetry with NaN/inf, of different shapes or not 1-D/2-D, fewer frames than
        ``nperseg`` (``nperseg + 1`` pre-whitened), a bad ``noise_band`` or one containing
        no Welch bin, an unknown ``method``, an ``optical_gain`` not positive or of the wrong
        length.
    TypeError
        If ``plant`` is not a transfer function.
    """
    method = _check_method(method)
    fs_ = plant_fs(plant, fs)
    if not isinstance(plant, control.TransferFunction):
        pseudo_open_loop(measurements, commands, plant, fs=fs_)  # its TypeError
    m, u = _check_telemetry_pair(measurements, commands)
    n_frames, n_modes = m.shape
    og = _check_optical_gain(optical_gain, n_modes)
    # The telemetry is checked before the segment length it implies: a short or transposed
    # record is the telemetry's fault, not that of an nperseg the user never passed.
    if nperseg is not None:
        nperseg = check_int("nperseg", nperseg, minimum=_MIN_FRAMES)
    extra = int(method == "prewhitened")
    need = (_MIN_FRAMES if nperseg is None else nperseg) + extra
    if n_frames < need:
        hint = " (transposed? frames go along the first axis)" if n_modes > n_frames else ""
        why = f"nperseg={nperseg}" if nperseg is not None else "a Welch estimate"
        if extra:
            why += " pre-whitened (one frame lost to the difference)"
        raise ValueError(
            f"telemetry (measurements, commands) must have shape (n_frames, n_modes) with "
            f"n_frames >= {need} for {why}, got {np.shape(measurements)}{hint}"
        )
    if nperseg is None:
        nperseg = default_nperseg(n_frames, method)
    threads = _threads(n_jobs)
    blocks = [slice(i, min(i + _BLOCK_MODES, n_modes)) for i in range(0, n_modes, _BLOCK_MODES)]

    def block(sl: slice) -> TelemetryPSD:
        return _estimate(m[:, sl], u[:, sl], plant, fs_, nperseg, noise_band, method, og[sl])

    if len(blocks) == 1:
        return block(blocks[0])
    if threads == 1:
        parts = [block(sl) for sl in blocks]
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(min(threads, len(blocks))) as pool:
            parts = list(pool.map(block, blocks))
    first = parts[0]
    return dataclasses.replace(
        first,
        psd=np.concatenate([p.psd for p in parts]),
        noise_psd=np.concatenate([p.noise_psd for p in parts]),
        pseudo_open_loop=np.concatenate([p.pseudo_open_loop for p in parts], axis=1),
        pol_psd=np.concatenate([p.pol_psd for p in parts]),
    )


def _threads(n_jobs: object) -> int:
    """Threads of ``n_jobs`` (None: every core; negative: joblib's convention, -1 every core)."""
    cores = os.cpu_count() or 1
    if n_jobs is None:
        return cores
    n = check_int("n_jobs", n_jobs)
    if n == 0:
        raise ValueError("n_jobs must be a nonzero integer (negative: joblib convention)")
    return n if n > 0 else max(1, cores + 1 + n)


#: Modes per block of :func:`disturbance_from_telemetry` (a thread's task; 15,000 frames x 64
#: modes of float64 are 7.7 MB).
_BLOCK_MODES = 64


def _estimate(
    m: np.ndarray,
    u: np.ndarray,
    plant: control.TransferFunction,
    fs_: float,
    nperseg: int,
    noise_band: tuple[float, float],
    method: str,
    og: np.ndarray,
) -> TelemetryPSD:
    """Steps 1-7 of :func:`disturbance_from_telemetry` on checked telemetry (a block of modes)."""
    pol = pseudo_open_loop(m, u, plant, fs=fs_, optical_gain=og)
    tel = _plain_estimate(pol, fs_, nperseg, noise_band)
    if method == "welch":
        return tel
    diff = pseudo_open_loop(np.diff(m, axis=0), np.diff(u, axis=0), plant, fs=fs_, optical_gain=og)
    f, pxx_diff = _welch_differenced(diff, fs_, nperseg)
    # Divided by the expected Welch estimate of differenced white noise (_whitening).
    nseg = min(nperseg, diff.shape[0])
    floor = _floor(tel.noise_psd, tel.pol_psd)
    excess = _debias(
        pxx_diff[:, 1:] / _whitening(f[1:], fs_, nseg) - tel.noise_psd[:, None],
        tel.noise_psd,
        _welch_dof(diff.shape[0], nseg),
    )
    f_low, excess_low, pol_low = _below_second_bin(
        diff, pol, fs_, nseg, excess[:, 1], tel.noise_psd
    )
    keep = 1 if f_low.size == 0 else 2  # the main grid's bins kept: from 1, or from 2
    freqs = np.concatenate([f[:1], f_low, f[keep:]])
    psd = np.concatenate([excess[:, :1], excess_low, excess[:, keep - 1 :]], axis=1)
    psd = np.maximum(psd, floor[:, None])
    pol_psd = np.concatenate([tel.pol_psd[:, :1], pol_low, tel.pol_psd[:, keep:]], axis=1)
    target = pol.var(axis=0) - tel.noise_psd * fs_ / 2
    f_sub, psd_sub = _below_finest_bin(freqs, psd, target, fs_ / (2 * m.shape[0]))
    freqs = np.concatenate([f_sub, freqs[1:]])
    psd = np.concatenate([psd_sub, psd[:, 1:]], axis=1)
    pol_psd = np.concatenate([psd_sub + tel.noise_psd[:, None], pol_psd[:, 1:]], axis=1)
    tel = dataclasses.replace(tel, freqs=freqs, psd=psd, pol_psd=pol_psd, method="prewhitened")
    return tel


def _plain_estimate(
    pol: np.ndarray, fs_: float, nperseg: int, noise_band: tuple[float, float]
) -> TelemetryPSD:
    """Steps 2-4 of :func:`disturbance_from_telemetry` on the pseudo-open loop."""
    n_frames = pol.shape[0]
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
    first = int(np.searchsorted(freqs, _EXTEND_MIN * nyq))
    dof = _welch_dof(n_frames, nperseg)
    noise = extended_noise_level(pxx, band, dof, first)[0]
    idx = np.flatnonzero(band)
    if idx.size >= 8:
        # A floor that still falls across the band is not white noise: the disturbance is
        # not negligible there and the noise level is overestimated.
        lower = np.median(pxx[:, idx[: idx.size // 2]], axis=1)
        upper = np.median(pxx[:, idx[idx.size // 2 :]], axis=1)
        threshold = _flatness_threshold(dof, idx.size // 2)
        sloped = np.flatnonzero(lower > threshold * upper)
        if sloped.size:
            logger.warning(
                "POL PSD not flat in the noise band %s of Nyquist for modes %s: "
                "noise level overestimated",
                (lo, hi),
                sloped[:10].tolist(),
            )
    excess = pxx - noise[:, None]
    excess[:, 1:] = _debias(excess[:, 1:], noise, dof)
    psd = np.maximum(excess, _floor(noise, pxx)[:, None])
    return TelemetryPSD(
        freqs=freqs,
        psd=psd,
        noise_psd=noise,
        pseudo_open_loop=pol,
        pol_psd=pxx,
        fs=fs_,
        noise_band=(lo, hi),
        method="welch",
    )
