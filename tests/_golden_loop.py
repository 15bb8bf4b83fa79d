"""Golden loop runs: the configurations and the script that records their arrays.

The arrays in ``tests/data/golden_loop.npz`` were recorded from the loop engine as it was
before the one-driver refactoring (issue 15; the code that the removed
``tests/_legacy_loop.py`` had been checked against bit for bit). ``tests/test_loop.py`` and
``tests/test_cascade.py`` run the same configurations with today's engine and compare:
the linear single-stage runs (a modal disturbance, no product whose rounding can change)
bit for bit; the runs that project phase screens on modes (science, diffractive, cascades)
to :data:`GOLDEN_RTOL` (see there why), with their integer counts exact.

The runs on KL bases (science, diffractive, both cascades) were re-recorded with today's
engine when :func:`aocontrol.sim.modes.kl_basis` got its canonical orientation of degenerate
modes and signs (issue 19: the modes had depended on the BLAS threads): the same engine that
matched the legacy arrays to ``GOLDEN_RTOL``, on the canonical modes (per-mode telemetry
changed by the orientation, the Strehl ratios by at most 5e-4 relative); the linear runs
(no basis) are the legacy arrays, unchanged bit for bit. The diffractive run was recorded
with the pyramid's former FFT propagation (``tests/_pyramid_reference.FFTPyramid``), as
its test runs it.

Regenerate (only when a change of the loop's numbers is intended, and say so in the commit)::

    PYTHONPATH=. python tests/_golden_loop.py

Each configuration is a function returning ``{name: array}``; keys are prefixed with the
configuration's name in the file.
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np

from aocontrol.controllers import Integrator
from aocontrol.sim.atmosphere import Atmosphere, Layer
from aocontrol.sim.dm import DeformableMirror, ModalDM
from aocontrol.sim.loop import (
    LinearModalSensor,
    ModalTimeSeries,
    Stage,
    TurbulenceSource,
    run_cascade,
    run_loop,
)
from aocontrol.sim.modes import kl_basis
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.sim.science import ScienceCamera

PATH = pathlib.Path(__file__).with_name("data") / "golden_loop.npz"
FS = 3000.0

#: Single-stage linear configurations (those of the former bit-identity test, shorter).
LINEAR = {
    "lin_a": dict(latency=0.83, noise=1.5),
    "lin_b": dict(latency=1.5, noise=0.0, stroke=0.8),
    "lin_c": dict(latency=0.0, noise=0.5, dm_stroke=True),
    "lin_d": dict(latency=2.0, noise=0.3, og=0.7, chunk=333),
}
_STAT = ("residual_variance", "disturbance_variance", "saturation", "actuator_saturation")


#: Tolerance of the runs that project phase screens on modes: each array's largest
#: difference to its golden, relative to the golden's largest magnitude. Two things round
#: differently from the recording: (1) the projection is float32 (issue 19;
#: aocontrol.sim._projection: relative rounding ~6e-7 RMS, ~2e-4 of a mode's largest
#: coefficient at worst), the golden single-stage runs were recorded with the float64
#: product; (2) the BLAS thread count changes the rounding of the float32 and float64
#: products (the engine runs with aocontrol.sim._runner.engine_blas_threads(), 1 by default;
#: the goldens were recorded with 2). Measured: at most 4e-6 (the science run's residual
#: variance; telemetry <= 1.5e-6), against 1 for any change of the noise or the dynamics.
GOLDEN_RTOL = 2e-5


def assert_close_to_golden(got: dict, gold: dict, rtol: float = GOLDEN_RTOL) -> None:
    """Every array of ``gold`` matched in ``got`` (same keys): integer arrays exactly, float
    arrays to ``rtol`` of their largest magnitude (:data:`GOLDEN_RTOL`)."""
    assert gold, "no golden arrays for this configuration"
    for name, want in gold.items():
        have = np.asarray(got[name])
        assert have.shape == want.shape, name
        if np.issubdtype(want.dtype, np.integer):
            np.testing.assert_array_equal(have, want, err_msg=name)
            continue
        scale = float(np.max(np.abs(want))) if want.size else 0.0
        np.testing.assert_allclose(have, want, rtol=0, atol=rtol * scale, err_msg=name)


def _loop_arrays(res, prefix="", telemetry=("measurements", "commands", "dm", "residuals")):
    out = {prefix + k: np.asarray(res.telemetry[k]) for k in telemetry}
    for k in _STAT:
        value = getattr(res, k)
        if value is not None:
            out[prefix + k] = np.asarray(value)
    return out


def linear_run(config: dict):
    """Run one of :data:`LINEAR` (returns the LoopResult)."""
    n_frames, n_modes = 500, 4
    rng = np.random.default_rng(3)
    d = 2.0 * rng.standard_normal((n_frames, n_modes)).cumsum(axis=0) / 30.0
    m2c = rng.standard_normal((9, n_modes)) if config.get("dm_stroke") else None
    dm = ModalDM(
        n_modes,
        modal_stroke=config.get("stroke"),
        actuator_stroke=1.2 if m2c is not None else None,
        m2c=m2c,
    )
    kw = dict(latency_frames=config["latency"], dm=dm)
    gains = np.linspace(0.2, 0.6, n_modes)
    sensor = LinearModalSensor(config.get("og", 1.0), config["noise"])
    return run_loop(
        Stage(Integrator(gains, fs=FS), sensor, **kw),
        ModalTimeSeries(d, fs=FS),
        n_frames,
        rng=7,
        chunk=config.get("chunk", 1000),
    )


def science_run():
    """A linear loop on turbulence with a science camera (LoopResult)."""
    pupil = vlt_pupil(24)
    basis = kl_basis(DeformableMirror(pupil, n_actuators=9), 20, r0=0.15)
    cam = ScienceCamera(pupil, field_of_view=6.0)
    atm = Atmosphere(pupil, 0.15, [Layer(0.0, 1.0, 10.0, 30.0)], FS, rng=4)
    return run_loop(
        Stage(Integrator(0.4, fs=FS, n_modes=20), LinearModalSensor(1.0, 2.0), 0.83),
        TurbulenceSource(atm, basis),
        300,
        science=cam.long_exposure(),
        rng=1,
        basis=basis,
        science_every=7,
        chunk=250,
    )


def diffractive_parts():
    """Pupil, basis, pyramid and its calibration of the diffractive golden run."""
    from aocontrol.sim.wfs import PyramidWFS, calibrate

    pupil = vlt_pupil(16)
    basis = kl_basis(DeformableMirror(pupil, n_actuators=9), 6, r0=0.15)
    pyramid = PyramidWFS(pupil, 1.04e-6, n_subapertures=8, modulation=2.0)
    return pupil, basis, pyramid, calibrate(pyramid, basis, amplitude=2.0)


def diffractive_run(sensor_factory):
    """A noisy diffractive pyramid loop on turbulence (LoopResult).

    ``sensor_factory(pyramid, recon, photons, read_noise)`` builds the sensor (the class
    changed names over time).
    """
    pupil, basis, pyramid, cal = diffractive_parts()
    atm = Atmosphere(pupil, 0.3, [Layer(0.0, 1.0, 5.0, 30.0)], FS, rng=5)
    sensor = sensor_factory(pyramid, cal.recon, 3000.0, 0.3)
    return run_loop(
        Stage(Integrator(0.4, fs=FS, n_modes=basis.n_modes), sensor, 0.83),
        TurbulenceSource(atm, basis),
        120,
        rng=2,
        basis=basis,
        chunk=50,
        settle_frames=10,
    )


def cascade_parts():
    """Bases and a phase source factory of the cascade golden runs."""
    pupil = vlt_pupil(24)
    b1 = kl_basis(DeformableMirror(pupil, n_actuators=11), 24, r0=0.15)
    b2 = kl_basis(DeformableMirror(pupil, n_actuators=8), 10, r0=0.15)
    return pupil, b1, b2


def cascade_run(scheme: str):
    """A noisy two-stage cascade (rate ratio 3) on turbulence with stroke (CascadeResult)."""
    pupil, b1, b2 = cascade_parts()
    atm = Atmosphere(pupil, 0.15, [Layer(0.0, 1.0, 10.0, 30.0)], FS, rng=6)
    s1 = Stage(
        Integrator(np.linspace(0.3, 0.4, b1.n_modes), fs=1000.0),
        LinearModalSensor(1.0, 1.0),
        0.84,
        name="SAXO",
    )
    s2 = Stage(
        Integrator(np.linspace(0.35, 0.5, b2.n_modes), fs=FS),
        LinearModalSensor(np.linspace(0.8, 1.0, b2.n_modes), 0.5),
        0.83,
        dm=ModalDM(b2.n_modes, modal_stroke=40.0),
        name="SAXO+",
    )
    cam = ScienceCamera(pupil, field_of_view=6.0)
    return run_cascade(
        s1,
        s2,
        atm,
        300,
        scheme=scheme,
        basis1=b1,
        basis2=b2,
        rng=9,
        science=cam.long_exposure(),
        science_every=5,
        chunk=120,
    )


def _science_arrays(sci, prefix):
    return {
        prefix + "strehl": np.asarray(sci.strehl),
        prefix + "contrast_profile": np.asarray(sci.contrast_profile),
    }


def record(sensor_factory) -> dict[str, np.ndarray]:
    """Every golden array, keyed ``<config>/<name>``."""
    out = {}
    for name, config in LINEAR.items():
        out.update(_loop_arrays(linear_run(config), f"{name}/"))
    res = science_run()
    out.update(_loop_arrays(res, "science/", ("measurements", "residuals")))
    out.update(_science_arrays(res.science, "science/"))
    out.update(_loop_arrays(diffractive_run(sensor_factory), "diffractive/"))
    for scheme in ("standalone", "dcao"):
        res = cascade_run(scheme)
        for i, st in enumerate(res.stages):
            out.update(_loop_arrays(st, f"{scheme}{i + 1}/", ("measurements", "residuals")))
        out.update(_science_arrays(res.science, f"{scheme}/"))
    return out


def main() -> None:
    from aocontrol.sim.loop import DiffractiveSensor

    def factory(wfs, recon, photons, read_noise):
        return DiffractiveSensor(wfs, recon, photons=photons, read_noise=read_noise)

    arrays = record(factory)
    PATH.parent.mkdir(exist_ok=True)
    np.savez_compressed(PATH, **arrays)
    size = PATH.stat().st_size
    sys.stdout.write(f"wrote {PATH} ({len(arrays)} arrays, {size / 1024:.0f} KiB)\n")


if __name__ == "__main__":
    main()
