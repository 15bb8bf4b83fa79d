"""Science camera: PSF, perfect coronagraph, long exposure and metrics against optics oracles."""

import numpy as np
import pytest
from scipy import special

from aocontrol.sim.pupil import Pupil, vlt_pupil
from aocontrol.sim.science import (
    LongExposure,
    ScienceCamera,
    ScienceResult,
    marechal_strehl,
    mean_contrast,
    opd_rms,
    opd_to_phase,
    radial_profile,
    strehl,
)

WL = 1.65e-6
NM_PER_RAD = WL * 1e9 / (2 * np.pi)  # OPD [nm] of one radian at 1.65 um
# complex64 FFT of a 64x64 pupil: relative rounding ~1e-7 on a peak of 1.
SINGLE = 1e-6
# complex128: rounding only.
DOUBLE = 1e-12
# A perfect coronagraph on a flat (or piston) wavefront: the brief's "numerical precision".
CORONAGRAPH_FLOOR = 1e-10


@pytest.fixture(scope="module")
def pupil():
    return vlt_pupil(64)


@pytest.fixture(scope="module")
def camera(pupil):
    return ScienceCamera(pupil, wavelength=WL)


def smooth_residual(pupil, rng, n_frames, rms_rad):
    """Random smooth phase (f^-11/6 amplitude), piston/tip/tilt removed, RMS ``rms_rad``, in nm."""
    n = pupil.n_pix
    fx = np.fft.fftfreq(n) * n
    f = np.hypot(*np.meshgrid(fx, fx))
    f[0, 0] = np.inf
    w = np.fft.ifft2(np.fft.fft2(rng.normal(size=(n_frames, n, n))) * f ** (-11 / 6)).real
    v = pupil.to_vector(w)
    basis = np.stack(
        [np.ones(pupil.n_valid), pupil.to_vector(pupil.x), pupil.to_vector(pupil.y)], axis=1
    )
    v = v - (np.linalg.lstsq(basis, v.T, rcond=None)[0].T @ basis.T)
    v *= rms_rad / v.std(axis=-1, keepdims=True)
    return pupil.to_map(v) * NM_PER_RAD


@pytest.mark.parametrize("precision, tol", [("single", SINGLE), ("double", DOUBLE)])
@pytest.mark.parametrize("piston_nm", [0.0, 437.0])
def test_flat_wavefront_strehl_one_and_star_removed(pupil, precision, tol, piston_nm):
    # Oracle: a flat (or piston-only) wavefront is diffraction limited, Strehl = 1; the perfect
    # coronagraph removes the whole field, E_c = P (e^{i phi0} - e^{i phi0}) = 0.
    cam = ScienceCamera(pupil, precision=precision)
    exposure = cam.long_exposure()
    exposure.add(np.full((3, 64, 64), piston_nm))
    assert abs(exposure.result().strehl - 1) < tol
    assert abs(exposure.psf[cam.centre, cam.centre] - 1) < tol
    assert exposure.coronagraphic.max() < CORONAGRAPH_FLOOR
    np.testing.assert_allclose(exposure.psf, cam.diffraction_psf, atol=tol)


def test_clear_circular_pupil_gives_airy_pattern():
    # Oracle: Airy pattern I(r)/I(0) = (2 J1(x)/x)^2, x = pi r (r in lambda/D); first dark ring
    # at 1.2197 lambda/D. Tolerances: a 64-pixel circle differs from a disc by ~0.3 % in area.
    airy_tol, ring_tol = 1e-2, 2e-3
    cam = ScienceCamera(
        Pupil(n_pix=64, obstruction=0.0),
        oversampling=16,
        field_of_view=3.0,
        coronagraph=False,
        precision="double",
    )
    psf = cam.images(np.zeros((64, 64)))[0][0]
    assert abs(psf.max() - 1) < DOUBLE
    radii, profile = cam.radial_profile(psf, 0.1)
    x = np.pi * radii
    airy = (2 * special.j1(x) / x) ** 2
    main_lobe = radii < 0.8
    assert np.all(np.abs(profile[main_lobe] / airy[main_lobe] - 1) < airy_tol)
    # First dark ring: minimum of the cut along x, refined by a parabola through 3 pixels.
    cut = psf[cam.centre, cam.centre :]
    r = np.arange(cut.size) * cam.pixel_scale
    i = int(np.argmin(np.where((r > 1.0) & (r < 1.5), cut, np.inf)))
    y0, y1, y2 = cut[i - 1 : i + 2]
    r_dark = (i + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)) * cam.pixel_scale
    assert abs(r_dark / 1.2197 - 1) < ring_tol


