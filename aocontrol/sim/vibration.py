"""Tilt vibrations: a PSD with sharp peaks, its FIR filter, and a streaming source.

The paper ("Vibration") builds a VLT vibration model from SPHERE pseudo-open-loop data: the
atmosphere filtered out, a finite impulse response (FIR) filter is fitted to the vibration
PSD, and vibrations are generated on the fly by filtering white noise. The paper's figure is
empty and its measured PSD is not published, so the default model here is
**representative, not measured**: a few lightly damped resonances in the range where VLT/SPHERE
tip-tilt vibrations are reported (telescope structure and wind shake from ~10 to ~20 Hz,
instrument and cryocooler lines at a few tens of Hz up to ~100 Hz; Petit et al., SPIE 7015
(2008) and SPIE 9148 (2014) on SAXO's tip-tilt vibration filtering; Sauvage et al., SPIE
9909 (2016) on SPHERE on sky). Amplitudes are chosen so that the total tilt vibration,
~12 nm RMS, gives a stage-2 integrator tilt residual of the paper's order (9.09 nm with the
atmosphere of bright 1 best); scale them with :meth:`VibrationPSD.scaled` or give other
peaks.

Conventions: PSDs one-sided [nm^2/Hz] (integrated over [0, fs/2] they give the variance),
frequencies in Hz, the tilt coefficient in nm RMS over the pupil (a unit coefficient of the
basis's tilt mode is 1 nm RMS).

Model of one peak: a second-order resonance (damped oscillator driven by white noise),
``P(f) = rms^2 (4 zeta / (pi f0)) f0^4 / ((f0^2 - f^2)^2 + (2 zeta f0 f)^2)``, whose integral
over ``[0, inf)`` is ``rms^2`` (the resonance's variance).

FIR: :func:`scipy.signal.firwin2` on the amplitude ``sqrt(PSD fs / 2)`` (frequency sampling
on a dense grid, Tukey window), so that filtering unit-variance white noise (one-sided PSD
``2 / fs``) gives the PSD; linear phase (a pure delay, irrelevant for a disturbance). Its
length covers ``_DECAY_TIMES`` decay times ``1 / (2 pi zeta f0)`` of the narrowest peak.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import signal

from aocontrol._validation import check_finite_array, check_int, check_positive

__all__ = [
    "VibrationPeak",
    "VibrationPSD",
    "DEFAULT_TILT_PEAKS",
    "fir_from_psd",
    "fir_psd",
    "TiltVibration",
    "tilt_vibration_psd",
]

# FIR half-length in decay times of the narrowest resonance (amplitude e^-5 ~ 0.7 % at the
# ends, before the window).
_DECAY_TIMES = 5.0
# Dense frequency grid of the FIR design: this many times the number of taps.
_GRID_FACTOR = 8
# Tukey window fraction of the FIR (tapers the outer quarter on each side, where the
# impulse response has decayed below ~e^-2.5).
_TUKEY_ALPHA = 0.5
# Block length of the streaming generator (frames); outputs do not depend on it or on how
# a run is split into calls.
_BLOCK = 8192


@dataclass(frozen=True)
class VibrationPeak:
    """One lightly damped resonance of the vibration PSD.

    Parameters
    ----------
    frequency : float
        Resonance frequency ``f0`` [Hz], > 0.
    damping : float
        Damping ratio ``zeta`` in (0, 1) (half-width at half-power ~ ``zeta f0`` Hz).
    rms : float
        Standard deviation of the tilt due to this peak [nm RMS], >= 0.
    """

    frequency: float
    damping: float
    rms: float

    def __post_init__(self) -> None:
        check_positive("frequency", self.frequency)
        zeta = check_positive("damping", self.damping)
        if zeta >= 1.0:
            raise ValueError(f"damping must be in (0, 1) (a resonance), got {zeta!r}")
        rms = float(self.rms)
        if not (math.isfinite(rms) and rms >= 0):
            raise ValueError(f"rms must be a finite number >= 0 [nm], got {self.rms!r}")

    @property
    def decay_time(self) -> float:
        """Amplitude decay time of the impulse response ``1 / (2 pi zeta f0)`` [s]."""
        return 1.0 / (2 * np.pi * self.damping * self.frequency)


#: Representative tilt vibration peaks (frequency [Hz], damping, rms [nm]); see the module
#: docstring for where they come from: a damped structural/wind-shake mode, two instrument
#: lines and a higher line. Total ~12 nm RMS.
DEFAULT_TILT_PEAKS = (
    VibrationPeak(17.5, 0.05, 6.0),
    VibrationPeak(47.0, 0.01, 8.0),
    VibrationPeak(60.0, 0.006, 6.0),
    VibrationPeak(98.0, 0.004, 4.0),
)


@dataclass(frozen=True)
class VibrationPSD:
    """Sum of resonance peaks: a one-sided vibration PSD [nm^2/Hz].

    Parameters
    ----------
    peaks : sequence of VibrationPeak
        The resonances (default :data:`DEFAULT_TILT_PEAKS`).
    """

    peaks: tuple = field(default=DEFAULT_TILT_PEAKS)

    def __post_init__(self) -> None:
        peaks = tuple(self.peaks)
        if not peaks or not all(isinstance(p, VibrationPeak) for p in peaks):
            raise TypeError("peaks must be a non-empty sequence of VibrationPeak")
        object.__setattr__(self, "peaks", peaks)

    @property
    def variance(self) -> float:
        """Total variance over ``[0, inf)`` [nm^2] (sum of the peaks' ``rms^2``)."""
        return float(sum(p.rms**2 for p in self.peaks))

    def scaled(self, factor: float) -> VibrationPSD:
        """The same peaks with every amplitude multiplied by ``factor``.

        Parameters
        ----------
        factor : float
            Amplitude factor, >= 0.

        Returns
        -------
        VibrationPSD
        """
        factor = float(factor)
        if not (math.isfinite(factor) and factor >= 0):
            raise ValueError(f"factor must be a finite number >= 0, got {factor!r}")
        return VibrationPSD(
            tuple(VibrationPeak(p.frequency, p.damping, p.rms * factor) for p in self.peaks)
        )

    def __call__(self, freqs: Any) -> np.ndarray:
        """One-sided PSD at ``freqs``.

        Parameters
        ----------
        freqs : array_like
            Frequencies [Hz], >= 0.

        Returns
        -------
        ndarray, same shape as ``freqs``
            PSD [nm^2/Hz].
        """
        f = check_finite_array("freqs", freqs)
        if np.any(f < 0):
            raise ValueError(f"freqs must be >= 0 [Hz], found min {f.min()!r}")
        out = np.zeros(f.shape)
        for p in self.peaks:
            f0, z = p.frequency, p.damping
            out += (
                p.rms**2
                * (4 * z / (np.pi * f0))
                * f0**4
                / ((f0**2 - f**2) ** 2 + (2 * z * f0 * f) ** 2)
            )
        return out


def _numtaps(psd: VibrationPSD, fs: float) -> int:
    tau = max(p.decay_time for p in psd.peaks)
    return 2 * int(math.ceil(_DECAY_TIMES * tau * fs)) + 1


def fir_from_psd(psd: VibrationPSD, fs: float, numtaps: int | None = None) -> np.ndarray:
    """FIR filter whose output PSD for unit-variance white noise input is ``psd``.

    Parameters
    ----------
    psd : VibrationPSD
        Target one-sided PSD [nm^2/Hz].
    fs : float
        Sampling rate [Hz]; every peak must lie below ``fs / 2``.
    numtaps : int, optional
        Odd number of taps (default: ``_DECAY_TIMES`` decay times of the narrowest peak on
        each side).

    Returns
    -------
    ndarray, shape (numtaps,)
        Taps [nm per unit white-noise sample] (linear phase).

    Raises
    ------
    ValueError
        A peak at or above ``fs / 2``, or an even/too small ``numtaps``.
    """
    fs = check_positive("fs", fs)
    for p in psd.peaks:
        if p.frequency >= fs / 2:
            raise ValueError(
                f"vibration peak at {p.frequency:g} Hz is not below the Nyquist frequency "
                f"{fs / 2:g} Hz of fs={fs:g} Hz"
            )
    n = _numtaps(psd, fs) if numtaps is None else check_int("numtaps", numtaps, minimum=3)
    if n % 2 == 0:
        raise ValueError(f"numtaps must be odd (a type-I linear-phase FIR), got {n}")
    nfreqs = 2 ** int(math.ceil(math.log2(_GRID_FACTOR * n))) + 1
    freq = np.linspace(0.0, fs / 2, nfreqs)
    gain = np.sqrt(psd(freq) * fs / 2)
    return signal.firwin2(n, freq, gain, nfreqs=nfreqs, window=("tukey", _TUKEY_ALPHA), fs=fs)


def fir_psd(taps: np.ndarray, freqs: Any, fs: float) -> np.ndarray:
    """One-sided output PSD of ``taps`` driven by unit-variance white noise.

    Parameters
    ----------
    taps : array_like, shape (numtaps,)
        FIR taps.
    freqs : array_like, shape (n_f,)
        Frequencies [Hz] in ``[0, fs / 2]``.
    fs : float
        Sampling rate [Hz].

    Returns
    -------
    ndarray, shape (n_f,)
        ``|H(f)|^2 2 / fs`` [units^2/Hz].
    """
    fs = check_positive("fs", fs)
    f = check_finite_array("freqs", freqs, ndim=1)
    _, h = signal.freqz(check_finite_array("taps", taps, ndim=1), worN=f, fs=fs)
    return np.abs(h) ** 2 * 2.0 / fs


class TiltVibration:
    """A tilt vibration generated on the fly: white noise through the FIR of a PSD.

    A disturbance source for both loops: ``phase_vectors(n)`` (the tilt on the valid pupil
    pixels, for :class:`aocontrol.sim.loop.PhaseSource` and the cascade) and ``next(n)``
    (modal, the coefficient in ``mode`` of ``basis``, for :class:`TurbulenceSource`'s
    ``additive`` or :func:`run_loop`). The same stream feeds all three methods: call one.

    The output is computed in fixed blocks of ``_BLOCK`` frames (FFT convolution of the
    block's white noise with the FIR, the previous ``numtaps - 1`` samples carried over), so
    the frames do not depend on how a run is split into calls, bit for bit. The filter history
    starts filled with white noise from the same generator: the process is stationary from
    frame 0.

    Parameters
    ----------
    fs : float
        Frame rate [Hz].
    basis : ModalBasis-like
        Provides the tilt mode (``modes[mode]`` on the valid pixels, 1 nm RMS per unit).
    rng : numpy.random.Generator or int
        Source of the white noise.
    psd : VibrationPSD, optional
        Target PSD of the tilt coefficient (default: :data:`DEFAULT_TILT_PEAKS`).
    mode : int
        Index of the tilt mode in ``basis`` (KL bases: 0 and 1 are tip and tilt).
    numtaps : int, optional
        FIR length (default from :func:`fir_from_psd`).
    """

    def __init__(
        self,
        fs: float,
        basis: Any,
        rng: np.random.Generator | int,
        *,
        psd: VibrationPSD | None = None,
        mode: int = 1,
        numtaps: int | None = None,
    ) -> None:
        self.fs = check_positive("fs", fs)
        self.psd = VibrationPSD() if psd is None else psd
        if not isinstance(self.psd, VibrationPSD):
            raise TypeError(f"psd must be a VibrationPSD, got {type(self.psd).__name__}")
        self.mode = check_int("mode", mode, minimum=0)
        self.n_modes = int(basis.n_modes)
        if self.mode >= self.n_modes:
            raise ValueError(f"mode must be < {self.n_modes} (modes in the basis), got {mode}")
        self.tilt = np.asarray(basis.modes[self.mode], dtype=float)
        self.taps = fir_from_psd(self.psd, self.fs, numtaps)
        if rng is None:
            raise ValueError("rng is required (reproducibility)")
        self._rng = np.random.default_rng(rng)
        self._hist = self._rng.standard_normal(self.taps.size - 1)
        self._buf = np.zeros(0)

    def _block(self) -> np.ndarray:
        x = np.concatenate([self._hist, self._rng.standard_normal(_BLOCK)])
        self._hist = x[-(self.taps.size - 1) :]
        return signal.fftconvolve(x, self.taps, mode="valid")

    def series(self, n_frames: int) -> np.ndarray:
        """The tilt coefficient of the next frames.

        Parameters
        ----------
        n_frames : int
            Frames requested.

        Returns
        -------
        ndarray, shape (n_frames,)
            Tilt [nm RMS].
        """
        n = check_int("n_frames", n_frames, minimum=0)
        parts = [self._buf]
        have = self._buf.size
        while have < n:
            blk = self._block()
            parts.append(blk)
            have += blk.size
        buf = np.concatenate(parts)
        self._buf = buf[n:]
        return buf[:n]

    def phase_vectors(self, n_frames: int) -> np.ndarray:
        """Tilt phase of the next frames on the valid pupil pixels.

        Parameters
        ----------
        n_frames : int
            Frames requested.

        Returns
        -------
        ndarray, shape (n_frames, n_valid)
            [nm of OPD].
        """
        return self.series(n_frames)[:, None] * self.tilt[None, :]

    def next(self, n_frames: int) -> tuple[np.ndarray, None]:
        """Modal disturbance of the next frames (the tilt mode only) and no phase.

        Parameters
        ----------
        n_frames : int
            Frames requested.

        Returns
        -------
        modal : ndarray (n_frames, n_modes)
            [nm RMS].
        phase : None
        """
        out = np.zeros((n_frames, self.n_modes))
        out[:, self.mode] = self.series(n_frames)
        return out, None


def tilt_vibration_psd(peaks: Sequence[tuple[float, float, float]]) -> VibrationPSD:
    """A :class:`VibrationPSD` from ``(frequency [Hz], damping, rms [nm])`` triples.

    Parameters
    ----------
    peaks : sequence of (float, float, float)
        One triple per resonance.

    Returns
    -------
    VibrationPSD
    """
    return VibrationPSD(tuple(VibrationPeak(*p) for p in peaks))
