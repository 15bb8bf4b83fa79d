"""Tilt vibration: PSD model, FIR fit, streaming generator."""

import numpy as np
import pytest
from scipy import signal

from aocontrol.controllers import Integrator
from aocontrol.sim import LinearModalSensor, PhaseSource, Stage, run_cascade
from aocontrol.sim.dm import DeformableMirror
from aocontrol.sim.modes import kl_basis
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.sim.vibration import (
    DEFAULT_TILT_PEAKS,
    TiltVibration,
    VibrationPeak,
    VibrationPSD,
    fir_from_psd,
    fir_psd,
    tilt_vibration_psd,
)


class _Basis:
    """Three orthonormal 'modes' on 5 pixels (coefficient = pixel value for mode 1)."""

    n_modes = 3
    modes = np.eye(3, 5)


@pytest.mark.parametrize("fs", [1000.0, 3000.0])
def test_fir_reproduces_the_psd(fs):
    # Oracle: the target PSD (analytic resonances). The FIR's exact output PSD for unit
    # white noise, |H|^2 2/fs, matches it at every peak within 3 % (the Tukey window and
    # the truncation at 5 decay times broaden the narrowest peaks by ~2 %), and its
    # variance sum(h^2) equals the PSD's integral over [0, fs/2] (0.1 %: the tails beyond
    # fs/2 hold < 1e-4 of it).
    psd = VibrationPSD()
    taps = fir_from_psd(psd, fs)
    f0 = np.array([p.frequency for p in psd.peaks])
    np.testing.assert_allclose(fir_psd(taps, f0, fs), psd(f0), rtol=0.03)
    f = np.linspace(0, fs / 2, 400001)
    band_var = np.trapezoid(psd(f), f)
    assert abs(np.sum(taps**2) / band_var - 1) < 1e-3
    assert abs(band_var / psd.variance - 1) < 1e-3
    # The one-sided normalisation can fail: a two-sided one would be off by 2.
    assert abs(np.sum(taps**2) / (psd.variance / 2) - 1) > 0.5


def test_welch_psd_of_a_long_realisation_matches_the_target():
    # Oracle: the target PSD. 400 s at 1 kHz. The narrow peaks decorrelate in ~0.4 s, so
    # the variance estimate has ~1000 independent samples (~3 % scatter at 1 sigma): 5 %.
    # The power within +-5 half-widths of each peak (Welch, 16 s segments, ~50 segments
    # and several bins per band): within 10 %.
    fs = 1000.0
    psd = VibrationPSD()
    x = TiltVibration(fs, _Basis(), 11).series(400_000)
    assert abs(x.var() / psd.variance - 1) < 0.05
    f, p = signal.welch(x, fs=fs, nperseg=2**14)
    for peak in psd.peaks:
        sel = np.abs(f - peak.frequency) < 5 * peak.damping * peak.frequency + 0.2
        ratio = np.trapezoid(p[sel], f[sel]) / np.trapezoid(psd(f[sel]), f[sel])
        assert abs(ratio - 1) < 0.1, (peak, ratio)


def test_frames_do_not_depend_on_how_a_run_is_split():
    # Invariant, bit for bit: the same seed gives the same frames whatever the calls.
    whole = TiltVibration(3000.0, _Basis(), 5).series(30_000)
    split = TiltVibration(3000.0, _Basis(), 5)
    parts = [split.series(n) for n in (1, 999, 8192, 0, 3333, 17475)]
    np.testing.assert_array_equal(np.concatenate(parts), whole)
    v = TiltVibration(3000.0, _Basis(), 5)
    maps = np.concatenate([v.phase_vectors(1000), v.phase_vectors(2000)])
    np.testing.assert_array_equal(maps, whole[:3000, None] * _Basis.modes[1][None, :])
    modal, _ = TiltVibration(3000.0, _Basis(), 5).next(500)
    np.testing.assert_array_equal(modal[:, 1], whole[:500])
    assert not modal[:, [0, 2]].any()
    other = TiltVibration(3000.0, _Basis(), 6).series(100)
    assert not np.array_equal(other, whole[:100])


class _Flat:
    """A zero atmosphere at a rate (so the cascade sees the vibration alone)."""

    def __init__(self, n_valid, fs):
        self.fs, self._n = fs, n_valid

    def phase_vectors(self, n):
        return np.zeros((n, self._n))


def test_both_stages_see_the_vibration():
    # The vibration is added to the phase: its tilt projects on each stage's tilt mode
    # (orthonormal KL modes: the coefficient itself), stage 1 seeing it averaged over its
    # frame.
    pupil = vlt_pupil(24)
    b1 = kl_basis(DeformableMirror(pupil, n_actuators=11), 20, r0=0.15)
    b2 = kl_basis(DeformableMirror(pupil, n_actuators=8), 8, r0=0.15)
    fs2, ratio, n = 3000.0, 3, 3000
    vib = TiltVibration(fs2, b1, 2)
    src = PhaseSource(_Flat(pupil.n_valid, fs2), additive=vib)
    s1 = Stage(Integrator(0.3, fs=fs2 / ratio, n_modes=20), LinearModalSensor(), 0.84)
    s2 = Stage(Integrator(0.4, fs=fs2, n_modes=8), LinearModalSensor(), 0.83)
    res = run_cascade(s1, s2, src, n, scheme="dcao", basis1=b1, basis2=b2)
    tilt = TiltVibration(fs2, b1, 2).series(n)
    # float32 projection: 1e-5 relative.
    scale = np.abs(tilt).max()
    np.testing.assert_allclose(
        res.stage1.telemetry["disturbance"][:, 1],
        tilt.reshape(-1, ratio).mean(axis=1),
        atol=1e-5 * scale,
    )
    # In stage-2 modes the tilt of basis 1 is (up to the DM-space difference) tilt again.
    tilt_in_2 = b2.project(b1.modes[1])
    assert abs(tilt_in_2[1]) > 0.99
    np.testing.assert_allclose(
        res.stage2.telemetry["disturbance"][:, 1], tilt * tilt_in_2[1], atol=1e-4 * scale
    )


def test_bad_input():
    with pytest.raises(ValueError, match="damping must be in"):
        VibrationPeak(50.0, 1.5, 1.0)
    with pytest.raises(ValueError, match="rms must be a finite number >= 0"):
        VibrationPeak(50.0, 0.01, -1.0)
    with pytest.raises(ValueError, match="frequency must be a finite number > 0"):
        VibrationPeak(-5.0, 0.01, 1.0)
    with pytest.raises(ValueError, match="98 Hz is not below the Nyquist frequency 75 Hz"):
        fir_from_psd(VibrationPSD(), 150.0)
    with pytest.raises(ValueError, match="numtaps must be odd"):
        fir_from_psd(VibrationPSD(), 1000.0, numtaps=100)
    with pytest.raises(ValueError, match="mode must be < 3"):
        TiltVibration(1000.0, _Basis(), 0, mode=3)
    assert tilt_vibration_psd([(50.0, 0.01, 2.0)]).variance == pytest.approx(4.0)
    assert VibrationPSD().scaled(2.0).variance == pytest.approx(4 * VibrationPSD().variance)
    assert len(DEFAULT_TILT_PEAKS) >= 3