@pytest.mark.parametrize("rms_rad", [0.1, 0.2, 0.3])
def test_strehl_agrees_with_marechal_small_errors(pupil, camera, rms_rad):
    # Oracle: extended Marechal, S = exp(-sigma^2) (tip/tilt removed so the peak stays on axis);
    # for Gaussian-like phase it is exact to O(sigma^4); the brief allows a few percent.
    marechal_tol = 1e-2
    opd = smooth_residual(pupil, np.random.default_rng(11), 4, rms_rad)
    psf = camera.images(opd)[0]
    rms_nm = opd_rms(opd, pupil)
    np.testing.assert_allclose(opd_to_phase(rms_nm, WL), rms_rad, rtol=1e-12)
    for frame, rms in zip(psf, rms_nm, strict=True):
        assert abs(strehl(frame) / marechal_strehl(rms, WL) - 1) < marechal_tol


@pytest.mark.parametrize("axis", ["x", "y"])
def test_sine_ripple_gives_two_speckles_of_contrast_a_over_2_squared(pupil, camera, axis):
    # Oracle (small aberrations): phi = a sin(2 pi k x / D) = (a/2i)(e^{i..} - e^{-i..}) puts two
    # copies of the PSF at +-k lambda/D with peak (a/2)^2 (exactly J1(a)^2 = (a/2)^2 (1 - a^2/8)^2);
    # the perfect coronagraph removes the central star. Tolerance: the other speckle's and the
    # star's Airy wings interfere at the ~0.3 % level for k = 8.
    speckle_tol = 1e-2
    a, k = 0.05, 8
    coord = pupil.x if axis == "x" else pupil.y
    opd = a * np.sin(2 * np.pi * k * coord / pupil.diameter + 0.3) * NM_PER_RAD
    psf, coro = camera.images(opd)
    coro = coro[0]
    c, off = camera.centre, int(round(k / camera.pixel_scale))
    spots = [(c, c + off), (c, c - off)] if axis == "x" else [(c + off, c), (c - off, c)]
    for spot in spots:
        assert abs(coro[spot] / (a / 2) ** 2 - 1) < speckle_tol
        assert coro[spot] == pytest.approx(coro.max(), rel=speckle_tol)
    # Star gone: the on-axis residual is far below the speckles.
    assert coro[c, c] < 1e-6 * (a / 2) ** 2
    # Away (> 3 lambda/D) from both speckles only faint Airy wings remain.
    yy, xx = np.indices(coro.shape)
    far = np.ones(coro.shape, dtype=bool)
    for sy, sx in spots:
        far &= np.hypot(yy - sy, xx - sx) * camera.pixel_scale > 3.0
    assert coro[far].max() < 0.03 * (a / 2) ** 2
    # Without coronagraph, the Strehl is the coherent energy J0(a)^2 ~ 1 - a^2/2.
    assert abs(strehl(psf[0]) / special.j0(a) ** 2 - 1) < SINGLE * 10


def test_parseval_energy_conservation(pupil):
    # Oracle (Parseval): on the full n_fft^2 field sum |FFT(E)|^2 = n_fft^2 sum |E|^2, so with
    # the normalisation by n_valid^2: sum(psf) = n_fft^2 / n_valid for any phase; the coronagraph
    # removes the coherent energy |c|^2 = psf(0): sum(coro) = n_fft^2 / n_valid (1 - psf(0)).
    energy_tol = 1e-5  # float32 rounding of ~1.6e4 summed pixels
    cam = ScienceCamera(pupil, oversampling=2.5)
    assert cam.n_image == cam.n_fft == 160
    opd = smooth_residual(pupil, np.random.default_rng(5), 3, 0.8)
    psf, coro = cam.images(opd)
    total = cam.n_fft**2 / pupil.n_valid
    for p, k in zip(psf, coro, strict=True):
        assert abs(p.sum() / total - 1) < energy_tol
        assert abs(k.sum() / (total * (1 - p[cam.centre, cam.centre])) - 1) < energy_tol
    # Integral over the sky of a peak-normalised PSF: lambda^2 / A in (lambda/D)^2 units.
    assert (
        abs(cam.diffraction_psf.sum() * cam.pixel_scale**2 / (pupil.n_pix**2 / pupil.n_valid) - 1)
        < energy_tol
    )


