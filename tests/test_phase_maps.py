"""The DM shapes of the diffractive sensor path (aocontrol.sim._phase_maps): float32, through
the mirror's separable influences or a float32 copy of the modes, against ``synthesize``."""

import dataclasses

import numpy as np
import pytest

from aocontrol.sim._phase_maps import ShapeSynthesizer, shape_synthesizer
from aocontrol.sim.dm import DeformableMirror
from aocontrol.sim.modes import kl_basis
from aocontrol.sim.pupil import vlt_pupil

# float32 rounding of the shape, relative to its largest value (measured 1.6e-7 with 400
# modes on 80 px; a wrong mirror, sign or piston gives O(1)).
REL = 1e-5


@pytest.fixture(scope="module")
def basis():
    return kl_basis(DeformableMirror(vlt_pupil(32), n_actuators=9), 40, r0=0.15)


@pytest.mark.parametrize("separable", [True, False])
def test_shapes_equal_the_float64_synthesis(basis, separable):
    # Oracle: ModalBasis.synthesize (float64 product with the modes). Without a mirror the
    # synthesiser takes the dense float32 path.
    b = basis if separable else dataclasses.replace(basis, mirror=None)
    synth = ShapeSynthesizer(b)
    assert synth.separable is separable
    rng = np.random.default_rng(1)
    for _ in range(3):
        y = rng.standard_normal(b.n_modes) * 50.0 / np.arange(1, b.n_modes + 1)
        want = b.synthesize(y)
        got = synth(y)
        assert got.dtype == np.float32 and got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=0, atol=REL * np.abs(want).max())
    # a zero command gives a flat shape (nothing kept from the previous call)
    np.testing.assert_array_equal(synth(np.zeros(b.n_modes)), 0.0)


def test_one_synthesizer_per_basis(basis):
    assert shape_synthesizer(basis) is shape_synthesizer(basis)
    assert shape_synthesizer(dataclasses.replace(basis, mirror=None)) is not shape_synthesizer(
        basis
    )


def test_no_subnormal_factors_at_saxo_plus_sampling():
    # The SAXO+ mirror (28x28) on 80 px: the Gaussian influences' far tails are subnormal in
    # float32 (a product with them runs ~10x slower); the synthesiser's factors hold none,
    # and its shapes stay the float64 synthesis to float32 rounding.
    from aocontrol.sim.dm import SAXO_PLUS_N_ACTUATORS

    b = kl_basis(DeformableMirror(vlt_pupil(80), n_actuators=SAXO_PLUS_N_ACTUATORS), 30, r0=0.15)
    tiny = np.finfo(np.float32).tiny

    def subnormal(a):
        a = np.asarray(a, dtype=np.float32)
        return np.count_nonzero((a != 0) & (np.abs(a) < tiny))

    assert subnormal(b.mirror.gx) > 0  # the twin: the raw factors have them
    synth = ShapeSynthesizer(b)
    assert subnormal(synth._gx) == 0 and subnormal(synth._gyt) == 0
    y = np.random.default_rng(2).standard_normal(b.n_modes) * 20.0
    want = b.synthesize(y)
    np.testing.assert_allclose(synth(y), want, rtol=0, atol=REL * np.abs(want).max())
