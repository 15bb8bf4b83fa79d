"""The cascade's projection of phases on both bases: dense, or through the mirrors' separable
Gaussian influence functions (aocontrol.sim._projection)."""

import dataclasses

import numpy as np
import pytest

from aocontrol.controllers import Integrator
from aocontrol.sim.atmosphere import Atmosphere, Layer
from aocontrol.sim.dm import DeformableMirror
from aocontrol.sim.loop import LinearModalSensor, Stage, run_cascade
from aocontrol.sim.modes import ModalProjector, SeparableMirror, kl_basis
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.sim.science import ScienceCamera

# float32 projection through the mirrors: the relative rounding of the m2c product (command
# vectors of tens of nm per nm RMS) is ~1e-4 of a mode's largest coefficient at the
# full-scale sizes (1200 + 540 modes, 96 px), ~3e-5 for the dense float32 product; bound
# 1e-3 here, and 1e-5 on the RMS over all coefficients (measured ~6e-7 at full scale).
MAX_REL, RMS_REL = 1e-3, 1e-5


@pytest.fixture(scope="module")
def scene():
    pupil = vlt_pupil(64)
    dm1, dm2 = DeformableMirror(pupil, n_actuators=9), DeformableMirror(pupil, n_actuators=7)
    return pupil, dm1, dm2, kl_basis(dm1, 40, r0=0.15), kl_basis(dm2, 20, r0=0.15)