def test_long_exposure_equals_mean_of_single_frames(pupil):
    # Invariant: the accumulator (fed in chunks, across the internal 64-frame chunking) equals
    # the mean of the instantaneous images; only float64 summation order differs.
    accumulate_tol = 1e-12
    cam = ScienceCamera(pupil, field_of_view=12.0)
    opd = smooth_residual(pupil, np.random.default_rng(2), 70, 0.5)
    exposure = LongExposure(cam)
    exposure.add(opd[:5])
    exposure.add(pupil.to_vector(opd[5:]))  # values on valid pixels are accepted too
    psf, coro = cam.images(opd)
    assert exposure.n_frames == 70
    np.testing.assert_allclose(exposure.psf, psf.mean(axis=0), rtol=accumulate_tol, atol=0)
    np.testing.assert_allclose(
        exposure.coronagraphic, coro.mean(axis=0), rtol=accumulate_tol, atol=1e-18
    )
    result = exposure.result()
    assert result.n_frames == 70 and result.wavelength == WL
    assert result.strehl == pytest.approx(psf.mean(axis=0).max(), rel=accumulate_tol)
    assert result.mean_contrast_4_6 == pytest.approx(
        cam.mean_contrast(coro.mean(axis=0)), rel=accumulate_tol
    )
    exposure.reset()
    assert exposure.n_frames == 0
    with pytest.raises(RuntimeError, match="no frame"):
        _ = exposure.psf


def test_single_precision_is_accurate_enough(pupil):
    # Two paths agree: complex64 vs complex128 FFTs on a bright-case residual (~10 nm RMS, contrast
    # ~1e-6 at 4-6 lambda/D) with a large piston (10 um, 38 rad in float32) as a stress test.
    contrast_tol, pixel_tol = 1e-5, 1e-4
    opd = smooth_residual(pupil, np.random.default_rng(7), 8, 10.0 / NM_PER_RAD) + 1e4
    single, double = (
        ScienceCamera(pupil, precision=p, field_of_view=8.0).long_exposure()
        for p in ("single", "double")
    )
    single.add(opd)
    double.add(opd)
    rs, rd = single.result(), double.result()
    assert abs(rs.strehl - rd.strehl) < SINGLE
    assert abs(rs.mean_contrast_4_6 / rd.mean_contrast_4_6 - 1) < contrast_tol
    annulus = (single.camera.radius_map >= 4) & (single.camera.radius_map < 6)
    ratio = single.coronagraphic[annulus] / double.coronagraphic[annulus]
    assert np.all(np.abs(ratio - 1) < pixel_tol)


def test_opd_wavelength_scaling(pupil):
    # Oracle: phi = 2 pi opd / lambda. An OPD tilt of lambda0 = 1.65 um across D is a 2 pi ramp:
    # the PSF moves by exactly 1 lambda/D at lambda0 (2 pixels at Nyquist, peak still 1) and by
    # 2 lambda/D at lambda0 / 2, towards +x.
    assert abs(opd_to_phase(1650.0, WL) / (2 * np.pi) - 1) < DOUBLE
    assert abs(opd_to_phase(1650.0, WL / 2) / (4 * np.pi) - 1) < DOUBLE
    tilt = 1650.0 * pupil.x / pupil.diameter
    for wavelength, shift_ld in [(WL, 1), (WL / 2, 2)]:
        cam = ScienceCamera(pupil, wavelength=wavelength, field_of_view=6.0, coronagraph=False)
        psf = cam.images(tilt)[0][0]
        row, col = np.unravel_index(np.argmax(psf), psf.shape)
        assert (row, col) == (cam.centre, cam.centre + 2 * shift_ld)
        assert abs(psf.max() - 1) < SINGLE
    # Marechal: sigma scales as 1/lambda, so ln S scales as 1/lambda^2.
    rms = 100.0
    assert (
        abs(np.log(marechal_strehl(rms, WL / 2)) / np.log(marechal_strehl(rms, WL)) / 4 - 1)
        < DOUBLE
    )


