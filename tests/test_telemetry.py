"""Tests of aocontrol.synthesis.disturbance_from_telemetry (pseudo-open-loop PSDs)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal, stats

from aocontrol.analysis import residual_variance, welch_psd, white_noise_psd
from aocontrol.controllers import Integrator
from aocontrol.plant import frequency_response, loop_plant, measured_plant
from aocontrol.synthesis import (
    TelemetryPSD,
    default_nperseg,
    disturbance_from_telemetry,
    pseudo_open_loop,
)

FS = 1000.0
A_POLE = 0.9  # double real pole of the AR(2) disturbance (about 10 Hz wide at 1 kHz)
SIGMA_W = np.array([0.15, 0.3, 0.06])  # innovation std per mode
SIGMA_N = np.array([1.0, 2.0, 0.5])  # white measurement-noise std per mode
N_FRAMES = 2**17


def _simulate(d, noise, K, latency):
    """Closed loop frame by frame, vectorised over modes.

    Residual e[t] = d[t] - dm[t], DM position dm[t] = (1-f) u[t-k] + f u[t-k-1] (RTC latency
    k + f frames, linear interpolation), measurement m[t] = e[t-1] + n[t] (WFS integration of
    one frame), command u[t] = K.step(m[t]). Plant command -> measurement:
    G = z^-1 ((1-f) z^-k + f z^-(k+1)), as loop_plant.
    """
    k = math.floor(latency)
    f = latency - k
    n_frames, n_modes = d.shape
    m, u, e = (np.zeros((n_frames, n_modes)) for _ in range(3))
    K.reset()
    zero = np.zeros(n_modes)
    for t in range(n_frames):
        m[t] = (e[t - 1] if t else zero) + noise[t]
        u[t] = K.step(m[t])
        dm = (1 - f) * (u[t - k] if t >= k else zero) + f * (u[t - k - 1] if t >= k + 1 else zero)
        e[t] = d[t] - dm
    return m, u, e


def _ar2_psd(f, sigma_w):
    """One-sided PSD of d = w / (1 - a z^-1)^2 [units^2/Hz], shape (n_modes, n_freqs)."""
    zi = np.exp(-2j * np.pi * f / FS)
    return 2 * sigma_w[:, None] ** 2 / FS / np.abs(1 - A_POLE * zi)[None, :] ** 4


@pytest.fixture(scope="module")
def loop_data():
    rng = np.random.default_rng(20241122)
    w = rng.normal(size=(N_FRAMES, 3)) * SIGMA_W
    d = signal.lfilter([1.0], np.convolve([1, -A_POLE], [1, -A_POLE]), w, axis=0)
    noise = rng.normal(size=(N_FRAMES, 3)) * SIGMA_N
    latency = 0.83
    K = Integrator(0.4, fs=FS, n_modes=3)
    m, u, e = _simulate(d, noise, K, latency)
    return {"d": d, "n": noise, "m": m, "u": u, "e": e, "K": K, "plant": loop_plant(FS, latency)}


def test_pseudo_open_loop_is_delayed_disturbance_plus_noise(loop_data):
    # Oracle: m + G u = z^-1 d + n exactly (the controller drops out), to rounding.
    tol = 1e-9
    pol = pseudo_open_loop(loop_data["m"], loop_data["u"], loop_data["plant"])
    truth = np.vstack([np.zeros((1, 3)), loop_data["d"][:-1]]) + loop_data["n"]
    assert np.max(np.abs(pol - truth)) < tol * np.max(np.abs(truth))


def test_simulated_residual_matches_analysis_sensitivity(loop_data):
    # Oracle: the analysis convention e = S d - T n (S = 1/(1+GK)) predicts the simulated
    # residual variance; statistical tolerance for 1.3e5 correlated samples.
    tol = 0.05
    f = np.linspace(0.0, FS / 2, 20001)
    pred = residual_variance(
        loop_data["plant"],
        loop_data["K"],
        f,
        _ar2_psd(f, SIGMA_W),
        white_noise_psd(SIGMA_N**2, FS)[:, None] * np.ones(f.size),
    )
    sim = np.var(loop_data["e"][1000:], axis=0)
    assert np.max(np.abs(sim / pred - 1)) < tol


@pytest.mark.parametrize("method", ["prewhitened", "welch"])
def test_noise_and_disturbance_estimates(loop_data, method):
    # Oracle: the true white level 2 sigma_n^2 / fs; the true AR(2) PSD. Statistics: ~100
    # bins of a 256-segment Welch estimate in the noise band (median std ~1 %); disturbance
    # variance from the PSD vs. the sample variance of d (~1 %); the PSD itself averaged over
    # the ~30 bins where it exceeds the noise 10x (Welch std ~7 % per bin, neighbours
    # correlated, and the low-frequency content of one realisation: ~2.5 % over seeds).
    tol_noise, tol_var, tol_psd = 0.04, 0.05, 0.08
    est = disturbance_from_telemetry(
        loop_data["m"], loop_data["u"], loop_data["plant"], method=method
    )
    assert isinstance(est, TelemetryPSD) and est.method == method
    assert est.psd.shape == (3, est.freqs.size) and est.noise_psd.shape == (3,)
    assert np.max(np.abs(est.noise_psd / white_noise_psd(SIGMA_N**2, FS) - 1)) < tol_noise
    assert np.max(np.abs(est.noise_variance / SIGMA_N**2 - 1)) < tol_noise
    var_est = np.trapezoid(est.psd, est.freqs, axis=1)
    assert np.max(np.abs(var_est / np.var(loop_data["d"], axis=0) - 1)) < tol_var
    truth = _ar2_psd(est.freqs, SIGMA_W)
    # The bins of the Welch segment (the pre-whitened estimate's finer levels below its
    # second bin have fewer degrees of freedom: tested in test_telemetry_prediction.py).
    welch_bins = est.freqs >= 2 * FS / default_nperseg(N_FRAMES, method)
    for mode in range(3):
        strong = (truth[mode] > 10 * est.noise_psd[mode]) & welch_bins
        assert strong.sum() >= 5
        ratio = np.mean(est.psd[mode, strong] / truth[mode, strong])
        assert abs(ratio - 1) < tol_psd
    assert np.all(est.psd > 0)


def test_sloped_noise_band_is_reported(caplog):
    # Oracle: a POL PSD that falls across the noise band (8th-order low-pass at 0.85 Nyquist,
    # no white floor) is not a noise floor: a warning names the mode; white data does not warn.
    rng = np.random.default_rng(3)
    x = rng.normal(size=(2**14, 2))
    sos = signal.butter(8, 0.85, output="sos")
    m = np.column_stack([signal.sosfilt(sos, x[:, 0]), x[:, 1]])
    with caplog.at_level("WARNING", logger="aocontrol.synthesis._telemetry"):
        disturbance_from_telemetry(m, np.zeros_like(m), loop_plant(FS, 0.0), nperseg=256)
    assert "not flat" in caplog.text and "[0]" in caplog.text


@pytest.mark.parametrize(("n_frames", "method"), [(1500, "welch"), (1500, "prewhitened")])
def test_white_noise_is_flat_in_short_records(caplog, n_frames, method):
    # White noise has a flat noise band whatever the record: no warning over 400 modes of a
    # 0.5-s record at 3 kHz (one 1024-frame Welch segment, chi-square(2) bins; or 256-frame
    # segments with 12 bins per half band). The fixed 1.5 ratio flagged 10 or more modes of
    # each: the scatter of a half band's median is that wide there.
    rng = np.random.default_rng(5)
    m = rng.standard_normal((n_frames, 400))
    with caplog.at_level("WARNING", logger="aocontrol.synthesis._telemetry"):
        disturbance_from_telemetry(m, np.zeros_like(m), loop_plant(3000.0, 1.0), method=method)
    assert "not flat" not in caplog.text


def test_noise_band_extends_over_white_noise_and_stops_at_a_disturbance():
    # Oracle: white noise of unit PSD, plus in half the modes a disturbance 3x the noise up
    # to 400 Hz (fs = 3 kHz). The band (0.8-1.0 Nyquist) extends down to 0.1 Nyquist in the
    # white modes and stops above 400 Hz in every other; the level stays unbiased and its
    # per-mode scatter falls (the band alone holds 1/5 of the bins).
    from aocontrol.synthesis._welch_stats import _welch_dof, extended_noise_level

    fs, n, nperseg = 3000.0, 4096, 512
    rng = np.random.default_rng(11)
    x = rng.standard_normal((n, 400)) * math.sqrt(fs / 2)  # one-sided PSD 1
    sos = signal.butter(8, 400.0, fs=fs, output="sos")
    x[:, 200:] += (
        math.sqrt(3.0)
        * signal.sosfilt(sos, rng.standard_normal((n, 200)), axis=0)
        * (math.sqrt(fs / 2))
    )
    f, pxx = welch_psd(x, fs, nperseg)
    nyq = fs / 2
    band = (f >= 0.8 * nyq) & (f < nyq)
    first = int(np.searchsorted(f, 0.1 * nyq))
    dof = _welch_dof(n, nperseg)
    noise, lowest = extended_noise_level(pxx, band, dof, first)
    alone = np.median(pxx[:, band], axis=1) * dof / stats.chi2.median(dof)
    # (A 3-sigma check over some 200 octave windows per mode stops a white mode early now and
    # then: 2 of 200 here, which only narrows its band.)
    assert np.mean(lowest[:200] == first) > 0.95
    assert np.all(f[lowest[200:]] > 400.0)
    assert abs(np.mean(noise) - 1) < 0.02
    assert np.std(noise[:200]) < 0.6 * np.std(alone[:200])


def test_one_dimensional_telemetry_and_pure_delay():
    # Oracle: G = z^-1: pol[k] = m[k] + u[k-1], by hand.
    m = np.array([1.0, -2.0, 0.5, 3.0])
    u = np.array([0.1, 0.2, 0.3, 0.4])
    pol = pseudo_open_loop(m, u, loop_plant(FS, 0.0))
    assert np.allclose(pol[:, 0], [1.0, -1.9, 0.7, 3.3], rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    ("kwargs", "err", "match"),
    [
        ({"measurements": np.full((64, 2), np.nan)}, ValueError, "measurements must contain"),
        ({"commands": np.zeros((63, 2))}, ValueError, "same shape"),
        ({"commands": np.zeros((64, 3))}, ValueError, "same shape"),
        ({"measurements": np.zeros((64, 2, 1))}, ValueError, "dimension"),
        # The pre-whitened default loses one frame to the difference.
        ({"nperseg": 128}, ValueError, r"n_frames >= 129 for nperseg=128 pre-whitened.*\(64, 2\)"),
        (
            {"nperseg": 128, "method": "welch"},
            ValueError,
            r"n_frames >= 128 for nperseg=128, got \(64, 2\)",
        ),
        ({"method": "bartlett"}, ValueError, r"method must be one of \['prewhitened', 'welch'\]"),
        ({"nperseg": 4}, ValueError, "nperseg"),
        ({"noise_band": (0.9, 0.5)}, ValueError, "noise_band"),
        ({"noise_band": (0.0, 1.5)}, ValueError, "noise_band"),
        ({"noise_band": (0.999, 1.0)}, ValueError, "no Welch frequency bin"),
        (
            {
                "plant": measured_plant(
                    [0.0, 500.0], frequency_response(loop_plant(FS, 0.0), [0.0, 500.0]), FS
                )
            },
            TypeError,
            "TransferFunction",
        ),
    ],
)
def test_bad_input(kwargs, err, match):
    args = {
        "measurements": np.zeros((64, 2)),
        "commands": np.zeros((64, 2)),
        "plant": loop_plant(FS, 0.5),
        "nperseg": 32,
        **kwargs,
    }
    with pytest.raises(err, match=match):
        disturbance_from_telemetry(
            args.pop("measurements"), args.pop("commands"), args.pop("plant"), **args
        )


@pytest.mark.parametrize("shape", [(5, 300), (1, 40)])
def test_short_or_transposed_telemetry_blames_the_telemetry(shape):
    # Before: "nperseg must be an integer >= 8, got 5", an argument the user never passed.
    with pytest.raises(ValueError, match=r"must have shape \(n_frames, n_modes\).*transposed"):
        disturbance_from_telemetry(np.zeros(shape), np.zeros(shape), loop_plant(FS, 0.5))
    with pytest.raises(ValueError, match=r"x must have shape.*transposed"):
        welch_psd(np.zeros((1, 40)), fs=FS)


def test_prewhitening_removes_the_window_leakage_of_a_steep_spectrum():
    # Oracle: d = AR(2) with a double pole at 0.999 (corner 0.16 Hz at 1 kHz, PSD ~ f^-4
    # above it, far below the first Welch bin of a 256-frame segment at 3.9 Hz), open loop
    # (u = 0), a tiny white floor. The true PSD 2 s^2 / fs / |1 - a z^-1|^4 at 5-20 Hz is
    # what the pre-whitened estimate finds (within 25 %: Welch scatter of 127 segments over
    # 4 bins, and the leakage left by the f^-2 differenced spectrum, measured +18 %); the
    # plain Welch estimate is swamped there by the Hann window's leakage of the sub-bin
    # variance (the twin: measured 7x, asserted > 3x).
    rng = np.random.default_rng(7)
    n, a = 2**14, 0.999
    d = signal.lfilter([1.0], np.convolve([1, -a], [1, -a]), rng.normal(size=(n, 1)), axis=0)
    m = d + 1e-3 * rng.normal(size=(n, 1))
    plant = loop_plant(FS, 0.0)
    pre = disturbance_from_telemetry(m, np.zeros_like(m), plant, nperseg=256)
    plain = disturbance_from_telemetry(m, np.zeros_like(m), plant, nperseg=256, method="welch")
    f = pre.freqs
    band = (f >= 5.0) & (f <= 20.0)
    truth = 2 / FS / np.abs(1 - a * np.exp(-2j * np.pi * f[band] / FS)) ** 4
    assert abs(np.mean(pre.psd[0, band] / truth) - 1) < 0.25
    fp = plain.freqs
    band_p = (fp >= 5.0) & (fp <= 20.0)
    truth_p = 2 / FS / np.abs(1 - a * np.exp(-2j * np.pi * fp[band_p] / FS)) ** 4
    assert np.mean(plain.psd[0, band_p] / truth_p) > 3
    # It integrates to the record's variance minus the noise (the variance the differenced
    # record cannot see put back in the 0-Hz bin).
    target = np.var(pre.pseudo_open_loop[:, 0]) - pre.noise_variance[0]
    assert abs(np.trapezoid(pre.psd[0], f) / target - 1) < 1e-9


def test_default_segment_gives_eight_segments():
    # Oracle: 2 n / (nperseg) - 1 >= 8 half-overlapped segments, nperseg a power of 2 in
    # [64, 1024]; the plain estimate keeps min(n, 1024).
    for n in (600, 4096, 10_000, 2**20):
        seg = default_nperseg(n)
        assert seg & (seg - 1) == 0 and 64 <= seg <= 1024
        assert 2 * n // seg - 1 >= 8 or seg == 64
        assert seg == 1024 or 2 * n // (2 * seg) - 1 < 8
    assert default_nperseg(500, "welch") == 500


@pytest.mark.parametrize("method", ["prewhitened", "welch"])
def test_blocks_and_threads_give_each_mode_its_own_estimate(method, monkeypatch):
    # Invariant (issue 34): every step is per mode, so the estimate of a mode is the one it
    # gets alone (to rounding: numpy sums a column and a block's columns in other orders),
    # in blocks of any size, and the same bits on one thread or several.
    from aocontrol.synthesis import _telemetry

    rng = np.random.default_rng(7)
    n_frames, n_modes = 3000, 7
    m = np.cumsum(rng.normal(size=(n_frames, n_modes)), axis=0) * 0.01
    m += rng.normal(size=m.shape) * np.linspace(0.5, 2.0, n_modes)
    u = rng.normal(size=m.shape) * 0.1
    plant = loop_plant(FS, 0.7)
    og = np.linspace(0.6, 1.0, n_modes)
    alone = [
        disturbance_from_telemetry(m[:, [i]], u[:, [i]], plant, method=method, optical_gain=og[i])
        for i in range(n_modes)
    ]
    monkeypatch.setattr(_telemetry, "_BLOCK_MODES", 3)  # blocks of 3, 3 and 1 modes
    one_thread, two = (
        disturbance_from_telemetry(m, u, plant, method=method, optical_gain=og, n_jobs=n_jobs)
        for n_jobs in (1, 2)
    )
    for name in ("freqs", "psd", "pol_psd", "noise_psd", "pseudo_open_loop"):
        assert np.array_equal(getattr(one_thread, name), getattr(two, name)), name
    for i, one in enumerate(alone):
        assert np.array_equal(two.freqs, one.freqs)
        np.testing.assert_allclose(two.psd[i], one.psd[0], rtol=1e-9, err_msg=str(i))
        np.testing.assert_allclose(two.pol_psd[i], one.pol_psd[0], rtol=1e-9)
        np.testing.assert_allclose(two.noise_psd[i], one.noise_psd[0], rtol=1e-9)
        np.testing.assert_array_equal(two.pseudo_open_loop[:, i], one.pseudo_open_loop[:, 0])
    # Twin: a mode's own optical gain changes its estimate (the blocks get their own slice).
    moved = disturbance_from_telemetry(m, u, plant, method=method, optical_gain=og[::-1])
    assert not np.array_equal(moved.psd[0], alone[0].psd[0])


def test_n_jobs_zero_is_refused():
    with pytest.raises(ValueError, match="n_jobs must be a nonzero integer"):
        disturbance_from_telemetry(
            np.zeros((64, 2)), np.zeros((64, 2)), loop_plant(FS, 0.5), n_jobs=0
        )
