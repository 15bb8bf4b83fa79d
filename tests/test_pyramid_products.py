"""The pyramid's propagation as line-operator products: analytic kernel, former path, loop.

Oracles: the closed form of the line operator's kernel (two geometric series, see
``aocontrol/sim/wfs/_pyramid_lines.py``); the former FFT propagation
(``tests/_pyramid_reference.py``) to a stated tolerance; the textbook beam-tilt propagation is
in ``tests/test_wfs.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

from aocontrol.sim.pupil import vlt_pupil
from aocontrol.sim.wfs import PyramidWFS
from aocontrol.sim.wfs._pyramid_lines import gemm_acc, line_operator, parity_classes

#: Single precision: complex64 rounding (~6e-8 per operation) accumulated over the pupil
#: samples of a product and the modulation points; measured ~1e-6 of the largest pixel.
SINGLE_TOL = 1e-5
#: Double precision: the two computations are the same linear map, rounding only.
DOUBLE_TOL = 1e-12


def _mask(n: int, n_pix: int) -> np.ndarray:
    u = np.fft.fftfreq(n) * n
    r0 = (n - n_pix) // 2
    return np.exp(0.5j * np.pi * np.abs(u + 0.5) - 2j * np.pi * r0 * u / n)


@pytest.mark.parametrize(("n", "n_pix"), [(40, 16), (72, 32), (168, 80)])
def test_line_operator_equals_its_closed_form(n, n_pix):
    # Oracle: k(d) = IFFT(mask)(d), summed as two geometric series (one per face):
    # d + s1 odd: (2/n) (e^{i pi/4} / (1 - w^m) - e^{-i pi/4} / (1 + w^m)), m = d + s1;
    # d + s1 even: e^{+-i pi/4} / 2 at the direct images (m = 0 or n/2 mod n), else 0.
    lines = np.arange(n)
    op = line_operator(n, n_pix, _mask(n, n_pix), lines)
    s1 = n // 4 - (n - n_pix) // 2
    m = (lines[:, None] - np.arange(n_pix)[None, :] + s1) % n
    w = np.exp(2j * np.pi * m / n)
    odd = m % 2 == 1
    want = np.zeros((n, n_pix), complex)
    e = np.exp(0.25j * np.pi)
    want[odd] = (2 / n) * (e / (1 - w[odd]) - np.conj(e) / (1 + w[odd]))
    want[m == 0] = e / 2
    want[m == n // 2] = np.conj(e) / 2
    assert np.abs(op - want).max() < 1e-12


def test_parity_classes_rebuild_the_operator():
    # Invariant: dense part (one parity) + deltas (the other) = the operator, every line.
    n, n_pix = 72, 32
    lines = np.r_[2:34, 38:70]
    op = line_operator(n, n_pix, _mask(n, n_pix), lines)
    rebuilt = np.zeros_like(op)
    for q, cls in enumerate(parity_classes(op)):
        rebuilt[np.ix_(cls.lines, np.arange(1 - q, n_pix, 2))] = cls.dense
        for r0, r1, s0, value in cls.runs:
            rows = cls.lines[r0:r1]
            rebuilt[rows, q + 2 * np.arange(s0, s0 + r1 - r0)] = value
    assert np.abs(rebuilt - op).max() < 1e-12


def test_parity_structure_is_checked():
    # Twin: a mask that is not two linear phases (a quadratic phase) has no parity structure.
    n, n_pix = 40, 16
    u = np.fft.fftfreq(n) * n
    with pytest.raises(RuntimeError, match="parity structure"):
        parity_classes(line_operator(n, n_pix, np.exp(0.01j * u**2), np.arange(n)))


@pytest.mark.parametrize("dtype", [np.complex64, np.complex128])
def test_gemm_acc_adds_the_product_in_place(dtype):
    rng = np.random.default_rng(0)
    a, b, c = (
        (rng.normal(size=s) + 1j * rng.normal(size=s)).astype(dtype)
        for s in ((5, 3), (3, 7), (5, 7))
    )
    want = c + a @ b
    buf = c.copy()
    gemm_acc(a, b, buf)
    tol = 1e-5 if dtype == np.complex64 else 1e-12
    assert np.abs(buf - want).max() < tol * np.abs(want).max()


@pytest.mark.parametrize(("precision", "tol"), [("single", SINGLE_TOL), ("double", DOUBLE_TOL)])
def test_products_agree_with_the_former_fft_propagation(precision, tol):
    from _pyramid_reference import FFTPyramid

    pupil = vlt_pupil(32)
    kw = dict(n_subapertures=16, modulation=3.0, precision=precision)
    rng = np.random.default_rng(5)
    opd = rng.normal(size=(2, 32, 32)) * 80.0  # strong: far out of the linear range [nm]
    new = PyramidWFS(pupil, 1.1e-6, **kw).detector_image(opd)
    ref = FFTPyramid(pupil, 1.1e-6, **kw).detector_image(opd)
    assert np.abs(new - ref).max() < tol * ref.max()


def test_blas_threads_do_not_change_the_frame():
    # workers only sets the BLAS threads of the products: same frames to rounding.
    pupil = vlt_pupil(32)
    opd = np.random.default_rng(2).normal(size=(32, 32)) * 40.0
    one = PyramidWFS(pupil, 1.1e-6, n_subapertures=16, workers=1).detector_image(opd)
    two = PyramidWFS(pupil, 1.1e-6, n_subapertures=16, workers=2).detector_image(opd)
    assert np.abs(one - two).max() < SINGLE_TOL * one.max()


def test_noise_free_diffractive_loop_agrees_with_the_former_propagation(monkeypatch):
    # The golden diffractive loop without detector noise (a noisy one diverges at the first
    # Poisson draw that the ~1e-7 differences flip): same telemetry to LOOP_TOL of its RMS
    # (single-precision differences of the signals, through calibration and 120 frames).
    import _golden_loop
    from _pyramid_reference import FFTPyramid

    import aocontrol.sim.wfs
    from aocontrol.sim.wfs import DiffractiveSensor

    loop_tol = 1e-4

    def factory(wfs, recon, photons, read_noise):
        return DiffractiveSensor(wfs, recon)

    new = _golden_loop.diffractive_run(factory)
    monkeypatch.setattr(aocontrol.sim.wfs, "PyramidWFS", FFTPyramid)
    ref = _golden_loop.diffractive_run(factory)
    for name in ("measurements", "residuals"):
        a, b = np.asarray(new.telemetry[name]), np.asarray(ref.telemetry[name])
        assert np.abs(a - b).max() < loop_tol * np.sqrt(np.mean(b**2)), name
