"""Cascade replay: stage 2 run on a recorded upstream (disturbance, projection, stage 1).

Oracle: two paths that must agree bit for bit. A replayed run and a full run of the same
disturbance, stage 1 and noise seed with another stage-2 controller (and the other scheme)
give equal telemetry, variances and science images; the twin checks show that a different
stage 2 or seed changes them (so the equality is not vacuous).
"""

import numpy as np
import pytest
import test_cascade

from aocontrol.controllers import Integrator
from aocontrol.sim import LinearModalSensor, Stage, run_cascade
from aocontrol.sim.loop import UpstreamRecord
from aocontrol.sim.science import ScienceCamera

FS2, RATIO, N_FRAMES = 3000.0, 3, 900
bases = test_cascade.bases  # the cascade tests' fixture: two small KL bases


class _Phase:
    """Random modal phase plus a part outside both bases, the same for every instance of a
    seed (a fresh source per run, as the study builds one)."""

    def __init__(self, basis, seed):
        self.fs = FS2
        rng = np.random.default_rng(seed)
        c = rng.standard_normal((N_FRAMES, basis.n_modes)) * 50.0
        self.phase = c @ basis.modes + 3.0 * rng.standard_normal((N_FRAMES, basis.modes.shape[1]))
        self._pos = 0

    def phase_vectors(self, n):
        out = self.phase[self._pos : self._pos + n]
        self._pos += n
        return out


def _run(bases, gain2, scheme, *, upstream=None, seed=7, source_seed=3, science=True):
    b1, b2 = bases
    s1 = Stage(
        Integrator(0.4, fs=FS2 / RATIO, n_modes=b1.n_modes),
        LinearModalSensor(1.0, 2.0),
        0.84,
        name="stage 1",
    )
    s2 = Stage(
        Integrator(gain2, fs=FS2, n_modes=b2.n_modes),
        LinearModalSensor(1.0, 1.0),
        0.83,
        name="stage 2",
    )
    cam = ScienceCamera(b1.pupil, field_of_view=8.0).long_exposure() if science else None
    return run_cascade(
        s1,
        s2,
        _Phase(b1, source_seed),
        N_FRAMES,
        scheme=scheme,
        basis1=b1,
        basis2=b2,
        rng=seed,
        science=cam,
        science_every=7,
        chunk=240,
        metadata={"gain2": gain2},
        upstream=upstream,
    )


def _assert_identical(a, b):
    for i in range(2):
        sa, sb = a.stages[i], b.stages[i]
        assert sa.telemetry.keys() == sb.telemetry.keys()
        for k in sa.telemetry:
            np.testing.assert_array_equal(sa.telemetry[k], sb.telemetry[k])
        np.testing.assert_array_equal(sa.residual_variance, sb.residual_variance)
        np.testing.assert_array_equal(sa.disturbance_variance, sb.disturbance_variance)
        assert sa.metadata == sb.metadata
    np.testing.assert_array_equal(a.science.contrast_profile, b.science.contrast_profile)
    assert a.science.strehl == b.science.strehl
    assert a.science.mean_contrast_4_6 == b.science.mean_contrast_4_6


def test_replay_equals_a_full_run_bit_for_bit(bases):
    rec = UpstreamRecord()
    recorded = _run(bases, 0.5, "standalone", upstream=rec)
    assert rec.filled
    # The recording run itself is a full run.
    _assert_identical(recorded, _run(bases, 0.5, "standalone"))
    for gain2, scheme in ((0.3, "standalone"), (0.6, "dcao"), (0.5, "standalone")):
        replayed = _run(bases, gain2, scheme, upstream=rec)
        full = _run(bases, gain2, scheme)
        _assert_identical(replayed, full)
    # Twins: another stage 2 (or noise seed) changes stage 2's figures, so the equalities
    # above can fail.
    other = _run(bases, 0.3, "standalone", upstream=rec)
    assert not np.array_equal(
        other.stages[1].telemetry["residuals"], recorded.stages[1].telemetry["residuals"]
    )
    assert not np.array_equal(
        _run(bases, 0.5, "standalone", seed=8).stages[0].telemetry["measurements"],
        recorded.stages[0].telemetry["measurements"],
    )


def test_record_refuses_a_different_setup(bases):
    rec = UpstreamRecord()
    _run(bases, 0.5, "dcao", upstream=rec)
    b1, b2 = bases
    s1 = Stage(Integrator(0.4, fs=FS2 / RATIO, n_modes=b1.n_modes), LinearModalSensor(1, 0), 0.84)
    s2 = Stage(Integrator(0.5, fs=FS2, n_modes=b2.n_modes), LinearModalSensor(1, 0), 0.83)
    kw = dict(scheme="dcao", basis1=b1, basis2=b2, rng=7, science_every=7, chunk=240)
    with pytest.raises(ValueError, match="n_frames"):
        run_cascade(s1, s2, _Phase(b1, 3), N_FRAMES - 3 * 10, upstream=rec, **kw)
    with pytest.raises(ValueError, match="science"):
        run_cascade(s1, s2, _Phase(b1, 3), N_FRAMES, upstream=rec, **kw)


class _MapReader:
    """A sensor that asks for the residual phase map each frame (like a diffractive one) and
    measures the modal residual."""

    n_modes = None

    def check(self, n_modes, basis=None):
        pass

    def start(self, n_modes, rng, pupil=None):
        inner = LinearModalSensor(1.0, 0.0).start(n_modes, rng, pupil)

        class _Run:
            optical_gain, noise_std, needs_phase = inner.optical_gain, inner.noise_std, True

            def begin_chunk(self, m):
                inner.begin_chunk(m)

            def read(self, j, residual, opd):
                opd()
                return inner.read(j, residual, opd)

        return _Run()


def test_record_refuses_a_stage_2_that_reads_phase_maps(bases):
    rec = UpstreamRecord()
    _run(bases, 0.5, "standalone", upstream=rec, science=False)
    b1, b2 = bases
    s1 = Stage(Integrator(0.4, fs=FS2 / RATIO, n_modes=b1.n_modes), LinearModalSensor(1, 2), 0.84)
    s2 = Stage(Integrator(0.5, fs=FS2, n_modes=b2.n_modes), _MapReader(), 0.83)
    kw = dict(scheme="standalone", basis1=b1, basis2=b2, rng=7, science_every=7, chunk=240)
    # A full run reads the maps; a replay refuses (the record keeps no phase).
    run_cascade(s1, s2, _Phase(b1, 3), N_FRAMES, **kw)
    with pytest.raises(ValueError, match="phase maps"):
        run_cascade(s1, s2, _Phase(b1, 3), N_FRAMES, upstream=rec, **kw)
