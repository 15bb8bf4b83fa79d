"""Tests of the adaptive multi-mode predictor (aocontrol.adaptive.AdaptivePredictor).

Oracles: after a switch the loop's commands are the trained predictor's FIR on the
pseudo-open loop rebuilt from the recorded measurements and applied commands, written here in
plain numpy (the switch is bumpless: the predictor's state is the loop's own past); a
predictor that cannot be certified never reaches the loop (the run equals the initial
controller's bit for bit); when the coupling of the modes changes half-way, retraining beats
the predictor trained once; the schedule follows period, window and latency.
"""

from __future__ import annotations

import control
import numpy as np
import pytest

from aocontrol import loop_plant
from aocontrol.adaptive import AdaptivePredictor
from aocontrol.controllers import Integrator, MultiModeBank
from aocontrol.plant import split_latency
from aocontrol.sim import LinearModalSensor, ModalTimeSeries, Stage, run_loop

FS = 1000.0
N = 4


def _coupled(n_frames: int, seed: int = 0, change: bool = False) -> np.ndarray:
    """A VAR(1) of 4 modes, x[t+1] = A x[t] + w, whose coupling rotates half-way when
    ``change`` (the wind turns: another mode predicts each mode)."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((N, N)))
    a1 = 0.97 * q
    a2 = 0.97 * q.T if change else a1
    x = np.zeros((n_frames, N))
    w = rng.standard_normal((n_frames, N))
    for t in range(1, n_frames):
        a = a1 if t < n_frames // 2 else a2
        x[t] = a @ x[t - 1] + w[t]
    return 10.0 * x


def _run(ctrl, d, latency, sigma=0.3, seed=1):
    stage = Stage(ctrl, LinearModalSensor(1.0, sigma), latency)
    return run_loop(
        stage, ModalTimeSeries(d, FS), d.shape[0], rng=seed, record=("measurements", "commands")
    )


def _predictor(latency, **kw):
    kw = {"period": 1.0, "window": 1.0, "latency": 0.01, "history": 3, **kw}
    return AdaptivePredictor(Integrator(0.4, fs=FS, n_modes=N), loop_plant(FS, latency), **kw)


@pytest.mark.parametrize("latency", [1.0, 0.83])
def test_after_the_switch_the_loop_runs_the_trained_fir_on_its_own_past(latency):
    d = _coupled(2500)
    ctrl = _predictor(latency, max_designs=1, precision="float64")
    res = _run(ctrl, d, latency)
    run = ctrl.last_run
    assert run.switch_frames == [1000 + 10]
    bank = run.final
    assert isinstance(bank, MultiModeBank)
    m = np.asarray(res.telemetry["measurements"], dtype=float)
    u = np.asarray(res.telemetry["commands"], dtype=float)
    # Plain numpy: p[t] = m[t] + (1 - f) u[t-1-k0] + f u[t-2-k0], u[k] = sum_j A_j p[k-j].
    k0, f = split_latency(latency)
    p = m.copy()
    p[k0 + 1 :] += (1 - f) * u[: -(k0 + 1)]
    p[k0 + 2 :] += f * u[: -(k0 + 2)]
    taps = bank.taps
    for k in range(1010, 1200):
        expect = sum(taps[j] @ p[k - j] for j in range(taps.shape[0]))
        # The record is kept in float32: equal to its rounding.
        np.testing.assert_allclose(u[k], expect, rtol=0, atol=1e-5 * np.abs(u).max())
    # Before the switch: the integrator's commands.
    np.testing.assert_allclose(
        u[1009], u[1008] + 0.4 * m[1009], rtol=0, atol=1e-5 * np.abs(u).max()
    )
    r = run.redesigns[0]
    assert r.certified.all() and r.modulus_margin[0] >= 0.5 and r.regularisation is not None


def test_a_predictor_that_cannot_be_certified_never_runs():
    # Persistence (history 1 with integral action) at an integer latency has margin exactly
    # 1/2 (module docstring of aocontrol.synthesis._eof): a requirement of 0.6 fails.
    d = _coupled(2500)
    ctrl = _predictor(1.0, history=1, modulus_margin=0.6)
    res = _run(ctrl, d, 1.0)
    ref = _run(Integrator(0.4, fs=FS, n_modes=N), d, 1.0)
    np.testing.assert_array_equal(res.telemetry["commands"], ref.telemetry["commands"])
    run = ctrl.last_run
    assert run.n_switches == 0 and run.n_rejected_banks == 2
    assert all(not r.certified.any() and "not certified" in r.reasons[0] for r in run.redesigns)


def test_retraining_follows_a_change_of_the_modes_coupling():
    d = _coupled(8000, change=True)
    fixed = _predictor(0.83, period=1.0, window=1.0, max_designs=1)
    adaptive = _predictor(0.83, period=1.0, window=1.0)
    second_half = slice(5000, 8000)
    r_fixed = _run(fixed, d, 0.83).telemetry
    r_adapt = _run(adaptive, d, 0.83).telemetry
    run = adaptive.last_run
    assert run.switch_frames == [1010 + 1000 * j for j in range(7)]
    assert all(r.certified.all() for r in run.redesigns)

    def resid(tel):
        return float(np.mean(np.asarray(tel["measurements"])[second_half] ** 2))

    # The fixed predictor still predicts with the first half's coupling.
    assert resid(r_adapt) < 0.7 * resid(r_fixed)


def test_the_oracle_trains_on_the_record_it_is_given():
    d = _coupled(2500)
    calls = []

    def oracle(frame):
        calls.append(frame)
        return d[frame - 1000 : frame]

    ctrl = _predictor(0.83, max_designs=1, oracle=oracle)
    _run(ctrl, d, 0.83)
    assert calls == [1000] and ctrl.last_run.n_switches == 1


def test_bad_input_is_refused_with_the_argument_named():
    plant = loop_plant(FS, 0.83)
    init = Integrator(0.4, fs=FS, n_modes=N)
    with pytest.raises(ValueError, match=r"window must hold at least \d+ frames"):
        AdaptivePredictor(init, plant, period=1.0, window=0.01, history=5)
    with pytest.raises(ValueError, match="history"):
        AdaptivePredictor(init, plant, period=1.0, window=1.0, history=0)
    with pytest.raises(ValueError, match="modulus_margin"):
        AdaptivePredictor(init, plant, period=1.0, window=1.0, modulus_margin=1.0)
    with pytest.raises(ValueError, match="regularisation"):
        AdaptivePredictor(init, plant, period=1.0, window=1.0, regularisation=-1.0)
    with pytest.raises(TypeError, match="oracle"):
        AdaptivePredictor(init, plant, period=1.0, window=1.0, oracle=3)
    with pytest.raises(TypeError, match="initial"):
        AdaptivePredictor("integrator", plant, period=1.0, window=1.0)
    with pytest.raises(ValueError, match="latency must be shorter"):
        AdaptivePredictor(init, plant, period=1.0, window=1.0, latency=2.0)
    lagged = plant * control.tf([0.5, 0.0], [1.0, -0.5], 1 / FS)  # a DM's lag: no pure delay
    with pytest.raises(ValueError):
        AdaptivePredictor(init, lagged, period=1.0, window=1.0)
