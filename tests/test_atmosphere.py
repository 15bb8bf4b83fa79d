"""Tests of the multi-layer frozen-flow atmosphere and the turbulence profiles.

Physics oracles: the von Kármán covariance ``B(r)`` and structure function
``D(r) = 2 (B(0) - B(r))`` of :mod:`aocontrol.sim.turbulence`. Linear statistics of a
screen sampled on the pupil pixels (tip/tilt, piston-removed variance, correlation between
shifted pupils) follow exactly from the covariance matrix of those pixels, ``a^T C a``; that
is the oracle for the low orders. Statistical tests use a fixed seed and tolerances several
standard deviations of the estimator wide.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from aocontrol.sim._screens import Extruder, fft_screens
from aocontrol.sim.atmosphere import Atmosphere, Layer
from aocontrol.sim.profiles import (
    compress_profile,
    effective_altitude,
    eso_atmosphere,
    eso_median_profile,
    isoplanatic_angle,
    normalize_layers,
    scale_to_tau0,
)
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.turbulence import (
    effective_wind_speed,
    opd_per_radian,
    phase_covariance,
    r0_from_seeing,
    structure_function,
    tau0,
)

L0 = 25.0
R0 = 1.0  # r0 = 1 m: statistics scale exactly as r0^(-5/3), the value is immaterial
NM2 = opd_per_radian() ** 2  # rad^2 at 500 nm -> nm^2
# Statistical tolerance of the brief: physics within 10 %. Each estimator below has a
# standard deviation of 1-3 %, so 10 % is >= 3 sigma.
STAT_TOL = 0.10
# Frozen-flow identities hold to floating-point rounding of the interpolation weights.
EXACT_RTOL = 1e-9


# ---------------------------------------------------------------------------- helpers
def _pixel_covariance(pupil: Pupil, shift=(0.0, 0.0)) -> np.ndarray:
    """Covariance [nm^2] between pupil pixels and pupil pixels shifted by ``shift`` [m]."""
    y, x = pupil.y[pupil.mask], pupil.x[pupil.mask]
    d = np.hypot(y[:, None] + shift[0] - y[None, :], x[:, None] + shift[1] - x[None, :])
    return phase_covariance(d, R0, L0) * NM2


def _tilt_projector(pupil: Pupil) -> np.ndarray:
    """Least-squares (x, y) tilt [nm/m] from phases on valid pixels, shape (2, n_valid)."""
    x, y = pupil.x[pupil.mask], pupil.y[pupil.mask]
    return np.linalg.pinv(np.column_stack([np.ones_like(x), x, y]))[1:]


def _piston_removal(n: int) -> np.ndarray:
    return np.eye(n) - 1.0 / n


def _sf_x(maps: np.ndarray, mask: np.ndarray, seps) -> np.ndarray:
    """Empirical structure function [nm^2] along x (columns), pairs inside ``mask``."""
    out = []
    for s in seps:
        both = mask[:, s:] & mask[:, :-s]
        diff = (maps[..., :, s:] - maps[..., :, :-s])[..., both]
        out.append(np.mean(diff**2))
    return np.array(out)


def _theory_sf(seps_pix, dx: float) -> np.ndarray:
    return structure_function(np.asarray(seps_pix) * dx, R0, L0) * NM2


def _moving_layer(
    pupil: Pupil, pixels_per_frame: tuple[float, float], fs: float = 1000.0, fraction: float = 1.0
) -> Layer:
    """A layer whose screen moves by (dy, dx) pixels per frame."""
    dy, dxp = pixels_per_frame
    speed = math.hypot(dy, dxp) * pupil.pixel_scale * fs
    return Layer(0.0, fraction, speed, math.degrees(math.atan2(dy, dxp)))


# ---------------------------------------------------------------------------- screens
def test_initial_fft_screen_matches_von_karman():
    # Oracle: structure function D(r) of von Kármán (separations 2 px = 1 m to 15 px = 7.5 m
    # ~ D) and tip/tilt variance a^T C a from the pixel covariance. 4000 independent FFT +
    # subharmonic screens (L0 = 25 m, larger than the 32 px = 16 m screen): tip/tilt
    # estimates have a 1.6 % standard deviation.
    pupil = Pupil(n_pix=16)
    dx = pupil.pixel_scale
    screens = fft_screens(4000, 32, dx, L0, np.random.default_rng(0)) * opd_per_radian()
    seps = [2, 4, 8, 12, 15]
    crop = screens[:, :16, :16]
    ratio_sf = _sf_x(crop, pupil.mask, seps) / _theory_sf(seps, dx)
    assert np.all(np.abs(ratio_sf - 1) < STAT_TOL), ratio_sf
    proj = _tilt_projector(pupil)
    tt = crop.reshape(len(crop), -1)[:, pupil.index] @ proj.T
    theory_tt = np.diag(proj @ _pixel_covariance(pupil) @ proj.T)
    ratio_tt = tt.var(axis=0) / theory_tt
    assert np.all(np.abs(ratio_tt - 1) < STAT_TOL), ratio_tt


@pytest.fixture(scope="module")
def long_run():
    """Two layers moving by whole pixels (4 px/frame along +x and +y): frames are exact
    screen samples, 20000 frames = 40 km of extruded screen per layer (1600 L0)."""
    pupil = Pupil(n_pix=16)
    layers = [
        _moving_layer(pupil, (0, 4), fraction=0.5),
        _moving_layer(pupil, (4, 0), fraction=0.5),
    ]
    atm = Atmosphere(pupil, R0, layers, fs=1000.0, L0=L0, rng=2)
    return pupil, atm.phase(20000)


def test_extruded_screen_matches_von_karman(long_run):
    # Oracle: as above, now for the extruded screens far from the initial one (frames
    # >= 200, i.e. > 30 screen lengths). 20000 frames, a new independent tip/tilt every
    # ~L0 = 50 px of travel: ~1600 x 2 samples, 2.5 % standard deviation. Also the
    # piston-removed pupil variance, tr(Q C Q) / n_valid.
    pupil, maps = long_run
    far = maps[200:]
    seps = [2, 4, 8, 12, 15]
    ratio_sf = _sf_x(far, pupil.mask, seps) / _theory_sf(seps, pupil.pixel_scale)
    assert np.all(np.abs(ratio_sf - 1) < STAT_TOL), ratio_sf
    proj = _tilt_projector(pupil)
    tt = far.reshape(len(far), -1)[:, pupil.index] @ proj.T
    theory_tt = np.diag(proj @ _pixel_covariance(pupil) @ proj.T)
    ratio_tt = tt.var(axis=0) / theory_tt
    assert np.all(np.abs(ratio_tt - 1) < STAT_TOL), ratio_tt
    v = far.reshape(len(far), -1)[:, pupil.index]
    q = _piston_removal(pupil.n_valid)
    theory_var = np.trace(q @ _pixel_covariance(pupil) @ q) / pupil.n_valid
    ratio_var = v.var(axis=1).mean() / theory_var
    assert abs(ratio_var - 1) < STAT_TOL, ratio_var


def test_extrusion_is_stationary(long_run):
    # Invariant: the statistics far along the extrusion equal those of the initial screen
    # (frame 0 of 400 independent atmospheres): piston-removed variance over the pupil and
    # structure function at 2-12 px. Both estimates have 2-3 % standard deviations.
    pupil, maps = long_run
    layers = [
        _moving_layer(pupil, (0, 4), fraction=0.5),
        _moving_layer(pupil, (4, 0), fraction=0.5),
    ]
    start = np.concatenate(
        [Atmosphere(pupil, R0, layers, fs=1000.0, L0=L0, rng=1000 + s).phase(1) for s in range(400)]
    )
    far = maps[200:]

    def stats(m):
        v = m.reshape(len(m), -1)[:, pupil.index]
        return np.concatenate([[v.var(axis=1).mean()], _sf_x(m, pupil.mask, [2, 6, 12])])

    ratio = stats(far) / stats(start)
    assert np.all(np.abs(ratio - 1) < STAT_TOL), ratio


def _interpolated_sf(seps_pix, dx: float, weights, taps) -> np.ndarray:
    """Structure function along x [nm^2] of a screen interpolated with ``weights`` at
    offsets ``taps`` [pixels]: I(x) = sum_m w_m phi(x + m dx). Exact for a Gaussian field:
    D_I(r) = sum_{m,m'} w_m w_m' ([D(r + d) + D(|r - d|)] / 2 - D(|d|)), d = (m - m') dx."""
    r = np.asarray(seps_pix, dtype=float) * dx
    out = np.zeros_like(r)
    for ma, wa in zip(taps, weights, strict=True):
        for mb, wb in zip(taps, weights, strict=True):
            d = (ma - mb) * dx
            pair = 0.5 * (
                structure_function(r + d, R0, L0) + structure_function(np.abs(r - d), R0, L0)
            )
            out += wa * wb * (pair - structure_function(abs(d), R0, L0))
    return out * NM2


@pytest.mark.parametrize(
    "interpolation, weights, taps",
    [
        ("linear", (0.5, 0.5), (0, 1)),
        ("cubic", (-1 / 16, 9 / 16, 9 / 16, -1 / 16), (-1, 0, 1, 2)),  # Keys a = -1/2 at f = 1/2
    ],
)
def test_interpolation_structure_function(interpolation, weights, taps):
    # Oracle: the exact structure function of the interpolated Gaussian field (see
    # _interpolated_sf). A layer moving 4.5 px/frame along x is sampled at a fraction
    # f = 0 of a pixel (even frames: D itself) and f = 1/2 (odd frames, the worst case).
    pupil = Pupil(n_pix=16)
    dx = pupil.pixel_scale
    atm = Atmosphere(
        pupil,
        R0,
        [_moving_layer(pupil, (0, 4.5))],
        fs=1000.0,
        L0=L0,
        rng=3,
        interpolation=interpolation,
    )
    maps = atm.phase(6000)[100:]
    seps = np.array([1, 2, 4, 8])
    d = _theory_sf(seps, dx)
    d_half = _interpolated_sf(seps, dx, weights, taps)
    ratio_exact = _sf_x(maps[0::2], pupil.mask, seps) / d
    ratio_half = _sf_x(maps[1::2], pupil.mask, seps) / d_half
    assert np.all(np.abs(ratio_exact - 1) < STAT_TOL), ratio_exact
    assert np.all(np.abs(ratio_half - 1) < STAT_TOL), ratio_half
    # The test discriminates: at 1 px the interpolated D is 0.66 D (linear), 0.78 D (cubic).
    assert d_half[0] / d[0] < 1 - 2 * STAT_TOL


# ---------------------------------------------------------------------------- frozen flow
@pytest.mark.parametrize(
    "shift, interpolation",
    [
        ((0, 1), "linear"),
        ((1, 0), "linear"),
        ((0, -1), "linear"),
        ((-1, 0), "linear"),
        ((1, 2), "linear"),
        ((-2, 1), "linear"),
        ((-1, -1), "linear"),
        ((-2, 1), "cubic"),
    ],
)
def test_frozen_flow_shift_and_direction(shift, interpolation):
    # Invariant: phi_{k+n}(x) = phi_k(x - v n dt). The layer moves by `shift` (dy, dx)
    # pixels every 7 frames, towards wind_direction = atan2(dy, dx): frame k+7 is frame k
    # translated by `shift` (same interpolation fractions), through many extrusions.
    pupil = Pupil(n_pix=16, obstruction=0.0)
    n_sub = 7
    layer = _moving_layer(pupil, (shift[0] / n_sub, shift[1] / n_sub))
    assert math.isclose(layer.wind_direction, math.degrees(math.atan2(*shift)))
    maps = Atmosphere(
        pupil, R0, [layer], fs=1000.0, L0=L0, rng=4, interpolation=interpolation
    ).phase(400)
    dy, dxp = shift
    n = pupil.n_pix
    src = (slice(max(0, -dy), n - max(0, dy)), slice(max(0, -dxp), n - max(0, dxp)))
    dst = (slice(max(0, dy), n - max(0, -dy)), slice(max(0, dxp), n - max(0, -dxp)))
    mask = pupil.mask[src] & pupil.mask[dst]
    before = maps[:-n_sub][:, src[0], src[1]][:, mask]
    after = maps[n_sub:][:, dst[0], dst[1]][:, mask]
    scale = np.sqrt(np.mean(before**2))
    np.testing.assert_allclose(after, before, rtol=0, atol=EXACT_RTOL * scale)
    # and the frames do change: the screen is not static
    assert np.sqrt(np.mean((maps[n_sub] - maps[0]) ** 2)) > 0.1 * scale


def test_long_run_has_no_wrap_around():
    # Oracle: the correlation of the piston-removed pupil phase with itself after the
    # screen moved by l, rho(l) = tr(Q C(l) Q) / tr(Q C(0) Q) from the pixel covariance.
    # 1 px/frame for 6000 frames = 190 screen lengths; periodic screens would give rho = 1
    # at their period (64 px for the FFT grid, 32 px for the stored screen).
    pupil = Pupil(n_pix=16)
    atm = Atmosphere(pupil, R0, [_moving_layer(pupil, (0, 1))], fs=1000.0, L0=L0, rng=5)
    v = atm.phase_vectors(6000)
    v = v - v.mean(axis=1, keepdims=True)
    q = _piston_removal(pupil.n_valid)
    c0 = np.trace(q @ _pixel_covariance(pupil) @ q)
    for lag in (atm.screen_size, 2 * atm.screen_size, 3 * atm.screen_size):
        rho = np.sum(v[:-lag] * v[lag:]) / np.sqrt(np.sum(v[:-lag] ** 2) * np.sum(v[lag:] ** 2))
        # the wind moves the screen by +x: frame k+lag sees the screen at x - lag dx
        c = _pixel_covariance(pupil, shift=(0.0, -lag * pupil.pixel_scale))
        rho_theory = np.trace(q @ c @ q) / c0
        assert abs(rho - rho_theory) < STAT_TOL, (lag, rho, rho_theory)
        assert rho < 0.5


def test_static_and_very_fast_layers():
    # Invariants: a layer without wind gives the same frame forever (tau0 = inf); a layer
    # moving 80 px/frame (more than its 32 px screen: stage-1 rates of 10 Hz with a fast
    # jet stream) is extruded by 80 columns per frame and keeps the von Kármán
    # piston-removed variance (oracle tr(Q C Q) / n_valid; 500 frames = 800 L0 of travel).
    pupil = Pupil(n_pix=16)
    static = Atmosphere(pupil, R0, [Layer(0.0, 1.0, 0.0)], fs=1000.0, rng=13)
    maps = static.phase(300)
    assert np.all(maps == maps[0]) and static.tau0 == math.inf
    fast = Atmosphere(pupil, R0, [_moving_layer(pupil, (0, 80), fs=10.0)], fs=10.0, rng=14)
    v = fast.phase_vectors(500)
    q = _piston_removal(pupil.n_valid)
    theory_var = np.trace(q @ _pixel_covariance(pupil) @ q) / pupil.n_valid
    ratio = v.var(axis=1).mean() / theory_var
    assert abs(ratio - 1) < STAT_TOL, ratio


# ---------------------------------------------------------------------------- API
def test_same_seed_bit_identical_and_split_invariant():
    # Invariants: same seed -> same frames bit for bit; reset() replays; the split of a run
    # into calls does not matter; another seed gives other frames.
    pupil = Pupil(n_pix=16)
    layers = [Layer(0.0, 0.6, 12.0, 30.0), Layer(8000.0, 0.4, 25.0, 200.0)]
    a = Atmosphere(pupil, 0.15, layers, fs=3000.0, rng=7)
    b = Atmosphere(pupil, 0.15, layers, fs=3000.0, rng=np.random.default_rng(7))
    ref = a.phase(1500)
    assert np.array_equal(ref, b.phase(1500))
    a.reset()
    parts = np.concatenate([a.phase(1), a.phase(333), a.phase(0), a.phase(1166)])
    assert np.array_equal(ref, parts)
    assert a.frame == 1500
    a.reset(rng=8)
    assert not np.allclose(a.phase(10), ref[:10])


def test_phase_maps_and_vectors_agree_and_scale_with_r0():
    # Invariants: phase() is phase_vectors() on the mask, zero outside; the OPD scales
    # exactly as r0^(-5/6) for a fixed seed (the phase PSD is proportional to r0^(-5/3)).
    pupil = Pupil(n_pix=16, obstruction=0.14)
    layers = eso_median_profile(3)
    maps = Atmosphere(pupil, 0.1, layers, fs=1000.0, rng=9).phase(50)
    vecs = Atmosphere(pupil, 0.1, layers, fs=1000.0, rng=9).phase_vectors(50)
    assert maps.shape == (50, 16, 16)
    np.testing.assert_array_equal(pupil.to_vector(maps), vecs)
    assert np.all(maps[:, ~pupil.mask] == 0)
    maps2 = Atmosphere(pupil, 0.2, layers, fs=1000.0, rng=9).phase(50)
    np.testing.assert_allclose(maps2, maps * 2 ** (-5 / 6), rtol=1e-12, atol=1e-9)


def test_layers_add_in_cn2():
    # Oracle: layers are independent with r0_i = r0 f_i^(-3/5), so the phase variance adds
    # to that of r0 (sum of f_i = 1). The exact per-layer check: one layer of fraction f
    # alone, with the same seed streams, is sqrt(f) times the full-weight layer.
    pupil = Pupil(n_pix=16)
    one = Atmosphere(pupil, 0.1, [Layer(0.0, 1.0, 10.0, 0.0)], fs=500.0, rng=11).phase(20)
    frac = Atmosphere(
        pupil, 0.1 * 0.3 ** (-3 / 5), [Layer(0.0, 1.0, 10.0, 0.0)], fs=500.0, rng=11
    ).phase(20)
    np.testing.assert_allclose(frac, one * math.sqrt(0.3), rtol=1e-12, atol=1e-9)


def test_atmosphere_tau0_and_properties():
    pupil = Pupil(n_pix=16)
    layers = [Layer(0.0, 0.7, 5.0, 0.0), Layer(10000.0, 0.3, 30.0, 90.0)]
    atm = Atmosphere(pupil, 0.12, layers, fs=1000.0, rng=0)
    # Oracle: tau0 = 0.314 r0 / v_bar, v_bar the 5/3-weighted mean speed.
    v_bar = (0.7 * 5.0 ** (5 / 3) + 0.3 * 30.0 ** (5 / 3)) ** 0.6
    assert abs(atm.tau0 / (0.314 * 0.12 / v_bar) - 1) < 1e-12
    assert atm.dt == 1e-3 and atm.L0 == 25.0 and atm.layers == tuple(layers)


# ---------------------------------------------------------------------------- profiles
def test_eso_profile_and_tau0_scaling():
    layers = eso_median_profile()
    assert len(layers) == 35
    assert abs(sum(lay.fraction for lay in layers) - 1) < 1e-12
    # Published ground-layer value: 24.2 % of the Cn2 at 30 m, 5.5 m/s (ESO-258292).
    assert layers[0].altitude == 30.0 and layers[0].wind_speed == 5.5
    assert abs(layers[0].fraction / 0.242 - 1) < 1e-12
    # Oracle: after scaling, 0.314 r0 / v_bar equals the requested tau0.
    r0 = r0_from_seeing(0.8)
    scaled = scale_to_tau0(layers, r0, 3.5e-3)
    speeds = [lay.wind_speed for lay in scaled]
    fracs = [lay.fraction for lay in scaled]
    assert abs(tau0(r0, speeds, fracs) / 3.5e-3 - 1) < 1e-12
    ratios = np.array(speeds) / [lay.wind_speed for lay in layers]
    assert np.ptp(ratios) < 1e-12  # one factor for all layers
    atm = Atmosphere(Pupil(n_pix=16), r0, scaled, fs=1000.0, rng=0)
    assert abs(atm.tau0 / 3.5e-3 - 1) < 1e-12


def test_frames_reproduce_tau0():
    # Oracle: in frozen flow the temporal structure function of the phase is
    # D_t(tau) = sum_l f_l D(v_l tau) (von Kármán, r0 of the whole atmosphere); in the
    # Kolmogorov limit (L0 -> inf) at tau = tau0 = 0.314 r0 / v_bar it is
    # 6.88 (v_bar tau0 / r0)^(5/3) = 6.88 * 0.314^(5/3) = 1.0 rad^2 -- the definition of tau0
    # with the 5/3-weighted speed. Three layers moving by 1, 2, 3 whole pixels per frame (no
    # interpolation); r0 chosen and the speeds scaled with scale_to_tau0 so that tau0 is
    # exactly 2 frames. (At these scales, 1-3 m, L0 = 25 m lowers D_t well below 1 rad^2.)
    pupil = Pupil(n_pix=16)
    fs, lag = 1000.0, 2
    layers = [
        _moving_layer(pupil, (0, 1), fraction=0.5),
        _moving_layer(pupil, (2, 0), fraction=0.3),
        _moving_layer(pupil, (0, -3), fraction=0.2),
    ]
    speeds = np.array([lay.wind_speed for lay in layers])
    v_bar = effective_wind_speed(speeds, [0.5, 0.3, 0.2])
    r0 = v_bar * lag / fs / 0.314
    layers = scale_to_tau0(layers, r0, lag / fs)
    np.testing.assert_allclose([lay.wind_speed for lay in layers], speeds, rtol=1e-12)
    atm = Atmosphere(pupil, r0, layers, fs=fs, L0=L0, rng=12)
    assert abs(atm.tau0 * fs / lag - 1) < 1e-12

    def d_t(outer_scale):
        return sum(
            lay.fraction * structure_function(lay.wind_speed * lag / fs, r0, outer_scale)
            for lay in layers
        )

    kolmogorov = sum(
        lay.fraction * 6.88 * (lay.wind_speed * lag / fs / r0) ** (5 / 3) for lay in layers
    )
    assert abs(kolmogorov - 1) < 0.01  # Kolmogorov limit: 1 rad^2 at tau0
    rad = atm.phase_vectors(4000)[100:] / opd_per_radian()
    measured = np.mean((rad[lag:] - rad[:-lag]) ** 2)
    assert abs(measured / d_t(L0) - 1) < STAT_TOL, (measured, d_t(L0))


@pytest.mark.parametrize("k", [1, 3, 5, 10])
def test_compressed_profile_preserves_moments(k):
    # Oracle: equivalent layers preserve exactly the total Cn2, the 5/3-moment wind speed
    # (tau0) and the 5/3-moment altitude (isoplanatic angle).
    full = eso_median_profile()
    comp = eso_median_profile(k)
    assert len(comp) == k
    assert np.all(np.diff([lay.altitude for lay in comp]) > 0)
    assert abs(sum(lay.fraction for lay in comp) - 1) < 1e-12

    def v_bar(layers):
        return effective_wind_speed(
            [lay.wind_speed for lay in layers], [lay.fraction for lay in layers]
        )

    assert abs(v_bar(comp) / v_bar(full) - 1) < 1e-12
    assert abs(effective_altitude(comp) / effective_altitude(full) - 1) < 1e-12
    assert abs(isoplanatic_angle(comp, 0.1) / isoplanatic_angle(full, 0.1) - 1) < 1e-12
    assert compress_profile(full, 35) == sorted(full, key=lambda lay: lay.altitude)


def test_eso_atmosphere_factory():
    # Oracle: r0 = 0.98 lambda / seeing at 500 nm and tau0 as requested.
    atm = eso_atmosphere(
        Pupil(n_pix=16), seeing=0.65, tau0=5e-3, fs=3000.0, n_layers=4, rng=0, dtype=np.float32
    )
    assert abs(atm.r0 / r0_from_seeing(0.65) - 1) < 1e-12
    assert abs(atm.tau0 / 5e-3 - 1) < 1e-12
    assert len(atm.layers) == 4 and atm.phase(3).dtype == np.float32


def test_float32_frames_match_float64():
    # Invariant: the float32 output is the float64 one rounded (relative 1e-6 of the rms).
    pupil = Pupil(n_pix=16)
    layers = eso_median_profile(3)
    f64 = Atmosphere(pupil, 0.1, layers, fs=1000.0, rng=1).phase_vectors(300)
    f32 = Atmosphere(pupil, 0.1, layers, fs=1000.0, rng=1, dtype="float32").phase_vectors(300)
    assert f32.dtype == np.float32
    np.testing.assert_allclose(f32, f64, rtol=0, atol=1e-6 * np.sqrt(np.mean(f64**2)))


def test_normalize_layers():
    layers = normalize_layers([Layer(0.0, 2.0 / 3.0, 5.0), Layer(1.0, 1.0, 5.0)])
    assert abs(sum(lay.fraction for lay in layers) - 1) < 1e-15


# ---------------------------------------------------------------------------- bad input
def _atm(**kw):
    args = dict(pupil=Pupil(n_pix=16), r0=0.1, layers=[Layer(0.0, 1.0, 10.0)], fs=1000.0)
    args.update(kw)
    return Atmosphere(**args)


@pytest.mark.parametrize(
    "kw, exc, words",
    [
        (dict(r0=-0.1), ValueError, ["r0", "-0.1", "> 0"]),
        (dict(fs=0.0), ValueError, ["fs", "0.0", "> 0"]),
        (dict(L0=float("inf")), ValueError, ["L0", "inf"]),
        (dict(layers=[Layer(0.0, 0.5, 10.0)]), ValueError, ["fractions", "sum to 1", "0.5"]),
        (dict(layers=[]), ValueError, ["layers", "at least one"]),
        (dict(layers=[(0.0, 1.0, 10.0)]), TypeError, ["layers[0]", "Layer"]),
        (dict(pupil=16), TypeError, ["pupil", "Pupil"]),
        (dict(rng="seed"), TypeError, ["rng", "seed"]),
        (dict(screen_size=10), ValueError, ["screen_size", "10", ">= 20"]),
        (dict(dtype=np.int32), ValueError, ["dtype", "int32", "float64 or float32"]),
        (dict(interpolation="nearest"), ValueError, ["interpolation", "nearest", "cubic"]),
    ],
)
def test_bad_atmosphere_input(kw, exc, words):
    with pytest.raises(exc) as info:
        _atm(**kw)
    for word in words:
        assert word in str(info.value)


@pytest.mark.parametrize(
    "args, words",
    [
        ((-1.0, 0.5, 10.0, 0.0), ["altitude", "-1.0"]),
        ((0.0, 1.5, 10.0, 0.0), ["fraction", "1.5", "[0, 1]"]),
        ((0.0, 0.5, -3.0, 0.0), ["wind_speed", "-3.0", ">= 0"]),
        ((0.0, 0.5, 3.0, float("nan")), ["wind_direction", "nan"]),
    ],
)
def test_bad_layer(args, words):
    with pytest.raises(ValueError) as info:
        Layer(*args)
    for word in words:
        assert word in str(info.value)


def test_bad_frames_and_profile_arguments():
    with pytest.raises(ValueError, match="n_frames must be an integer >= 0, got -1"):
        _atm().phase(-1)
    with pytest.raises(ValueError, match=r"n_layers must be in \[1, 35\], got 36"):
        eso_median_profile(36)
    with pytest.raises(ValueError, match="tau0 must be a finite number > 0, got 0.0"):
        scale_to_tau0(eso_median_profile(), 0.1, 0.0)
    with pytest.raises(ValueError, match="non-zero wind speed"):
        scale_to_tau0([Layer(0.0, 1.0, 0.0)], 0.1, 1e-3)
    with pytest.raises(ValueError, match="not all be zero"):
        normalize_layers([Layer(0.0, 0.0, 1.0)])


def test_extrusion_of_k_columns_at_once_equals_k_single_columns():
    # Invariant (bit for bit): the noise terms of a block of new columns are computed together;
    # the screen must not depend on how many columns one call adds.
    ext = Extruder.build(32, 0.1, 25.0)
    rng = np.random.default_rng(5)
    screen = rng.standard_normal((32, 32))
    white = rng.standard_normal((6, 32))
    block, single = screen.copy(), screen.copy()
    ext.extrude(block, white, 3.0)
    for row in white:
        ext.extrude(single, row[None], 3.0)
    assert np.array_equal(block, single)
    ext.extrude(single, 1.001 * white[:1], 3.0)  # the check can fail
    assert not np.array_equal(block, single)


@pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-12), (np.float32, 2e-6)])
def test_interpolation_products_equal_the_direct_weighted_sum(dtype, rtol):
    # Oracle: each frame is, per layer, the sum over the taps (a, b) of wy[a] wx[b] times the
    # screen's window at (floor(py) + a, floor(px) + b), computed here in float64 from the
    # layer screens as they are after the block (the frames of one block need no further
    # extrusion). The atmosphere forms them as dense products per sub-block of frames:
    # float64 agrees to rounding; float32 to its rounding (~6e-8 per term, a few 1e-7 of the
    # largest value after the sums; tolerance 2e-6).
    pupil = Pupil(n_pix=16)
    layers = [
        Layer(0.0, 0.5, 10.0, 30.0),
        Layer(5000.0, 0.3, 25.0, 200.0),
        Layer(10000.0, 0.2, 4.0, 95.0),
    ]
    atm = Atmosphere(pupil, 0.15, layers, fs=3000.0, rng=9, dtype=dtype)
    n = min(atm._block, 120)
    got = atm.phase_vectors(n).astype(float)
    frames = np.arange(n, dtype=float)
    ref = np.zeros((n, pupil.n_valid))
    size = pupil.n_pix
    for st in atm._states:
        py, px = st.positions(frames)
        for f in range(n):
            gy, gx = math.floor(py[f]), math.floor(px[f])
            fy, fx = py[f] - gy, px[f] - gx
            cy, cx = gy - st.oy, gx - st.ox
            for a, wy in ((0, 1.0 - fy), (1, fy)):
                for b, wx in ((0, 1.0 - fx), (1, fx)):
                    win = st.screen[cy + a : cy + a + size, cx + b : cx + b + size]
                    ref[f] += wy * wx * win[pupil.mask]
    scale = np.max(np.abs(ref))
    np.testing.assert_allclose(got, ref, rtol=0, atol=rtol * scale)
    # The check can fail: the frames are not the neighbouring frames.
    assert np.max(np.abs(got[1:] - ref[:-1])) > 100 * rtol * scale
