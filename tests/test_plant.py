"""Loop models: the fractional-delay plant and measured (FRD) plants."""

import control
import numpy as np
import pytest

from aocontrol import frequency_response, loop_plant, measured_plant
from aocontrol.plant import (
    check_system,
    plant_delay_frames,
    plant_fs,
    tf_from_z_inverse,
    z_inverse_coefficients,
)

# Exact polynomial evaluation on the unit circle: only rounding error.
EXACT = 1e-12


@pytest.mark.parametrize("latency", [0.0, 0.3, 0.83, 1.0, 1.5, 2.7])
def test_fractional_delay_plant_matches_formula(latency):
    # Oracle: G(e^{jw}) = e^{-jw} ((1-f) e^{-jkw} + f e^{-j(k+1)w}), k = floor, f = frac.
    fs = 3000.0
    G = loop_plant(fs, latency)
    f = np.linspace(0, fs / 2, 257)
    w = 2 * np.pi * f / fs
    k, fr = np.floor(latency), latency - np.floor(latency)
    expected = np.exp(-1j * w) * ((1 - fr) * np.exp(-1j * k * w) + fr * np.exp(-1j * (k + 1) * w))
    np.testing.assert_allclose(frequency_response(G, f), expected, atol=EXACT)
    # python-control's own evaluation agrees with ours.
    np.testing.assert_allclose(G(np.exp(1j * w[1:-1])), expected[1:-1], atol=1e-10)


def test_plant_is_discrete_with_dt():
    G = loop_plant(1250.0, 0.83)
    assert isinstance(G, control.TransferFunction)
    assert G.dt == pytest.approx(1 / 1250.0, rel=EXACT)


@pytest.mark.parametrize("latency", [0.0, 0.5, 0.83, 2.0])
def test_low_frequency_delay_is_one_plus_latency(latency):
    # Oracle: group delay at DC of z^-1((1-f)z^-k + f z^-(k+1)) is 1 + k + f frames.
    assert plant_delay_frames(loop_plant(1000.0, latency)) == pytest.approx(1 + latency, abs=1e-6)


def test_integer_latency_from_float_noise_is_integer():
    # 0.1 * 3 = 0.30000000000000004: f must not become a spurious 1e-17 extra tap.
    G = loop_plant(1000.0, 3 * (1.0 / 3.0))
    b, _ = z_inverse_coefficients(G)
    assert np.count_nonzero(b) == 1


def test_tf_coefficients_round_trip():
    b, a = [0.2, 0.1, 0.05], [1.0, -0.9, 0.1, 0.02]
    bb, aa = z_inverse_coefficients(tf_from_z_inverse(b, a, 1e-3))
    np.testing.assert_allclose(bb[: len(b)], b, atol=EXACT)
    np.testing.assert_allclose(aa, a, atol=EXACT)


def test_measured_plant_keeps_dt_and_reproduces_tf():
    fs = 2000.0
    G = loop_plant(fs, 0.83)
    f = np.linspace(0, fs / 2, 401)
    P = measured_plant(f, frequency_response(G, f), fs)
    assert isinstance(P, control.FRD)
    assert plant_fs(P) == pytest.approx(fs)
    np.testing.assert_allclose(frequency_response(P, f), frequency_response(G, f), atol=EXACT)
    # Between grid points: log-magnitude/phase interpolation of a smooth response.
    fm = 0.5 * (f[1:] + f[:-1])
    np.testing.assert_allclose(frequency_response(P, fm), frequency_response(G, fm), atol=1e-3)


def test_frd_that_lost_dt_needs_fs():
    # python-control 0.10.2 resets dt to 0 on FRD arithmetic: we must notice, not guess.
    fs = 1000.0
    f = np.linspace(0, fs / 2, 11)
    P = measured_plant(f, np.exp(-2j * np.pi * f / fs), fs) * 1.0
    with pytest.raises(ValueError, match="pass fs explicitly"):
        frequency_response(P, f)
    np.testing.assert_allclose(
        frequency_response(P, f, fs=fs), np.exp(-2j * np.pi * f / fs), atol=EXACT
    )


def test_frd_outside_measured_range_raises():
    fs = 1000.0
    P = measured_plant(np.linspace(10, 400, 20), np.ones(20), fs)
    with pytest.raises(ValueError, match="measured range"):
        frequency_response(P, [450.0])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"fs": 0.0, "latency_frames": 0.5}, "fs must be a finite number > 0, got 0.0"),
        ({"fs": -10.0, "latency_frames": 0.5}, "fs must be a finite number > 0"),
        ({"fs": float("nan"), "latency_frames": 0.5}, "fs must be a finite number > 0"),
        ({"fs": 1000.0, "latency_frames": -0.1}, "latency_frames must be a finite number >= 0"),
        ({"fs": 1000.0, "latency_frames": float("inf")}, "latency_frames"),
    ],
)
def test_loop_plant_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        loop_plant(**kwargs)


