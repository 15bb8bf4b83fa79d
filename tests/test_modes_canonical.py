"""KL modes independent of the process: canonical orientation of degenerate modes and signs.

The pupil's symmetry makes KL variances come in degenerate pairs, and LAPACK returns any
orthonormal basis of a degenerate eigenspace, which depends on the BLAS threads: before the
canonical orientation (:func:`aocontrol.sim.modes.kl_basis`, step 5) two processes built
different modes from the same settings (max difference ~1x a mode's largest value with 1 and
2 BLAS threads), and the runs on them differed by a few per cent.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aocontrol.sim.dm import DeformableMirror
from aocontrol.sim.modes import _canonical_rotation, _reference_maps, kl_basis
from aocontrol.sim.pupil import vlt_pupil

# Two builds of the same basis by different BLAS paths: rounding of the eigensolver and of the
# products (measured <= 2e-11 of a mode's largest value, 100 modes on 1360 actuators).
SAME_BASIS_TOL = 1e-10
# The same run on the two bases: the rounding above through a 150-frame loop.
SAME_RUN_RTOL = 1e-8

# Builds the basis with N BLAS threads, then a short noisy loop on turbulence with it (the
# engine's own thread limit, the same in both processes); prints the modes and the figures.
_BUILD_AND_RUN = """
import json, sys
import numpy as np
from threadpoolctl import threadpool_limits
from aocontrol.controllers import Integrator
from aocontrol.sim.atmosphere import Atmosphere, Layer
from aocontrol.sim.dm import DeformableMirror
from aocontrol.sim.loop import LinearModalSensor, Stage, TurbulenceSource, run_loop
from aocontrol.sim.modes import kl_basis
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.sim.science import ScienceCamera

pupil = vlt_pupil(24)
with threadpool_limits(int(sys.argv[1]), user_api="blas"):
    basis = kl_basis(DeformableMirror(pupil, n_actuators=11), 40, r0=0.15)
n = basis.n_modes
res = run_loop(
    Stage(Integrator(np.linspace(0.3, 0.5, n), fs=3000.0),
          LinearModalSensor(np.linspace(0.8, 1.0, n), 2.0), 0.83),
    TurbulenceSource(Atmosphere(pupil, 0.15, [Layer(0.0, 1.0, 10.0, 30.0)], 3000.0, rng=4), basis),
    150, science=ScienceCamera(pupil, field_of_view=6.0).long_exposure(), rng=1, basis=basis,
    science_every=10,
)
np.save(sys.argv[2], basis.modes)
fig = {"strehl": res.science.strehl, "residual": res.residual_variance.sum()}
print(json.dumps({k: float(v) for k, v in fig.items()}))
"""


def _build_and_run(threads: int, path) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    out = subprocess.run(
        [sys.executable, "-c", _BUILD_AND_RUN, str(threads), str(path)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_basis_and_run_identical_with_1_and_2_blas_threads(tmp_path):
    # Oracle: the same settings give the same modes (to rounding) whatever the BLAS path,
    # and so the same run. Failed before the canonical orientation (modes 1.2x apart).
    fig = {t: _build_and_run(t, tmp_path / f"modes{t}.npy") for t in (1, 2)}
    a, b = np.load(tmp_path / "modes1.npy"), np.load(tmp_path / "modes2.npy")
    assert np.max(np.abs(a - b)) < SAME_BASIS_TOL * np.max(np.abs(a))
    for k in ("strehl", "residual"):
        assert fig[1][k] == pytest.approx(fig[2][k], rel=SAME_RUN_RTOL, abs=0), (k, fig)


@pytest.fixture(scope="module")
def basis11():
    return kl_basis(DeformableMirror(vlt_pupil(24), n_actuators=11), 60, r0=0.15)


def _pairs(basis):
    var = basis.variances
    rel = -np.diff(var[2:]) / var[2]
    return [i + 2 for i in np.flatnonzero(rel < 1e-8)]


def test_degenerate_pairs_are_even_and_odd_in_x(basis11):
    # Oracle: the VLT pupil and the DM grid are symmetric under x -> -x, which maps each
    # degenerate eigenspace to itself; the canonical basis of a pair (projections of the
    # x-even then the x-odd reference) is one x-even and one x-odd mode, like Zernike's
    # cos/sin pairs.
    p = basis11.pupil
    pairs = _pairs(basis11)
    assert len(pairs) >= 5
    maps = p.to_map(basis11.modes)
    flipped = p.to_vector(maps[:, :, ::-1])
    parity = np.sum(basis11.modes * flipped, axis=1) / np.sum(basis11.modes**2, axis=1)
    for i in pairs:
        assert parity[i] == pytest.approx(1, abs=1e-9) and parity[i + 1] == pytest.approx(
            -1, abs=1e-9
        ), (i, parity[i : i + 2])


def test_signs_positive_on_the_sign_reference(basis11):
    # Oracle: the documented sign rule, every mode from 2 on has a positive overlap with the
    # fixed sign map; tip and tilt point to +x and +y.
    from aocontrol.sim.modes import _sign_reference

    p = basis11.pupil
    assert np.all(basis11.modes[2:] @ _sign_reference(p) > 0)
    assert basis11.modes[0] @ p.to_vector(p.x) > 0 and basis11.modes[1] @ p.to_vector(p.y) > 0


@settings(max_examples=25, deadline=None)
@given(
    k=st.integers(2, 4),
    seed=st.integers(0, 2**32 - 1),
)
def test_canonical_rotation_does_not_depend_on_the_starting_basis(k, seed):
    # Oracle: two orthonormal bases of the same subspace (one a random rotation of the
    # other, as two eigensolvers may return) give the same canonical modes.
    rng = np.random.default_rng(seed)
    pupil = vlt_pupil(16)
    refs = _reference_maps(pupil, 2 * k + 4)
    basis, _ = np.linalg.qr(rng.standard_normal((pupil.n_valid, k)))  # (n_valid, k)
    rot, _ = np.linalg.qr(rng.standard_normal((k, k)))
    other = basis @ rot
    canon = [b @ _canonical_rotation(b.T @ refs.T) for b in (basis, other)]
    np.testing.assert_allclose(canon[0], canon[1], atol=1e-12)
    np.testing.assert_allclose(canon[0].T @ canon[0], np.eye(k), atol=1e-12)
