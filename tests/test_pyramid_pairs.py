"""The pyramid's propagation as real products of conjugate pairs (issue 15, pyramid cost).

Oracles: the line operator itself (the pairs must rebuild it); frames and signals recorded
from the propagation the library used before (main ccdd059: complex line-operator products per
modulation point, double precision; ``tests/data/pyramid_main_frames.npz``, 34 kB: for each
case of ``CASES``, two OPD maps drawn in order from ``default_rng(15)``, 5 and 120 nm RMS,
through ``detector_image`` and ``signals``); the former FFT propagation
(``tests/_pyramid_reference.py``) at the stage-2 geometry.

Tolerances. Double precision: the same linear maps in another order, rounding only
(``DOUBLE_TOL`` of the largest pixel; measured ~1e-13). Single precision: complex64 / float32
rounding through two products and the sum over the points (``SINGLE_TOL``; measured ~2e-7 of
the largest pixel). The mirror points on the x axis (``k = 0``, ``n / 2``) are taken with a
y tilt of exactly 0 (``sin(pi)`` is 1.2e-16 in floating point): a change of ~1e-15 rad.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from aocontrol.sim.pupil import vlt_pupil
from aocontrol.sim.wfs import PyramidWFS
from aocontrol.sim.wfs._pyramid_lines import gemm_acc, image_pairs, line_operator

DOUBLE_TOL = 1e-11
SINGLE_TOL = 1e-5
GOLDEN = Path(__file__).parent / "data" / "pyramid_main_frames.npz"
#: (n_pix, n_subapertures, modulation, n_modulation_points) of the recorded frames
CASES = {"a": (24, 12, 2.0, 7), "b": (24, 12, 0.0, None), "c": (25, 10, 1.5, 12)}


def _mask(n: int, n_pix: int) -> np.ndarray:
    u = np.fft.fftfreq(n) * n
    r0 = (n - n_pix) // 2
    return np.exp(0.5j * np.pi * np.abs(u + 0.5) - 2j * np.pi * r0 * u / n)


@pytest.mark.parametrize(("n", "n_pix"), [(40, 16), (72, 32), (76, 33), (168, 80)])
def test_image_pairs_rebuild_the_line_operator(n, n_pix):
    # Invariant: first image u - i v + c0 (dense) + delta, second u + i v + c0 + conj(delta),
    # on the rows of the two pupil images (r0 -+ n/4 + [0, n_pix)).
    r0 = (n - n_pix) // 2
    lines = np.r_[r0 - n // 4 + np.arange(n_pix), r0 + n // 4 + np.arange(n_pix)]
    op = line_operator(n, n_pix, _mask(n, n_pix), lines)
    rebuilt = np.zeros_like(op)
    for q, pr in enumerate(image_pairs(op, lines, n)):
        dense = np.arange(1 - q, n_pix, 2)
        src = q + 2 * (pr.src + np.arange(pr.first.size))
        for rows, sign, delta in ((pr.first, -1, pr.delta), (pr.second, 1, np.conj(pr.delta))):
            rebuilt[np.ix_(rows, dense)] = pr.u + sign * 1j * pr.v + pr.c0
            rebuilt[rows, src] = delta
        assert abs(pr.c0.real) == 0 and abs(pr.c0.imag) > 0  # the DC term is imaginary
    assert np.abs(rebuilt - op).max() < 1e-12


def test_conjugate_structure_is_checked():
    # Twin: a mask that is not two opposite linear phases (a quadratic phase) is refused.
    n, n_pix = 40, 16
    lines = np.r_[2:18, 22:38]
    u = np.fft.fftfreq(n) * n
    with pytest.raises(RuntimeError, match="structure|pair up"):
        image_pairs(line_operator(n, n_pix, np.exp(0.01j * u**2), lines), lines, n)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_gemm_acc_real(dtype):
    rng = np.random.default_rng(1)
    a, b, c = (rng.normal(size=s).astype(dtype) for s in ((4, 3), (3, 6), (4, 6)))
    want = c + a @ b
    gemm_acc(a, b, c)
    assert np.abs(c - want).max() < (1e-5 if dtype == np.float32 else 1e-12) * np.abs(want).max()


@pytest.fixture(scope="module")
def golden():
    with np.load(GOLDEN) as data:
        return dict(data)


def _case(name: str, precision: str) -> tuple[PyramidWFS, np.ndarray]:
    rng = np.random.default_rng(15)
    for key, (n_pix, n_sub, mod, npts) in CASES.items():
        opd = rng.normal(size=(2, n_pix, n_pix)) * np.array([5.0, 120.0])[:, None, None]
        if key == name:
            wfs = PyramidWFS(
                vlt_pupil(n_pix),
                1.1e-6,
                n_subapertures=n_sub,
                modulation=mod,
                n_modulation_points=npts,
                precision=precision,
            )
            return wfs, opd
    raise KeyError(name)


@pytest.mark.parametrize("name", sorted(CASES))
@pytest.mark.parametrize(("precision", "tol"), [("double", DOUBLE_TOL), ("single", SINGLE_TOL)])
def test_pairs_equal_the_former_propagation(golden, name, precision, tol):
    # Oracle: frames and signals of main's propagation on a weak (5 nm) and a strong (120 nm
    # RMS, far out of the linear range) phase; one point (r = 0), odd point count, odd n_pix.
    wfs, opd = _case(name, precision)
    frames = wfs.detector_image(opd)
    ref = golden[f"{name}_frames"]
    for i in range(2):
        assert np.abs(frames[i] - ref[i]).max() < tol * ref[i].max(), i
    sig, ref_sig = wfs.signals(opd), golden[f"{name}_signals"]
    for i in range(2):
        scale = max(np.sqrt(np.mean(ref_sig[i] ** 2)), 1e-3)
        assert np.abs(sig[i] - ref_sig[i]).max() < 10 * tol * scale, i


def test_pairs_equal_the_fft_propagation_at_saxo_plus_sampling():
    # Oracle: the FFT propagation at the stage-2 geometry (80 px, 40x40, 3 lambda/D, 20 points).
    from _pyramid_reference import FFTPyramid

    kw = dict(n_subapertures=40, modulation=3.0, n_modulation_points=20, precision="single")
    opd = np.random.default_rng(4).normal(size=(80, 80)) * 60.0
    new = PyramidWFS(vlt_pupil(80), 1.04e-6, **kw).detector_image(opd)
    ref = FFTPyramid(vlt_pupil(80), 1.04e-6, **kw).detector_image(opd)
    assert np.abs(new - ref).max() < SINGLE_TOL * ref.max()


def test_frame_derivative_is_the_limit_of_the_difference():
    # Oracle: central difference of the frames (double precision; the derivative uses the
    # bilinear accumulation of the pair products, the frames the quadratic one).
    wfs, opd = _case("a", "double")
    d = np.random.default_rng(3).normal(size=(1, 24, 24))
    eps = 1e-3
    fd = (wfs.detector_image(opd[1] + eps * d[0]) - wfs.detector_image(opd[1] - eps * d[0])) / (
        2 * eps
    )
    an = wfs.frame_derivative(opd[1], d)[0]
    assert np.abs(an - fd).max() < 1e-6 * np.abs(fd).max()