def test_loop_plant_type_errors():
    with pytest.raises(TypeError, match="fs must be a real number"):
        loop_plant("1000", 0.5)


def test_continuous_time_plant_rejected():
    Gc = control.tf([1], [1, 1])
    with pytest.raises(ValueError, match="discrete-time"):
        frequency_response(Gc, [1.0])
    with pytest.raises(ValueError, match="continuous"):
        frequency_response(Gc, [1.0], fs=1000.0)


def test_frequency_beyond_nyquist_rejected():
    with pytest.raises(ValueError, match="fs/2"):
        frequency_response(loop_plant(1000.0, 0.0), [600.0])


def test_measured_plant_bad_input():
    with pytest.raises(ValueError, match="strictly increasing"):
        measured_plant([1.0, 1.0, 2.0], [1, 1, 1], 100.0)
    with pytest.raises(ValueError, match="Nyquist"):
        measured_plant([1.0, 60.0], [1, 1], 100.0)
    with pytest.raises(ValueError, match="finite"):
        measured_plant([1.0, 2.0], [1, np.nan], 100.0)
    with pytest.raises(ValueError, match="shape of freqs"):
        measured_plant([1.0, 2.0], [1, 1, 1], 100.0)


def test_frd_covering_the_band_is_held_over_the_end_gap_only():
    # A grid ending half a step short of Nyquist covers [0, fs/2] (FRD_END_GAP_FRACTION):
    # the last value is held there; a frequency beyond a real gap still raises.
    fs, n = 1000.0, 51
    f = np.arange(n) * fs / (2 * n - 1)
    resp = np.exp(-2j * np.pi * f / fs)
    P = measured_plant(f, resp, fs)
    assert frequency_response(P, [fs / 2]) == pytest.approx(resp[-1], abs=EXACT)
    partial = measured_plant(f[:40], resp[:40], fs)
    with pytest.raises(ValueError, match="measured range"):
        frequency_response(partial, [fs / 2])


def test_check_system_reads_dt_types_not_values():
    # python-control keeps dt=True ("unspecified") distinct from dt=1.0; True == 1.0 in Python.
    assert check_system("plant", control.tf([1.0], [1.0, 0.0], 1.0)) == 1.0
    with pytest.raises(ValueError, match="plant must be discrete-time.*unspecified.*pass fs"):
        check_system("plant", control.tf([1.0], [1.0, 0.0], True))
    assert check_system("plant", control.tf([1.0], [1.0, 0.0], True), 50.0) == 50.0
    with pytest.raises(ValueError, match="controller must be a discrete-time transfer function"):
        check_system("controller", control.tf([1.0], [1.0, 1.0]), 50.0)


@pytest.mark.parametrize("fs", [0.6608, 1.0, 9.388e5])
@pytest.mark.parametrize("grid", ["linear", "log", "random"])
def test_frd_over_exactly_zero_to_nyquist_is_accepted(fs, grid):
    # An FRD measured on exactly [0, fs/2] stores omega = 2 pi f; read back as omega / 2 pi its
    # last point may exceed fs/2 by an ulp (0.3304000000000001 at fs = 0.6608). The analysis
    # grid ends at fs/2 and must still fall inside the measured range (one tolerance, FREQ_RTOL).
    # Oracle: the FRD samples the TF plant, so the verdict and the margin are the TF's.
    from aocontrol.analysis import is_stable, margins
    from aocontrol.controllers import Integrator

    nyq = fs / 2
    if grid == "linear":
        f = np.linspace(0.0, nyq, 300)
    elif grid == "log":
        f = np.concatenate([[0.0], np.geomspace(1e-4 * nyq, nyq, 299)])
    else:
        f = np.sort(np.random.default_rng(3).uniform(0.0, nyq, 300))
        f[0], f[-1] = 0.0, nyq
    G = loop_plant(fs, 1.0)
    P = measured_plant(f, frequency_response(G, f), fs)
    C = Integrator(gain=0.3, fs=fs)
    assert is_stable(P, C) and is_stable(G, C)
    # The modulus margin from a 300-point FRD against the exact TF: the grid's resolution.
    assert margins(P, C).modulus_margin == pytest.approx(margins(G, C).modulus_margin, rel=1e-3)
    assert frequency_response(P, [nyq]) == pytest.approx(frequency_response(G, [nyq]), abs=1e-9)
