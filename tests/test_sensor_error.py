"""The sensor's error beyond its linear response (aocontrol.synthesis._sensor_error).

Oracle: a synthetic closed loop simulated exactly with scipy.signal.lfilter (plant
``z^-1 z^-1``, an integrator, a low-frequency disturbance and an injected coloured
measurement error ``v``, no pyramid): the error's PSD is known analytically, and the residual
``e = S d - T v`` of any gain is known from the same records.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from aocontrol.analysis import residual_variance
from aocontrol.controllers import Integrator
from aocontrol.plant import loop_plant
from aocontrol.synthesis import (
    disturbance_from_telemetry,
    sensor_error_psd,
    split_sensor_error,
)

FS, N, MODES = 1000.0, 2**14, 3
# v = white noise through a one-pole low-pass of pole A_V, coloured like an aliased
# turbulence (an ~8 Hz corner), most of its variance where |T| ~ 1.
A_V = 0.95
SIGMA_V = np.array([1.0, 2.0, 0.5])
# Disturbance: white noise through a pole at 0.995 (a ~0.8 Hz corner), RMS ~ 10 sigma_v.
A_D, SIGMA_D = 0.995, 1.0


def _v_psd(f: np.ndarray) -> np.ndarray:
    """One-sided PSD of v: sigma^2 2/fs |1 / (1 - a z^-1)|^2 [units^2/Hz]."""
    z1 = np.exp(-2j * np.pi * f / FS)
    return SIGMA_V[:, None] ** 2 * 2.0 / FS / np.abs(1 - A_V * z1) ** 2


def _loop(gain: float, seed: int = 3):
    """Records (m, u, e, v) of the loop with ``u = g/(1 - z^-1) m``, plant ``z^-2``.

    Exact: ``m = S pol`` with ``pol = z^-1 d + v``, ``S = (1 - z^-1) / (1 - z^-1 + g z^-2)``;
    the residual follows from ``m = z^-1 e + v``.
    """
    rng = np.random.default_rng(seed)
    d = signal.lfilter([SIGMA_D], [1, -A_D], rng.standard_normal((N + 1, MODES)), axis=0)
    v = signal.lfilter([1.0], [1, -A_V], rng.standard_normal((N + 1, MODES)), axis=0) * SIGMA_V
    pol = np.vstack([np.zeros((1, MODES)), d[:-1]]) + v
    m = signal.lfilter([1, -1], [1, -1, gain], pol, axis=0)
    u = signal.lfilter([gain], [1, -1], m, axis=0)
    e = (m - v)[1:]  # e[k] = m[k+1] - v[k+1]
    return m[:-1], u[:-1], e, v[:-1]


@pytest.fixture(scope="module")
def loop():
    return _loop(0.3)


def test_recovers_known_error_psd(loop):
    m, u, e, _ = loop
    plant = loop_plant(FS, 1.0)
    err = sensor_error_psd(m, e, plant)
    band = (err.freqs > 2.0) & (err.freqs < 0.95 * FS / 2)
    rel = err.psd[:, band] / _v_psd(err.freqs[band]) - 1
    # Welch scatter of ~30 segments: 26 % per bin; its median over hundreds of bins is
    # within a few %; 10 % allows the window's leakage near the 30-Hz corner.
    assert np.all(np.abs(np.median(rel, axis=1)) < 0.10)
    var = np.trapezoid(err.psd, err.freqs, axis=1)
    # The record's variance conserved by the estimator (its step 7) to its trapezoid error
    # (5 %); the record's own variance scatters by ~5 % around sigma^2 / (1 - a^2).
    np.testing.assert_allclose(var, err.variance, rtol=0.05)
    np.testing.assert_allclose(err.variance, SIGMA_V**2 / (1 - A_V**2), rtol=0.15)


@pytest.mark.parametrize("gain", [0.3, 0.6])
def test_prediction_with_error_apart(loop, gain):
    """The calibration (gain 0.3) predicts the residual at its own gain and at another
    (independent records), within 5 %; the white-noise split of the telemetry does not
    (its twin: > 15 % low, the coloured error counted as disturbance through |S|^2)."""
    m, u, e, _ = loop
    plant = loop_plant(FS, 1.0)
    tel = disturbance_from_telemetry(m, u, plant)
    psd, noise = split_sensor_error(tel, sensor_error_psd(m, e, plant))
    ctrl = Integrator(np.full(MODES, gain), fs=FS, n_modes=MODES)
    measured = _loop(gain, seed=11)[2].var(axis=0)
    new = residual_variance(plant, ctrl, tel.freqs, psd, noise) / measured
    old = residual_variance(plant, ctrl, tel.freqs, tel.psd, tel.noise_psd) / measured
    # 5 %: Welch scatter of the variance of 16k frames of a ~30-Hz process, and the
    # estimator's trapezoid error below its finest bin.
    assert np.all(np.abs(np.sqrt(new) - 1) < 0.05), np.sqrt(new)
    assert np.all(np.sqrt(old) < 0.85), np.sqrt(old)


def test_gain_scan_cannot_separate(loop):
    """Why the error comes from a sensor model: the pseudo-open loop of a loop-independent
    error is the same signal at every gain, so two gains give one equation."""
    plant = loop_plant(FS, 1.0)
    m1, u1, _, _ = loop
    m2, u2, _, _ = _loop(0.6)
    p1 = disturbance_from_telemetry(m1, u1, plant).pol_psd
    p2 = disturbance_from_telemetry(m2, u2, plant).pol_psd
    np.testing.assert_allclose(p1, p2, rtol=1e-6)


def test_split_refuses_other_modes(loop):
    m, u, e, _ = loop
    plant = loop_plant(FS, 1.0)
    tel = disturbance_from_telemetry(m, u, plant)
    err = sensor_error_psd(m[:, :2], e[:, :2], plant)
    with pytest.raises(ValueError, match="error has 2 modes"):
        split_sensor_error(tel, err)
    with pytest.raises(ValueError, match="measurements and residuals"):
        sensor_error_psd(m, e[:, :2], plant)


def test_loop_gain_oracle():
    """White noise through T of g/(z-1), plant z^-1: variance g'/(2-g') per unit with the
    loop's gain g' = loop_gain * g."""
    plant = loop_plant(FS, 0.0)
    f = np.linspace(0, FS / 2, 20001)
    k = Integrator(np.array([0.25, 0.5]), fs=FS, n_modes=2)
    v = residual_variance(plant, k, f, np.zeros((2, f.size)), 2.0 / FS, loop_gain=[2.0, 1.2])
    np.testing.assert_allclose(v, [0.5 / 1.5, 0.6 / 1.4], rtol=1e-4)
    with pytest.raises(ValueError, match="loop_gain must be"):
        residual_variance(plant, k, f, np.zeros((2, f.size)), 2.0 / FS, loop_gain=[1.0, -1.0])
    # A loop gain that destabilises the loop (g' = 2.5 > 2): infinite, as for the gain itself.
    assert np.isinf(
        residual_variance(plant, k, f, np.zeros((2, f.size)), 2.0 / FS, loop_gain=[1.0, 5.0])
    )[1]
