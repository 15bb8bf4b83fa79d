"""The engine's settings and fast paths (issue 19): BLAS threads of a run, the sequential
statistics, the single-stage projection through the cached ModalProjector."""

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from aocontrol.controllers import Integrator
from aocontrol.sim._runner import drive
from aocontrol.sim._stage_run import _sequential_sum
from aocontrol.sim.atmosphere import Atmosphere, Layer
from aocontrol.sim.dm import DeformableMirror
from aocontrol.sim.loop import (
    ENV_BLAS_THREADS,
    LinearModalSensor,
    ModalTimeSeries,
    Stage,
    TurbulenceSource,
    engine_blas_threads,
    run_loop,
)
from aocontrol.sim.modes import kl_basis
from aocontrol.sim.pupil import vlt_pupil

FS = 3000.0
# float32 projection (aocontrol.sim._projection): relative rounding ~6e-7 RMS, up to ~2e-4
# of a mode's largest coefficient; bounds 1e-5 (RMS) and 1e-3 (worst), as
# tests/test_projection.py.
MAX_REL, RMS_REL = 1e-3, 1e-5


def _blas_threads_now() -> int:
    return max(int(i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas")


# ------------------------------------------------------------------------ BLAS threads
def test_engine_blas_threads_setting(monkeypatch):
    monkeypatch.delenv(ENV_BLAS_THREADS, raising=False)
    assert engine_blas_threads() == 1
    monkeypatch.setenv(ENV_BLAS_THREADS, " 3 ")
    assert engine_blas_threads() == 3
    monkeypatch.setenv(ENV_BLAS_THREADS, "0")
    assert engine_blas_threads() is None
    for bad in ("two", "-1", "1.5"):
        monkeypatch.setenv(ENV_BLAS_THREADS, bad)
        with pytest.raises(ValueError, match=rf"\$AOCONTROL_ENGINE_BLAS_THREADS .* got '{bad}'"):
            engine_blas_threads()


def test_drive_runs_with_the_engine_blas_threads(monkeypatch):
    # The limit holds inside the chunks and is lifted afterwards; "0" leaves the BLAS alone.
    before = _blas_threads_now()
    seen = []

    def advance(first, m):
        seen.append(_blas_threads_now())

    monkeypatch.delenv(ENV_BLAS_THREADS, raising=False)
    drive(10, 4, advance, ())
    assert seen == [1, 1, 1] and _blas_threads_now() == before
    seen.clear()
    monkeypatch.setenv(ENV_BLAS_THREADS, "0")
    drive(10, 5, advance, ())
    assert seen == [before, before]


def test_run_does_not_depend_on_the_blas_threads_without_products(monkeypatch):
    # A modal loop (no projection) is bit-identical whatever the engine's BLAS threads.
    d = np.random.default_rng(0).standard_normal((300, 5)).cumsum(axis=0)

    def run():
        stage = Stage(Integrator(0.4, fs=FS, n_modes=5), LinearModalSensor(0.8, 0.5), 0.83)
        return run_loop(stage, ModalTimeSeries(d, fs=FS), 300, rng=1, chunk=70)

    monkeypatch.delenv(ENV_BLAS_THREADS, raising=False)
    a = run()
    monkeypatch.setenv(ENV_BLAS_THREADS, "0")
    b = run()
    for name in a.telemetry:
        np.testing.assert_array_equal(a.telemetry[name], b.telemetry[name])
    np.testing.assert_array_equal(a.residual_variance, b.residual_variance)


# ------------------------------------------------------------------ sequential statistics
@pytest.mark.parametrize("shape", [(1, 3), (7, 5), (1200, 540), (333, 1200)])
def test_sequential_sum_is_the_per_frame_sum(shape):
    # Oracle: the per-frame += (the statistics' definition), bit for bit.
    rng = np.random.default_rng(shape[0])
    rows = rng.standard_normal(shape) ** 2 * 10.0 ** rng.uniform(-8, 8, shape)
    total = rng.random(shape[1]) * 1e3
    want = total.copy()
    for row in rows:
        want += row
    np.testing.assert_array_equal(_sequential_sum(total, rows), want)
    # Twin: another order of the same terms (pairwise, as numpy sums a contiguous axis)
    # rounds differently somewhere, so the check sees the order.
    if shape[0] > 100:
        other = total + np.add.reduce(np.ascontiguousarray(rows.T), axis=1)
        assert not np.array_equal(other, want)


# -------------------------------------------------- single-stage projection (TurbulenceSource)
@pytest.fixture(scope="module")
def scene():
    pupil = vlt_pupil(48)
    basis = kl_basis(DeformableMirror(pupil, n_actuators=9), 30, r0=0.15)
    return pupil, basis


def _atmosphere(pupil, seed):
    return Atmosphere(pupil, 0.15, [Layer(0.0, 1.0, 10.0, 30.0)], FS, rng=seed)


def test_turbulence_source_projects_to_the_stated_tolerance(scene):
    # Oracle: the basis' float64 least-squares projection of the same phase.
    pupil, basis = scene
    modal, phase = TurbulenceSource(_atmosphere(pupil, 3), basis).next(200)
    want = basis.project(phase)
    err = modal - want
    assert modal.dtype == np.float64 and modal.shape == want.shape
    assert np.sqrt(np.mean(err**2) / np.mean(want**2)) < RMS_REL
    assert np.all(np.abs(err).max(axis=0) <= MAX_REL * np.abs(want).max(axis=0))
    np.testing.assert_array_equal(phase, _atmosphere(pupil, 3).phase_vectors(200))


def test_turbulence_source_uses_its_own_project_for_other_bases(scene):
    # A basis-like object that is not a ModalBasis keeps its own projection, exactly.
    pupil, basis = scene

    class Doubled:
        n_modes = basis.n_modes
        modes = basis.modes
        pupil = basis.pupil

        def project(self, phase):
            return 2.0 * basis.project(phase)

        def synthesize(self, c):
            return basis.synthesize(c)

    modal, phase = TurbulenceSource(_atmosphere(pupil, 4), Doubled()).next(50)
    np.testing.assert_array_equal(modal, 2.0 * basis.project(phase))


def test_pupil_runs_fill_maps_like_to_map():
    # Oracle: Pupil.to_map (a scatter through pupil.index). The runs cover every valid pixel
    # once, in vector order, each inside one map row (the obstruction splits rows in two).
    pupil = vlt_pupil(24)
    v = np.random.default_rng(0).standard_normal((3, pupil.n_valid))
    maps = np.zeros((3, pupil.n_pix, pupil.n_pix))
    for row, first, stop, col in pupil.runs:
        assert col + stop - first <= pupil.n_pix
        maps[:, row, col : col + stop - first] = v[:, first:stop]
    np.testing.assert_array_equal(maps, pupil.to_map(v))
    assert sum(stop - first for _, first, stop, _ in pupil.runs) == pupil.n_valid
    assert len(pupil.runs) > pupil.n_pix - 4  # some rows hold two runs, a few none
