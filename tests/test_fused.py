"""The fused frame loop of a linear stage (aocontrol.sim._stage_run, aocontrol.sim._fused).

Oracle: the per-frame path (``_StageRun.step`` frame after frame, the controller's public
``step``), which the golden runs of tests/test_loop.py pin down. The numpy fused loop and
the compiled one must give the same arrays bit for bit, also when the energy guard trips
without a diverging mode (the loop goes on) and when a command is not finite (the
controller's error).
"""

from __future__ import annotations

import numpy as np
import pytest

from aocontrol._jit import ENV_NO_NUMBA
from aocontrol.controllers import IIRBank, Integrator
from aocontrol.sim import _fused, _stage_run
from aocontrol.sim.loop import LinearModalSensor, ModalTimeSeries, Stage, run_loop

FS = 3000.0
PATHS = ("per_frame", "numpy", "compiled")


def _run(path, monkeypatch, controller, *, latency, og=1.0, noise=0.5, n_frames=700, d=None):
    with monkeypatch.context() as mp:
        if path == "per_frame":
            mp.setattr(_stage_run._StageRun, "fusable", False, raising=False)
            orig = _stage_run._StageRun.__init__

            def init(self, *args, **kwargs):
                orig(self, *args, **kwargs)
                self.fusable = False

            mp.setattr(_stage_run._StageRun, "__init__", init)
        if path == "numpy":
            mp.setenv(ENV_NO_NUMBA, "1")
        else:
            mp.delenv(ENV_NO_NUMBA, raising=False)
        n = controller.n_modes
        if d is None:
            rng = np.random.default_rng(11)
            d = rng.standard_normal((n_frames, n)).cumsum(axis=0) / 20.0
        stage = Stage(controller, LinearModalSensor(og, noise), latency)
        return run_loop(stage, ModalTimeSeries(d, fs=FS), d.shape[0], rng=3, chunk=256)


def _assert_same(a, b):
    for name in a.telemetry:
        np.testing.assert_array_equal(a.telemetry[name], b.telemetry[name], err_msg=name)
    np.testing.assert_array_equal(a.residual_variance, b.residual_variance)
    np.testing.assert_array_equal(a.disturbance_variance, b.disturbance_variance)


@pytest.mark.parametrize(
    "make, latency, og",
    [
        (lambda: Integrator(np.linspace(0.2, 0.5, 6), fs=FS, leak=0.01), 0.83, 1.0),
        (lambda: Integrator(0.3, fs=FS, n_modes=5), 2.0, 0.7),  # integer latency, og != 1
        # A depth-3 IIR bank (rows summed one after the other), fractional latency > 1.
        (lambda: IIRBank([0.25, 0.05], [1.0, -0.9, -0.05], FS, n_modes=4), 1.4, 0.9),
    ],
)
def test_fused_loops_equal_the_per_frame_path(make, latency, og, monkeypatch):
    runs = {p: _run(p, monkeypatch, make(), latency=latency, og=og) for p in PATHS}
    assert _fused.kernel() is not None  # numba is a dependency: the compiled loop ran
    _assert_same(runs["numpy"], runs["per_frame"])
    _assert_same(runs["compiled"], runs["per_frame"])
    # The check can fail: another noise seed changes the arrays.
    other = _run("compiled", monkeypatch, make(), latency=latency, og=og, noise=0.5001)
    m_other, m_ref = other.telemetry["measurements"], runs["per_frame"].telemetry["measurements"]
    assert not np.array_equal(m_other, m_ref)


def test_fused_loops_go_on_when_the_energy_guard_trips(monkeypatch):
    # With the divergence factor at 2, the residual energy of 60 modes of equal size exceeds
    # limit^2 = (2 scale + 1)^2 in most frames while no mode exceeds the limit: the guard's
    # element-wise check runs and the loop goes on (the path of GUARD in the compiled loop).
    monkeypatch.setattr(_stage_run, "_DIVERGENCE_FACTOR", 2.0)
    calls = []
    orig = _stage_run._StageRun._diverged

    def counted(self, k, ae):
        calls.append(k)
        return orig(self, k, ae)

    monkeypatch.setattr(_stage_run._StageRun, "_diverged", counted)
    d = np.tile(np.sign(np.sin(np.arange(400) / 7.0))[:, None], (1, 60)) * 3.0
    runs = {}
    for p in PATHS:
        calls.clear()
        runs[p] = _run(p, monkeypatch, Integrator(0.05, fs=FS, n_modes=60), latency=0.5, d=d)
        runs[p, "calls"] = list(calls)
    assert len(runs["per_frame", "calls"]) > 50
    for p in ("numpy", "compiled"):
        _assert_same(runs[p], runs["per_frame"])
        assert runs[p, "calls"] == runs["per_frame", "calls"]


@pytest.mark.parametrize("path", PATHS)
def test_fused_loops_report_a_non_finite_command(path, monkeypatch):
    # b = 1e308: the first measurement above ~1.8 makes the command inf; the controller's
    # FloatingPointError, whatever the path.
    # (numpy's overflow warnings silenced: the error is what is tested.)
    bank = IIRBank([1e308], [1.0, -1.0], FS, n_modes=3)
    with np.errstate(all="ignore"), pytest.raises(FloatingPointError, match="not finite for"):
        _run(path, monkeypatch, bank, latency=0.0, noise=5.0)


def test_linear_stages_take_the_fused_loop():
    # The comparisons above are meaningful only if the fused loop runs for a linear stage
    # (and not for a controller with a command limit, which keeps the per-frame path).
    def fusable(controller):
        stage = Stage(controller, LinearModalSensor(1.0, 0.5), 0.5)
        run = _stage_run._StageRun(
            stage, n_frames=10, record=(), settle=0, rng=np.random.default_rng(0)
        )
        return run.fusable

    assert fusable(Integrator(0.3, fs=FS, n_modes=3))
    assert not fusable(Integrator(0.3, fs=FS, n_modes=3, command_limit=1.0))
