"""Tests of the wavefront sensors, their calibration and the linear modal model.

Small pupils (16-32 samples) keep the suite fast; physics is checked against analytic oracles
(geometric pyramid, tilt gradients, Poisson statistics) and invariants (linearity, symmetry,
agreement of two computations).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from aocontrol.sim.noise import add_detector_noise
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.wfs import (
    LinearModalSensor,
    PyramidWFS,
    ShackHartmannWFS,
    calibrate,
    default_modulation_points,
    fitting_residual_screens,
    interaction_matrix,
    optical_gains,
    reconstructor,
)

WAVELENGTH = 1.04e-6  # SAXO+ stage-2 sensing wavelength [m]


def _modes(pupil: Pupil, n_modes: int) -> np.ndarray:
    """Orthonormal (1 nm RMS), piston-free low-order polynomial modes on the pupil."""
    x = pupil.to_vector(pupil.x) / (pupil.diameter / 2)
    y = pupil.to_vector(pupil.y) / (pupil.diameter / 2)
    cols = [x**i * y**j for d in range(1, 8) for i in range(d + 1) for j in [d - i]]
    a = np.stack([np.ones_like(x)] + cols[:n_modes], axis=1)
    q, _ = np.linalg.qr(a)
    return (q[:, 1 : n_modes + 1] * np.sqrt(pupil.n_valid)).T


def _tilt_opd(pupil: Pupil, shift: float, wavelength: float = WAVELENGTH) -> np.ndarray:
    """OPD [nm] of a tilt that moves the PSF by ``shift`` lambda/D along +x."""
    return shift * wavelength * 1e9 * pupil.x / pupil.diameter


def _beam_tilt_reference(wfs: PyramidWFS, opd: np.ndarray) -> np.ndarray:
    """Straightforward (non-separable) pyramid propagation in double precision: for each
    modulation point tilt the beam, FFT, multiply by the 2-D mask, inverse FFT, |.|^2."""
    p, n = wfs.pupil, wfs.n_fft
    q, n_pix = wfs.samples_per_lambda_over_d, p.n_pix
    u = np.fft.fftfreq(n) * n + 0.5
    mask = np.exp(0.5j * np.pi * (np.abs(u)[:, None] + np.abs(u)[None, :]))
    r0 = (n - n_pix) // 2
    idx = np.arange(n_pix)
    total = np.zeros((n, n))
    for ax, ay in wfs.modulation_offsets:
        phase = 2 * np.pi * opd / (wfs.wavelength * 1e9)
        tilt = (ax * q - 0.5) * idx[None, :] + (ay * q - 0.5) * idx[:, None]
        phase = phase + 2 * np.pi * tilt / n
        field = np.zeros((n, n), complex)
        field[r0 : r0 + n_pix, r0 : r0 + n_pix] = p.mask * np.exp(1j * phase)
        total += np.abs(np.fft.ifft2(np.fft.fft2(field) * mask)) ** 2
    total /= p.n_valid * wfs.n_points
    b = wfs._binning_full
    return b @ total @ b.T


@pytest.fixture(scope="module")
def pupil32() -> Pupil:
    return Pupil(n_pix=32, obstruction=0.14)


@pytest.fixture(scope="module")
def pyramid(pupil32: Pupil) -> PyramidWFS:
    return PyramidWFS(pupil32, WAVELENGTH, n_subapertures=16, modulation=3.0)


@pytest.fixture(scope="module")
def calibrated(pyramid: PyramidWFS):
    modes = _modes(pyramid.pupil, 20)
    return modes, calibrate(pyramid, modes, amplitude=5.0)


# ---------------------------------------------------------------------------- pyramid physics
def test_default_modulation_points():
    # Oracle: 4 ceil(pi r): 3 lambda/D -> 4 * 10 = 40 points (~2 per lambda/D of perimeter).
    assert default_modulation_points(3.0) == 40
    assert default_modulation_points(0.0) == 1


def test_pyramid_flat_wavefront_zero_signal_symmetric_images(pyramid: PyramidWFS):
    # Oracle: a flat wavefront gives zero signals and four images related by the pyramid's
    # mirror symmetries (I1 = I0 flipped left-right, I2 = I0 flipped up-down, I0 = I0^T).
    n = pyramid.n_subapertures
    f = pyramid.reference_frame
    i0, i1, i2 = f[:n, :n], f[:n, n:], f[n:, :n]
    tol = 1e-5  # single-precision FFTs
    assert np.abs(i0 - i1[:, ::-1]).max() < tol * i0.max()
    assert np.abs(i0 - i2[::-1, :]).max() < tol * i0.max()
    assert np.abs(i0 - i0.T).max() < tol * i0.max()
    assert np.abs(pyramid.signals(np.zeros((32, 32)))).max() == 0.0
    # flux: the four images hold most of the light (some diffracts outside the pupil images)
    assert 0.8 < f.sum() <= 1.0 + 1e-6


def test_pyramid_matches_unfactored_beam_tilt_propagation(pupil32: Pupil):
    # Oracle: the separable computation is an exact rewrite of the textbook propagation
    # (tilt, FFT, 2-D mask, inverse FFT per modulation point): equal to rounding in double.
    wfs = PyramidWFS(
        pupil32,
        WAVELENGTH,
        n_subapertures=16,
        modulation=1.3,
        n_modulation_points=7,
        precision="double",
    )
    opd = _tilt_opd(pupil32, 0.3) + 30 * np.cos(2 * np.pi * pupil32.x / 2.0)
    fast, ref = wfs.detector_image(opd), _beam_tilt_reference(wfs, opd)
    assert np.abs(fast - ref).max() < 1e-10 * ref.max()


def test_pyramid_single_precision_accuracy(pupil32: Pupil):
    # Oracle: complex64 FFTs have ~1e-7 relative rounding; signals agree with complex128 to
    # SINGLE_TOL (generous: accumulation over modulation points and pixels).
    single_tol = 1e-4
    opd = 40 * np.sin(2 * np.pi * pupil32.y / 3.0) + _tilt_opd(pupil32, 0.5)
    s32 = PyramidWFS(pupil32, WAVELENGTH, n_subapertures=16).signals(opd)
    s64 = PyramidWFS(pupil32, WAVELENGTH, n_subapertures=16, precision="double").signals(opd)
    assert np.linalg.norm(s32 - s64) / np.linalg.norm(s64) < single_tol


def test_pyramid_linear_and_push_pull_symmetric_for_small_aberrations(pyramid, calibrated):
    # Oracle: for aberrations << lambda / (2 pi) the response is linear: s(a) / a constant and
    # s(-a) = -s(a), to second order in a (LIN_TOL covers a = 1..4 nm at 1.04 um).
    lin_tol = 0.01
    modes, _ = calibrated
    shape = pyramid.pupil.to_map(modes[4] + 0.5 * modes[9])
    s1 = pyramid.signals(1.0 * shape)
    for a in (2.0, 4.0):
        sa = pyramid.signals(a * shape)
        assert abs(np.linalg.norm(sa) / (a * np.linalg.norm(s1)) - 1) < lin_tol
        sm = pyramid.signals(-a * shape)
        assert np.linalg.norm(sa + sm) / np.linalg.norm(sa) < lin_tol


@pytest.mark.parametrize("radius", [3.0, 4.0])
def test_modulated_pyramid_tilt_response_matches_geometric_optics(pupil32: Pupil, radius: float):
    # Oracle: geometric optics, a spot displaced by d circling with radius r spends a fraction
    # arccos(-d/r)/pi on one side of the edge: Sx = (2/pi) arcsin(d/r) for |d| <= r.
    # Diffraction adds a few per cent (~1/r): GEOM_TOL.
    geom_tol = 0.10
    wfs = PyramidWFS(pupil32, WAVELENGTH, n_subapertures=16, modulation=radius, precision="double")
    nv = wfs.n_valid_subapertures
    for d in (0.5, 1.0, 1.5):
        s = wfs.signals(_tilt_opd(pupil32, d))
        expected = 2 / np.pi * np.arcsin(d / radius)
        assert abs(s[:nv].mean() / expected - 1) < geom_tol
        assert abs(s[nv:].mean()) < 1e-6 * expected  # no cross-talk into y


def test_pyramid_linear_range_grows_with_modulation(pupil32: Pupil):
    # Oracle (geometric optics): the response departs from its small-signal slope once the
    # tilt is a sizeable fraction of r, so the non-linearity at a fixed 1.5 lambda/D tilt
    # decreases as the modulation radius grows.
    errors = []
    for radius in (1.0, 2.0, 3.0, 4.0):
        wfs = PyramidWFS(pupil32, WAVELENGTH, n_subapertures=16, modulation=radius)
        nv = wfs.n_valid_subapertures
        slope = wfs.signals(_tilt_opd(pupil32, 0.01))[:nv].mean() / 0.01
        big = wfs.signals(_tilt_opd(pupil32, 1.5))[:nv].mean()
        errors.append(abs(big / (1.5 * slope) - 1))
    assert all(a > b for a, b in zip(errors[:-1], errors[1:], strict=True))
    assert errors[-1] < 0.05


def test_full_frame_signals(pupil32: Pupil):
    # Invariant: full-frame signals of the 4 images determine the slopes (same linear map).
    kw = dict(n_subapertures=16, modulation=3.0)
    full = PyramidWFS(pupil32, WAVELENGTH, signal_type="full_frame", **kw)
    slopes = PyramidWFS(pupil32, WAVELENGTH, **kw)
    opd = _tilt_opd(pupil32, 0.2)
    f = full.signals(opd).reshape(4, -1)
    nv = full.n_valid_subapertures
    s = slopes.signals(opd)
    assert full.n_signals == 4 * nv
    np.testing.assert_allclose(f[0] + f[2] - f[1] - f[3], s[:nv], atol=1e-6)


# ---------------------------------------------------------------------------- calibration
def test_reconstructor_inverts_interaction_matrix(calibrated):
    # Oracle: R = D^+ and D has full column rank, so R D = I.
    _, cal = calibrated
    assert cal.imat.shape[1] == 20
    np.testing.assert_allclose(cal.recon @ cal.imat, np.eye(20), atol=1e-10)


def test_derivative_interaction_matrix_matches_push_pull(pyramid, calibrated):
    # Oracle: push-pull with amplitude a is the exact derivative up to O(a^2): with a = 1 nm
    # at 1.04 um, (2 pi a / lambda)^2 ~ 4e-5, hence DERIV_TOL; also around a residual screen.
    deriv_tol = 1e-3
    modes, _ = calibrated
    screen = fitting_residual_screens(
        pyramid.pupil, 60.0, 1, np.random.default_rng(4), cutoff_frequency=1.0
    )[0]
    for offset in (None, screen):
        pp = interaction_matrix(pyramid, modes[:6], 1.0, offset_opd=offset)
        lin = interaction_matrix(pyramid, modes[:6], 1.0, offset_opd=offset, method="derivative")
        assert np.linalg.norm(lin - pp) / np.linalg.norm(pp) < deriv_tol


def test_reconstructor_truncation():
    # Oracle: with max_condition the smallest singular direction is dropped (rank n - 1).
    rng = np.random.default_rng(0)
    d = rng.standard_normal((30, 5)) @ np.diag([1, 1, 1, 1, 1e-6])
    r = reconstructor(d, max_condition=1e3)
    assert np.linalg.matrix_rank(r @ d, tol=1e-8) == 4
    assert reconstructor(d, n_modes=3).shape == (3, 30)


def test_reconstruction_of_a_modal_combination(pyramid, calibrated):
    # Oracle: in the linear regime m = R s recovers small modal coefficients (RECON_TOL: the
    # second-order terms at a few nm RMS).
    recon_tol = 0.02
    modes, cal = calibrated
    coeffs = np.linspace(-3.0, 3.0, 20)
    s = pyramid.signals(pyramid.pupil.to_map(coeffs @ modes))
    est = cal.recon @ s
    assert np.linalg.norm(est - coeffs) / np.linalg.norm(coeffs) < recon_tol


def test_optical_gain_below_one_and_decreasing_with_residual(pyramid, calibrated):
    # Oracle (pyramid optical gains): a residual phase spreads the PSF beyond the modulation
    # circle, lowering the sensitivity: gains < 1, decreasing with the residual RMS.
    modes, cal = calibrated
    rng = np.random.default_rng(3)
    means = []
    for rms in (30.0, 80.0):
        screens = fitting_residual_screens(
            pyramid.pupil, rms, 2, rng, cutoff_frequency=16 / (2 * 8.0)
        )
        g = optical_gains(pyramid, modes[:6], screens, recon=cal.recon[:6])
        assert np.all(g < 1)
        means.append(g.mean())
    assert means[1] < means[0] < 1
    flat = optical_gains(pyramid, modes[:3], np.zeros((32, 32)), recon=cal.recon[:3], amplitude=5.0)
    # the recon of 20 modes restricted to 3 rows: diagonal of R D is exactly 1 when flat
    np.testing.assert_allclose(flat, 1.0, atol=1e-8)


def test_fitting_residual_screens_rms(pupil32: Pupil):
    # Oracle: each screen is scaled to the requested RMS over the pupil, piston-free.
    s = fitting_residual_screens(pupil32, 50.0, 3, np.random.default_rng(0), cutoff_frequency=1.0)
    v = pupil32.to_vector(s)
    np.testing.assert_allclose(np.sqrt((v**2).mean(axis=1)), 50.0, rtol=1e-12)
    np.testing.assert_allclose(v.mean(axis=1), 0.0, atol=1e-9)


# ---------------------------------------------------------------------------- noise propagation
@pytest.mark.parametrize(("photons", "read_noise"), [(2000.0, 0.3), (300.0, 1.5)])
def test_noise_propagation_matches_monte_carlo(pyramid, calibrated, photons, read_noise):
    # Oracle: Monte Carlo of Poisson + Gaussian read noise on the detector pixels through the
    # full non-linear signal processing and R, against the linearised model
    # var = c_ph / N + c_ro sigma^2 / N^2, per mode. Photon- and read-noise dominated cases.
    # With N_MC = 4000 draws the sampling error of a variance is sqrt(2/4000) = 2.2 %, so
    # NOISE_TOL = 10 % is > 4 sigma for each of the 20 modes.
    noise_tol = 0.10
    n_mc = 4000
    modes, cal = calibrated
    rng = np.random.default_rng(12)
    frame = pyramid.reference_frame * photons
    noisy = add_detector_noise(np.broadcast_to(frame, (n_mc, *frame.shape)), read_noise, rng)
    meas = pyramid.signals_from_frame(noisy) @ cal.recon.T
    ratio = meas.var(axis=0) / cal.noise_variance(photons, read_noise)
    assert np.all(np.abs(ratio - 1) < noise_tol), ratio


def test_noise_scalings(calibrated):
    # Oracle: linearised photon-noise variance ~ 1/N, read-noise variance ~ sigma^2 / N^2;
    # the flux-normalisation correction is 1 + 3 (f N + n sigma^2) / (f N)^2.
    _, full = calibrated
    cal = dataclasses.replace(full, norm_pixels=0)
    n, f = full.norm_pixels, full.norm_fraction
    np.testing.assert_allclose(
        full.noise_variance(50.0, 1.0) / cal.noise_variance(50.0, 1.0),
        1 + 3 * (f * 50 + n) / (f * 50) ** 2,
    )
    v1 = cal.noise_variance(100.0, 0.0)
    np.testing.assert_allclose(cal.noise_variance(400.0, 0.0), v1 / 4)
    r = cal.noise_variance(100.0, 2.0) - v1
    np.testing.assert_allclose(cal.noise_variance(200.0, 2.0) - v1 / 2, r / 4)


# ---------------------------------------------------------------------------- linear model
def test_linear_modal_wfs_statistics_and_shapes():
    # Oracle: measurement = g x + n with n ~ N(0, sigma^2): sample mean and std over many
    # frames match (STAT_TOL: 5 sigma of the estimators for 20000 frames).
    stat_tol = 0.05
    g, sigma = np.array([1.0, 0.5, 0.2]), np.array([1.0, 2.0, 0.5])
    wfs = LinearModalSensor(optical_gain=g, noise_std=sigma)
    x = np.array([10.0, -4.0, 3.0])
    m = wfs.measure(np.broadcast_to(x, (20000, 3)), np.random.default_rng(0))
    assert m.shape == (20000, 3)
    assert np.all(np.abs(m.mean(axis=0) - g * x) < stat_tol * sigma)
    assert np.all(np.abs(m.std(axis=0) / sigma - 1) < stat_tol)
    assert wfs.measure(x, np.random.default_rng(0)).shape == (3,)


def test_same_seed_same_numbers(pyramid):
    # Invariant: randomness only through the passed Generator, bit for bit.
    wfs = LinearModalSensor(optical_gain=np.ones(4), noise_std=np.full(4, 3.0))
    a = wfs.measure(np.zeros((5, 4)), np.random.default_rng(42))
    b = wfs.measure(np.zeros((5, 4)), np.random.default_rng(42))
    assert np.array_equal(a, b)
    opd = np.zeros((32, 32))
    s1 = pyramid.measure(opd, 500.0, 0.3, np.random.default_rng(7))
    s2 = pyramid.measure(opd, 500.0, 0.3, np.random.default_rng(7))
    assert np.array_equal(s1, s2)


def test_linear_model_from_diffractive(pyramid, calibrated):
    # Invariant: from_diffractive = calibrate + noise model at the given flux; gains 1 when
    # no residual is given.
    modes, cal = calibrated
    lin = LinearModalSensor.from_diffractive(pyramid, modes, 1000.0, 0.3, amplitude=5.0)
    np.testing.assert_allclose(lin.noise_std, np.sqrt(cal.noise_variance(1000.0, 0.3)))
    np.testing.assert_array_equal(lin.optical_gain, 1.0)


def test_modal_basis_object_accepted(pupil32: Pupil, pyramid):
    # Invariant: a ModalBasis-like object (.modes, .pupil) and the plain array give the same
    # interaction matrix.
    class Basis:
        def __init__(self, pupil, modes):
            self.pupil, self.modes = pupil, modes

    modes = _modes(pupil32, 3)
    np.testing.assert_array_equal(
        interaction_matrix(pyramid, Basis(pupil32, modes), 5.0),
        interaction_matrix(pyramid, modes, 5.0),
    )


# ---------------------------------------------------------------------------- Shack-Hartmann
@pytest.mark.parametrize("model", ["geometric", "diffractive"])
def test_shack_hartmann_tilt_equals_analytic_gradient(model: str):
    # Oracle: OPD = a x [nm, x in m] has gradient a, so each subaperture reads a d [nm] in x
    # and 0 in y. Geometric: exact (finite differences of a plane). Diffractive: centre of
    # gravity of the spot on fully illuminated subapertures, to SH_TOL: the sampled
    # subaperture (8 samples) makes the spot periodic with a field of view of 8 lambda/d and
    # its wrapped wings bias the centre of gravity by a few per cent (the known CoG gain of a
    # truncated spot); edge subapertures have asymmetric spots and are not checked.
    sh_tol = 0.05 if model == "diffractive" else 1e-10
    pupil = Pupil(n_pix=64)
    wfs = ShackHartmannWFS(pupil, 0.69e-6, n_subapertures=8, model=model)
    a = 20.0
    s = wfs.signals(a * pupil.x)
    nv = wfs.n_valid_subapertures
    full = (
        np.add.reduceat(np.add.reduceat(pupil.mask, np.arange(0, 64, 8), 0), np.arange(0, 64, 8), 1)
        == 64
    )[wfs.valid_subapertures]
    assert full.sum() > 10
    np.testing.assert_allclose(s[:nv][full] / (a * wfs.subaperture_size), 1.0, atol=sh_tol)
    assert np.abs(s[nv:]).max() < 1e-9 * a


def test_shack_hartmann_noise_propagation_monte_carlo():
    # Oracle: as for the pyramid, centroid noise from Poisson + read noise, linearised.
    noise_tol = 0.10
    pupil = Pupil(n_pix=32)
    wfs = ShackHartmannWFS(pupil, 0.69e-6, n_subapertures=4, model="diffractive")
    modes = _modes(pupil, 5)
    cal = calibrate(wfs, modes, amplitude=5.0)
    rng = np.random.default_rng(5)
    frame = wfs.reference_frame * 5000.0
    noisy = add_detector_noise(np.broadcast_to(frame, (4000, *frame.shape)), 0.5, rng)
    var = (wfs.signals_from_frame(noisy) @ cal.recon.T).var(axis=0)
    assert np.all(np.abs(var / cal.noise_variance(5000.0, 0.5) - 1) < noise_tol)


# ---------------------------------------------------------------------------- bad input
def test_bad_inputs(pupil32: Pupil):
    with pytest.raises(ValueError, match=r"modulation must be .*>= 0.*-1.0"):
        PyramidWFS(pupil32, WAVELENGTH, n_subapertures=16, modulation=-1.0)
    with pytest.raises(ValueError, match=r"pupil.n_pix must be >= n_subapertures=40.*32"):
        PyramidWFS(pupil32, WAVELENGTH, n_subapertures=40)
    with pytest.raises(ValueError, match=r"modulation must be < pupil.n_pix / 4"):
        PyramidWFS(pupil32, WAVELENGTH, n_subapertures=16, modulation=9.0)
    with pytest.raises(ValueError, match=r"wavelength must be a finite number > 0, got -1"):
        PyramidWFS(pupil32, -1e-6)
    with pytest.raises(ValueError, match=r"signal_type"):
        PyramidWFS(pupil32, WAVELENGTH, n_subapertures=16, signal_type="quad")
    with pytest.raises(ValueError, match=r"pupil.n_pix must be a multiple of n_subapertures=40"):
        ShackHartmannWFS(pupil32, 0.69e-6, n_subapertures=40)
    with pytest.raises(ValueError, match=r">= 4 samples per subaperture"):
        ShackHartmannWFS(pupil32, 0.69e-6, n_subapertures=16, model="diffractive")
    with pytest.raises(ValueError, match=r"opd must end with shape \(32, 32\)"):
        PyramidWFS(pupil32, WAVELENGTH, n_subapertures=16).signals(np.zeros((16, 16)))
    with pytest.raises(ValueError, match=r"noise_std must be >= 0"):
        LinearModalSensor(optical_gain=[1.0], noise_std=[-1.0])
    with pytest.raises(ValueError, match=r"same shape"):
        LinearModalSensor(optical_gain=[1.0, 1.0], noise_std=[1.0])
    with pytest.raises(ValueError, match=r"residual must have shape"):
        LinearModalSensor(optical_gain=[1.0], noise_std=[1.0]).measure(
            np.zeros(3), np.random.default_rng(0)
        )
    with pytest.raises(ValueError, match=r"amplitude must be a finite number > 0, got 0.0"):
        interaction_matrix(
            PyramidWFS(pupil32, WAVELENGTH, n_subapertures=16), _modes(pupil32, 2), amplitude=0.0
        )


def test_white_noise_propagation_matches_monte_carlo():
    # Oracle: for white signal noise of unit variance, cov(R n) = R R^T; its diagonal against
    # 20000 draws (STAT_TOL: 5 sigma of a variance estimate, sqrt(2/20000) = 1 %).
    from aocontrol.sim.wfs import white_noise_propagation

    stat_tol = 0.05
    rng = np.random.default_rng(2)
    r = rng.standard_normal((4, 30))
    var = (rng.standard_normal((20000, 30)) @ r.T).var(axis=0)
    assert np.all(np.abs(var / white_noise_propagation(r) - 1) < stat_tol)


def test_saxo_plus_scale_pyramid_noise_model_with_kl_modes():
    # SAXO+ stage-2 sampling (40 x 40 subapertures, 80 pupil samples, 3 lambda/D, 40 points)
    # with KL modes of a 28x28 DM. Oracles: R D = I on the calibrated modes; Monte Carlo of
    # photon + read noise (J = 10-like flux, 0.3 e-) through R matches the noise model within
    # NOISE_TOL (3000 draws: 2.6 % standard error of a variance, 10 % is ~4 sigma).
    from aocontrol.sim.dm import DeformableMirror
    from aocontrol.sim.modes import kl_basis
    from aocontrol.sim.pupil import vlt_pupil

    noise_tol = 0.10
    pupil = vlt_pupil(80)
    basis = kl_basis(DeformableMirror(pupil, n_actuators=28), 12)
    wfs = PyramidWFS(pupil, 1.14e-6, n_subapertures=40, modulation=3.0)
    assert (wfs.n_fft, wfs.n_points) == (168, 40)
    cal = calibrate(wfs, basis, amplitude=10.0)
    np.testing.assert_allclose(cal.recon @ cal.imat, np.eye(12), atol=1e-10)
    photons, ron = 3000.0, 0.3
    frame = wfs.reference_frame * photons
    noisy = add_detector_noise(
        np.broadcast_to(frame, (3000, *frame.shape)), ron, np.random.default_rng(8)
    )
    var = (wfs.signals_from_frame(noisy) @ cal.recon.T).var(axis=0)
    assert np.all(np.abs(var / cal.noise_variance(photons, ron) - 1) < noise_tol)


def test_saxo_shack_hartmann_geometry():
    # SAXO stage 1: 40 x 40 Shack-Hartmann at 0.69 um on the VLT pupil (160 samples, 4 per
    # subaperture). Oracle: a pure tilt reads a d on every valid subaperture (geometric model),
    # and the diffractive model agrees with it on fully illuminated subapertures to SH_TOL
    # (centre-of-gravity gain of the 4 lambda/d field of view, see the tilt test).
    from aocontrol.sim.pupil import vlt_pupil

    sh_tol = 0.10
    pupil = vlt_pupil(160)
    geo = ShackHartmannWFS(pupil, 0.69e-6, n_subapertures=40)
    dif = ShackHartmannWFS(pupil, 0.69e-6, n_subapertures=40, model="diffractive")
    a = 5.0
    s_geo, s_dif = geo.signals(a * pupil.y), dif.signals(a * pupil.y)
    nv = geo.n_valid_subapertures
    assert nv == dif.n_valid_subapertures > 1000
    np.testing.assert_allclose(s_geo[nv:], a * geo.subaperture_size, rtol=1e-10)
    blocks = pupil.mask.reshape(40, 4, 40, 4).sum(axis=(1, 3)) == 16
    full = blocks[geo.valid_subapertures]
    assert np.all(np.abs(s_dif[nv:][full] / s_geo[nv:][full] - 1) < sh_tol)