def test_separable_mirror_reproduces_the_influence_functions(scene):
    # Two implementations: the DM's influence functions on the valid pixels and the outer
    # products of the factors (the Gaussian is separable exactly).
    pupil, dm1, _, _, _ = scene
    m = SeparableMirror.from_dm(dm1)
    rows, cols = np.divmod(m.act_index, m.n_actuators)
    maps = m.gy[rows][:, :, None] * m.gx[cols][:, None, :]
    np.testing.assert_allclose(pupil.to_vector(maps), dm1.influence, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(m.mean, dm1.influence.mean(axis=1), rtol=1e-12)


def test_separable_projection_agrees_with_the_dense_product(scene):
    pupil, _, _, b1, b2 = scene
    phase = Atmosphere(pupil, 0.15, [Layer(0.0, 1.0, 10.0, 30.0)], 3000.0, rng=1)
    phi = phase.phase_vectors(200)
    ref = phi.astype(float) @ np.concatenate([b1.modes, b2.modes]).T / pupil.n_valid
    sep = ModalProjector((b1, b2), separable=True)
    dense = ModalProjector((b1, b2), separable=False)
    assert sep.path == "separable" and dense.path == "dense"
    # At these small sizes the automatic choice is the dense product (not cheaper).
    assert ModalProjector((b1, b2)).path == "dense"
    for proj in (sep, dense):
        got = proj(phi)
        assert got.dtype == np.float64 and got.shape == ref.shape
        assert np.max(np.abs(got - ref) / np.abs(ref).max(axis=0)) < MAX_REL
        assert np.sqrt(np.mean((got - ref) ** 2) / np.mean(ref**2)) < RMS_REL
    # The two paths differ by rounding only, not by the same rounding (the check can fail).
    assert not np.array_equal(sep(phi), dense(phi))


def test_a_mirror_that_is_not_the_basis_is_refused(scene):
    # Twin: the factors of a mirror of another coupling (same actuators) fail the probe.
    pupil, _, dm2, b1, b2 = scene
    other = DeformableMirror(pupil, n_actuators=9, coupling=0.2)
    wrong = dataclasses.replace(b1, mirror=SeparableMirror.from_dm(other))
    assert ModalProjector((wrong, b2)).path == "dense"
    from aocontrol.sim import _projection

    with pytest.MonkeyPatch.context() as mp:  # cheap enough: only the probe refuses it
        mp.setattr(_projection, "_SEPARABLE_COST_FRACTION", 10.0)
        assert ModalProjector((b1, b2)).path == "separable"
        assert ModalProjector((wrong, b2)).path == "dense"
    with pytest.raises(ValueError, match="does not reproduce the modes"):
        ModalProjector((wrong, b2), separable=True)
    # A mirror of another actuator count is refused by the basis itself, naming it.
    with pytest.raises(ValueError, match="mirror must have n_act=77 actuators"):
        dataclasses.replace(b1, mirror=SeparableMirror.from_dm(dm2))
    with pytest.raises(TypeError, match="mirror must be a SeparableMirror"):
        dataclasses.replace(b1, mirror=dm2)
    no_mirror = dataclasses.replace(b1, mirror=None)
    with pytest.raises(ValueError, match="basis 0 has no separable mirror"):
        ModalProjector((no_mirror, b2), separable=True)


def test_cascade_through_the_mirrors_agrees_with_the_dense_cascade(scene, monkeypatch):
    # Same run with the bases stripped of their mirrors (dense projection): results agree to
    # the float32 rounding of the projection (noise-free, no stroke: a linear loop). The
    # separable path is made the choice at these small sizes.
    from aocontrol.sim import _projection

    monkeypatch.setattr(_projection, "_SEPARABLE_COST_FRACTION", 10.0)
    pupil, _, _, b1, b2 = scene
    runs = []
    for mirrors in (True, False):
        bases = [b if mirrors else dataclasses.replace(b, mirror=None) for b in (b1, b2)]
        s1 = Stage(Integrator(0.4, fs=1000.0, n_modes=40), LinearModalSensor(1.0, 0.0), 0.84)
        s2 = Stage(Integrator(0.5, fs=3000.0, n_modes=20), LinearModalSensor(1.0, 0.0), 0.83)
        atm = Atmosphere(pupil, 0.15, [Layer(0.0, 1.0, 10.0, 30.0)], 3000.0, rng=4)
        runs.append(
            run_cascade(
                s1,
                s2,
                atm,
                600,
                scheme="dcao",
                basis1=bases[0],
                basis2=bases[1],
                science=ScienceCamera(pupil, field_of_view=8.0).long_exposure(),
                science_every=5,
            )
        )
    a, b = runs
    for i in range(2):
        np.testing.assert_allclose(
            a.stages[i].residual_variance, b.stages[i].residual_variance, rtol=1e-4
        )
    assert abs(a.science.strehl - b.science.strehl) < 1e-6
    assert a.stages[1].residual_variance.tolist() != b.stages[1].residual_variance.tolist()


def test_the_pair_setup_is_built_once_and_released_with_the_bases(scene):
    # Invariant: the runs of a study share P and the projector; a cache entry does not keep
    # its bases alive (weak keys; the projector holds no reference to them).
    import gc
    import weakref

    from aocontrol.sim._cascade import _PAIRS, _pair_setup

    _, _, _, b1, b2 = scene
    first = _pair_setup(b1, b2)
    assert _pair_setup(b1, b2) is first
    np.testing.assert_array_equal(first[0], b2.modes @ b1.modes.T / b1.modes.shape[1])
    c1, c2 = dataclasses.replace(b1), dataclasses.replace(b2)
    _pair_setup(c1, c2)
    ref = weakref.ref(c1)
    n = len(_PAIRS)
    del c1, c2
    gc.collect()
    assert ref() is None and len(_PAIRS) == n - 1


def test_separable_synthesis_agrees_with_the_modes(scene):
    # Oracle: coeffs @ modes in float64; the separable path is its float32 transpose.
    pupil, _, _, b1, b2 = scene
    coeffs = np.random.default_rng(2).standard_normal((30, 60)) * np.linspace(50, 1, 60)
    ref = coeffs @ np.concatenate([b1.modes, b2.modes])
    sep = ModalProjector((b1, b2), separable=True)
    dense = ModalProjector((b1, b2), separable=False)
    for proj in (sep, dense):
        got = proj.synthesize(coeffs)
        assert got.dtype == np.float32 and got.shape == (30, pupil.n_valid)
        assert np.sqrt(np.mean((got - ref) ** 2) / np.mean(ref**2)) < RMS_REL
    assert not np.array_equal(sep.synthesize(coeffs), dense.synthesize(coeffs))


def test_the_float32_factors_hold_no_subnormal_numbers():
    # The Gaussian tails of a 28-actuator mirror fall in float32's subnormal range (a BLAS
    # slow path on x86: 14x slower products measured); the projector flushes them to zero
    # and projects as before.
    pupil = vlt_pupil(64)
    dm = DeformableMirror(pupil, n_actuators=28)
    basis = kl_basis(dm, 20, r0=0.15)
    raw = np.abs(SeparableMirror.from_dm(dm).gx.astype(np.float32))
    tiny = np.finfo(np.float32).tiny
    assert np.any((raw > 0) & (raw < tiny))  # the case the flush is for
    proj = ModalProjector((basis,), separable=True)
    for gxt, gy, _ in proj._mirrors:
        for f in (gxt, gy):
            assert f.dtype == np.float32 and not np.any((f != 0) & (np.abs(f) < tiny))
    phi = np.random.default_rng(2).standard_normal((50, pupil.n_valid))
    ref = phi @ basis.modes.T / pupil.n_valid
    got = proj(phi)
    assert np.max(np.abs(got - ref) / np.abs(ref).max(axis=0)) < MAX_REL