def test_radial_profile_and_mean_contrast_invariants(camera):
    # Invariants: the profile of a constant image is that constant; the profile of the radius
    # map is the mean radius of each bin (= radii_ld); annulus mean of a constant is the constant.
    const = np.full((camera.n_image, camera.n_image), 3.5e-6)
    radii, prof = camera.radial_profile(const, 0.5)
    assert np.all(np.abs(prof / 3.5e-6 - 1) < DOUBLE)
    r_edge = (camera.n_image - 1 - camera.centre) * camera.pixel_scale  # largest inner circle
    assert r_edge - 0.5 <= radii[-1] < r_edge
    radii, prof = radial_profile(
        camera.radius_map, None, np.arange(0.0, 20.5, 0.5), pixel_scale=camera.pixel_scale
    )
    np.testing.assert_allclose(prof, radii, rtol=DOUBLE)
    lower, upper = np.arange(0.5, 20.0, 0.5), np.arange(1.0, 20.5, 0.5)
    assert np.all((radii[1:] >= lower) & (radii[1:] < upper))
    c_mean = mean_contrast(const, 4.0, 6.0, pixel_scale=camera.pixel_scale)
    assert abs(c_mean / 3.5e-6 - 1) < DOUBLE
    # Two paths: the 4-6 lambda/D mean is the radial profile with the single bin [4, 6).
    image = camera.diffraction_psf
    _, one_bin = radial_profile(image, None, [4.0, 6.0], pixel_scale=camera.pixel_scale)
    assert abs(camera.mean_contrast(image) / one_bin[0] - 1) < DOUBLE


def test_result_roundtrip_and_no_coronagraph(pupil):
    cam = ScienceCamera(pupil, field_of_view=8.0, coronagraph=False)
    exposure = cam.long_exposure()
    exposure.add(np.zeros((64, 64)))
    assert exposure.coronagraphic is None
    result = exposure.result()
    assert not result.coronagraph
    # Without coronagraph the "contrast" is the raw PSF: the Airy halo, far above 1e-10.
    assert result.mean_contrast_4_6 == pytest.approx(cam.mean_contrast(cam.diffraction_psf))
    again = ScienceResult.from_dict(result.to_dict())
    assert again.strehl == result.strehl and again.n_frames == 1
    np.testing.assert_array_equal(again.contrast_profile, result.contrast_profile)
    with pytest.raises(ValueError, match="n_frames"):
        ScienceResult(1.0, 1e-6, [1.0], [1e-6], n_frames=0)


def test_bad_inputs_raise_clear_errors(pupil, camera):
    with pytest.raises(ValueError, match="oversampling must be >= 2"):
        ScienceCamera(pupil, oversampling=1.5)
    with pytest.raises(ValueError, match="wavelength"):
        ScienceCamera(pupil, wavelength=-1.65e-6)
    with pytest.raises(ValueError, match="metres"):
        ScienceCamera(pupil, wavelength=1650.0)
    with pytest.raises(ValueError, match="field_of_view"):
        ScienceCamera(pupil, field_of_view=40.0)
    with pytest.raises(ValueError, match="precision"):
        ScienceCamera(pupil, precision="half")
    with pytest.raises(TypeError, match="pupil"):
        ScienceCamera(np.ones((64, 64)))
    exposure = camera.long_exposure()
    with pytest.raises(ValueError, match=r"opd_maps must have shape \(n_frames, 64, 64\)"):
        exposure.add(np.zeros((2, 63, 64)))
    with pytest.raises(ValueError, match="finite"):
        exposure.add(np.full((1, 64, 64), np.nan))
    assert exposure.n_frames == 0
    with pytest.raises(ValueError, match="r_out"):
        camera.mean_contrast(camera.diffraction_psf, 4.0, 40.0)
    with pytest.raises(ValueError, match="rms_nm"):
        marechal_strehl(-1.0)


def test_contrast_at_small_separations_sees_a_close_speckle(pupil, camera):
    # Oracle: a sine ripple of k = 1.5 cycles per pupil puts its speckles at 1.5 lambda/D:
    # the 1-2 lambda/D contrast holds them (a few (a/2)^2 spread over the annulus), the 4-6
    # lambda/D contrast only Airy wings; a ripple at k = 5 does the opposite. The result
    # carries both; a file without the 1-2 figure (written before it) reads NaN.
    a = 0.05
    out = {}
    for k in (1.5, 5.0):
        exposure = camera.long_exposure()
        opd = a * np.sin(2 * np.pi * k * pupil.x / pupil.diameter) * NM_PER_RAD
        exposure.add(np.asarray(opd)[None])
        out[k] = exposure.result()
    near, far = out[1.5], out[5.0]
    assert near.mean_contrast_1_2 > 10 * near.mean_contrast_4_6
    assert far.mean_contrast_4_6 > 10 * far.mean_contrast_1_2
    d = near.to_dict()
    d.pop("mean_contrast_1_2")
    assert np.isnan(type(near).from_dict(d).mean_contrast_1_2)
