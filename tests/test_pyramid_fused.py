"""The pyramid frame's compiled element-wise passes (issues 19, 34): oracle, the numpy passes.

:mod:`aocontrol.sim.wfs._pyramid_fused` replaces the pupil field, the x tilts and step x's
direct images, the y tilts, the constant row, step y's direct images, the intensity sums and
the binning of :meth:`PyramidWFS._frames`, and the bilinear sums of the frame derivatives, by
compiled loops; the numpy path (``$AOCONTROL_NO_NUMBA``) stays and is the oracle here. The y
tilts and the constant row are the same operations in the same order: bit for bit; so are the
products, written without the direct images (``beta = 0``) plus the direct images (as the
intensity loop adds them). The intensity loop sums in float64 (the numpy path: float32,
``einsum``): the frames agree to float32 rounding (``SINGLE_TOL`` of the largest pixel, as
``tests/test_pyramid_pairs.py``; measured ~1e-7) and to ``DOUBLE_TOL`` in double precision
(measured ~2e-16). The recorded frames of ``tests/test_pyramid_pairs.py`` check the compiled
path against the former propagation.
"""

from __future__ import annotations

import numpy as np
import pytest

from aocontrol._jit import ENV_NO_NUMBA
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.sim.wfs import PyramidWFS, _pyramid_fused
from aocontrol.sim.wfs import pyramid as pyramid_module

SINGLE_TOL = 1e-5
DOUBLE_TOL = 1e-12
#: (n_pix, n_subapertures, modulation, n_modulation_points): even and odd pupils, two-point
#: and one-point pairs, no modulation (one point, no two-point pair)
GEOMETRIES = [(24, 12, 2.0, 7), (25, 10, 1.5, 12), (24, 12, 0.0, None), (32, 16, 3.0, None)]


def _wfs(geometry, precision="single"):
    n_pix, n_sub, mod, n_pts = geometry
    return PyramidWFS(
        vlt_pupil(n_pix),
        1.1e-6,
        n_subapertures=n_sub,
        modulation=mod,
        n_modulation_points=n_pts,
        precision=precision,
    )


def _opds(n_pix, m=2):
    rng = np.random.default_rng(19)
    return rng.standard_normal((m, n_pix, n_pix)) * np.array([20.0, 150.0])[:m, None, None]


@pytest.fixture(autouse=True)
def _compiled():
    if _pyramid_fused.kernels() is None:  # pragma: no cover - numba is a dependency
        pytest.skip("numba is not available or disabled")


@pytest.mark.parametrize("geometry", GEOMETRIES)
@pytest.mark.parametrize(("precision", "tol"), [("single", SINGLE_TOL), ("double", DOUBLE_TOL)])
def test_compiled_frames_equal_the_numpy_frames(monkeypatch, geometry, precision, tol):
    opd = _opds(geometry[0])
    fused = _wfs(geometry, precision).detector_image(opd)
    monkeypatch.setenv(ENV_NO_NUMBA, "1")
    ref = _wfs(geometry, precision).detector_image(opd)
    err = np.abs(fused - ref).max() / ref.max()
    assert err < tol
    # a twin that must fail: the same comparison sees a 1e-3 change of one pixel
    bad = fused.copy()
    bad[0, 3, 4] += 1e-3 * ref.max()
    assert np.abs(bad - ref).max() / ref.max() > tol


@pytest.mark.parametrize("geometry", [GEOMETRIES[0], GEOMETRIES[1], GEOMETRIES[3]])
@pytest.mark.parametrize(("precision", "tol"), [("single", SINGLE_TOL), ("double", DOUBLE_TOL)])
def test_compiled_derivatives_equal_the_numpy_derivatives(monkeypatch, geometry, precision, tol):
    # The frame derivatives (the interaction matrix, the optical gains) through the compiled
    # bilinear sums; oracle: the numpy path's einsum sums.
    n_pix = geometry[0]
    opd = _opds(n_pix, 1)[0]
    directions = _opds(n_pix)
    fused = _wfs(geometry, precision).frame_derivative(opd, directions)
    monkeypatch.setenv(ENV_NO_NUMBA, "1")
    ref = _wfs(geometry, precision).frame_derivative(opd, directions)
    scale = np.abs(ref).max()
    assert np.abs(fused - ref).max() < tol * scale
    # a twin that must fail: the derivative along a doubled direction is not the same
    assert np.abs(2 * fused - ref).max() > tol * scale


def test_several_chunks_of_pairs(monkeypatch):
    # The chunked y step (small chunks forced): compiled and numpy paths still agree.
    monkeypatch.setattr(pyramid_module, "_CHUNK_BYTES", 1)
    geometry = (24, 12, 2.0, 12)
    wfs = _wfs(geometry)
    assert len(wfs._chunks) > 3
    opd = _opds(24)
    fused = wfs.detector_image(opd)
    monkeypatch.setenv(ENV_NO_NUMBA, "1")
    ref = _wfs(geometry).detector_image(opd)
    assert np.abs(fused - ref).max() < SINGLE_TOL * ref.max()


@pytest.mark.parametrize("geometry", [GEOMETRIES[0], GEOMETRIES[1]])
def test_tilts_are_bit_identical_and_products_differ_by_the_direct_images(geometry):
    # Step y's inputs (y tilts, constant row) are the numpy ones bit for bit; the products
    # without the direct images plus x_q[src + l] * delta_q are the numpy products.
    ref_wfs, new_wfs = _wfs(geometry), _wfs(geometry)
    field = ref_wfs._field(np.deg2rad(_opds(geometry[0], 1)[0]))
    kernels = _pyramid_fused.kernels()
    plan = ref_wfs._plan
    n_chunks = len(ref_wfs._chunks)
    with ref_wfs._blas_threads():
        ref_steps = []
        for ci, f in enumerate(ref_wfs._fields(field)):
            xs = ref_wfs._work["xs"]
            ref_steps.append(([xs[p * n_chunks + ci].copy() for p in (0, 1)], f[0].copy()))
        for (x_ref, o_ref), f in zip(ref_steps, new_wfs._fields(field, kernels), strict=True):
            for p in (0, 1):
                assert np.array_equal(f[3][p], x_ref[p])
            pr = plan["pairs"][0]
            direct = f[3][0][pr.src : pr.src + pr.first.size, None] * plan["delta"][0]
            assert np.array_equal(f[0] + direct, o_ref)
