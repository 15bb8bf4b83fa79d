"""Benchmark of the MPC (aocontrol.controllers.MPCBank). A script, not a test.

    python benchmarks/bench_mpc.py [--quick]

(a) Stroke-limited tip/tilt, SAXO+ stage 2 timing (fs = 3000 Hz, latency 0.83 frame):
    AR(2) turbulence on tip and tilt plus a 40 Hz vibration on tilt, white measurement
    noise; the DM stroke is set to a multiple of the disturbance RMS so that the limit is
    active. Closed-loop runs (aocontrol.sim.run_loop) of the MPC (one QP for tip and tilt,
    horizon 10), the LQG whose commands are simply clipped by the DM, the LQG that clips its
    own command and feeds it to its predictor (LQGBank command_limit), and integrators clipped
    with anti-windup (best of 0.4, 0.6, 0.8 times the stability limit). Residual variance
    over the run, the fraction of frames at the limit, and the floor no controller within the
    stroke can beat: the mean of (|d| - stroke)_+^2 (the residual when the DM sits at the
    limit).
(b) Real-time cost per frame: MPC for tip/tilt (QP every frame, and with the shortcut that
    skips the QP when the unconstrained optimum meets the limits), and for 540 modes (one
    QP per mode), against the LQG bank's step in the same run. The real-time solver (DAQP,
    warm-started) and the casadi reference (qpOASES) on the same measurements: median,
    99th percentile and worst step, the frames over the 333 us budget of 3 kHz, and the
    largest difference of their commands.

Timings are wall-clock on a shared machine: compare the ratios measured in one run.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from aocontrol.controllers import Integrator, LQGBank, MPCBank
from aocontrol.plant import loop_plant
from aocontrol.sim import LinearModalSensor, ModalDM, ModalTimeSeries, Stage, run_loop
from aocontrol.synthesis import DisturbanceModel, integrator_gain_limit, lqg_state_space

FS = 3000.0
LATENCY = 0.83
NOISE_STD = 2.0  # nm per frame
HORIZON = 10
SETTLE = 100  # frames left out of the statistics (the loop converging)


def tip_tilt_model() -> DisturbanceModel:
    """Tip/tilt turbulence (AR(2), double pole 0.995) and a 40 Hz vibration on tilt."""
    a = 0.995
    return DisturbanceModel(
        [[2 * a, -(a**2)], [2 * a, -(a**2)]],
        [400.0**2, 300.0**2],
        [[40.0], [40.0]],
        [[0.01], [0.01]],
        [[0.0], [80.0**2]],
        fs=FS,
    )


def run(controller, series: np.ndarray, stroke) -> tuple[np.ndarray, np.ndarray]:
    """Residual variance per mode and the commands of one closed-loop run."""
    stage = Stage(
        controller,
        sensor=LinearModalSensor(noise_std=NOISE_STD),
        latency_frames=LATENCY,
        dm=ModalDM(controller.n_modes, modal_stroke=stroke),
    )
    res = run_loop(
        stage,
        ModalTimeSeries(series, fs=FS),
        series.shape[0],
        rng=11,
        record=("commands",),
        settle_frames=SETTLE,
    )
    return res.residual_variance, np.asarray(res.telemetry["commands"], dtype=float)


BUDGET = 1 / FS  # [s] one frame at 3 kHz


def time_steps(bank, measurements: np.ndarray) -> float:
    """Mean wall time of ``bank.step`` per frame [s]."""
    bank.reset()
    t0 = time.perf_counter()
    for m in measurements:
        bank.step(m)
    return (time.perf_counter() - t0) / measurements.shape[0]


def frame_times(bank, measurements: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wall and thread-CPU time of each ``bank.step`` [s], and the commands.

    On a shared machine the wall time of a frame includes the time the process was not
    scheduled; the thread CPU time is what the step itself cost.
    """
    bank.reset()
    wall = np.empty(measurements.shape[0])
    cpu = np.empty(measurements.shape[0])
    commands = np.empty(measurements.shape)
    clock, cpu_clock = time.perf_counter, time.thread_time
    for k, m in enumerate(measurements):
        t0, c0 = clock(), cpu_clock()
        commands[k] = bank.step(m)
        cpu[k] = cpu_clock() - c0
        wall[k] = clock() - t0
    return wall, cpu, commands


def describe(times: tuple[np.ndarray, np.ndarray, np.ndarray]) -> str:
    """Median, p99 and worst of the CPU time [us], the frames over budget (CPU, wall)."""
    wall, cpu = times[0], times[1]
    return (
        f"CPU median {np.median(cpu) * 1e6:6.1f} p99 {np.percentile(cpu, 99) * 1e6:6.1f} "
        f"worst {cpu.max() * 1e6:7.1f}; over {BUDGET * 1e6:.0f} us: CPU {np.sum(cpu > BUDGET)}, "
        f"wall {np.sum(wall > BUDGET)} of {cpu.size}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter runs")
    args = parser.parse_args()
    n_frames = 3000 if args.quick else 9000
    model = tip_tilt_model()
    series = model.simulate(n_frames, np.random.default_rng(7))
    rms = series.std(axis=0)
    ss = lqg_state_space(model, latency_frames=LATENCY, noise_variance=NOISE_STD**2)
    print(
        f"tip/tilt at fs = {FS:g} Hz, latency {LATENCY} frame, {n_frames} frames, "
        f"disturbance RMS {np.round(rms, 1).tolist()} nm, noise {NOISE_STD} nm/frame"
    )

    print("\n(a) stroke-limited tip/tilt: residual variance (sum tip+tilt) [nm^2]")
    free, _ = run(LQGBank(ss), series, None)
    g_max = integrator_gain_limit(loop_plant(FS, LATENCY))
    print(f"  LQG, no stroke limit: {free.sum():10.1f}")
    header = (
        "  stroke/RMS   MPC        LQG clipped   integrator clipped (gain)   at limit (MPC)   floor"
    )
    print(header)
    for factor in (2.0, 1.5, 1.0):
        stroke = factor * rms
        v_mpc, u_mpc = run(
            MPCBank(ss, HORIZON, command_limit=stroke, groups=[[0, 1]]), series, None
        )
        v_lqg, _ = run(LQGBank(ss), series, stroke)
        # LQG that clips its own command and feeds the clipped one to its predictor.
        v_lqg_aw, _ = run(LQGBank(ss, command_limit=stroke), series, stroke)
        ints = {
            g: run(Integrator(g, fs=FS, n_modes=2, command_limit=stroke), series, stroke)[0].sum()
            for g in np.round(np.array([0.4, 0.6, 0.8]) * g_max, 3)
        }
        g_best = min(ints, key=ints.get)
        at_limit = np.mean(np.abs(u_mpc[SETTLE:]) >= stroke * (1 - 1e-6))
        # Floor: no command within the stroke does better than (|d| - stroke)_+ per frame.
        # (Over the frames of the statistics.)
        excess = np.maximum(np.abs(series[SETTLE:]) - stroke, 0.0)
        floor = np.sum(np.mean(excess**2, axis=0))
        print(
            f"  {factor:7.1f}   {v_mpc.sum():10.1f}  {v_lqg.sum():12.1f}  {ints[g_best]:12.1f} "
            f"({g_best})        {at_limit:6.1%}      {floor:9.1f}"
        )
        print(
            f"             ratios: MPC / clipped LQG {v_mpc.sum() / v_lqg.sum():.3f}, "
            f"MPC / LQG clipping its own command {v_mpc.sum() / v_lqg_aw.sum():.4f}, "
            f"MPC / clipped integrator {v_mpc.sum() / ints[g_best]:.4f}, "
            f"MPC / floor {v_mpc.sum() / floor:.4f}"
        )

    print("\n(b) real-time cost per frame (2-core shared machine) [us]")
    rng = np.random.default_rng(0)
    m2 = rng.standard_normal((400 if args.quick else 2000, 2)) * rms
    stroke = 1.0 * rms
    lqg_times = frame_times(LQGBank(ss), m2)
    every = {"groups": [[0, 1]], "skip_inactive": False}
    qp_times = frame_times(MPCBank(ss, HORIZON, command_limit=stroke, **every), m2)
    ref_times = frame_times(
        MPCBank(ss, HORIZON, command_limit=stroke, solver="qpoases", **every), m2
    )
    # Limits inactive: measurements at the noise level (a converged loop), stroke 10 RMS.
    m_small = rng.standard_normal(m2.shape) * NOISE_STD
    short_times = frame_times(
        MPCBank(ss, HORIZON, command_limit=10 * rms, groups=[[0, 1]]), m_small
    )
    t_lqg, t_qp, t_ref = (float(np.median(t[1])) for t in (lqg_times, qp_times, ref_times))
    print(
        f"  (times per frame; wall counts include the time the process was not scheduled on "
        f"the loaded machine)\n  tip/tilt LQG step           {describe(lqg_times)}"
    )
    print(f"  tip/tilt MPC, QP every frame (N={HORIZON}), stroke 1 RMS, {m2.shape[0]} frames:")
    print(f"    DAQP (real time)          {describe(qp_times)}")
    print(f"    casadi qpOASES (ref.)     {describe(ref_times)}")
    diff = np.abs(qp_times[2] - ref_times[2]).max() / stroke.min()
    print(
        f"    median CPU: DAQP / qpOASES {t_qp / t_ref:.3f}, DAQP / LQG {t_qp / t_lqg:.1f}; "
        f"largest command difference {diff:.1e} x stroke"
    )
    print(f"  tip/tilt MPC, limits inactive (shortcut) {describe(short_times)}")

    n_modes = 540
    a = np.linspace(0.995, 0.9, n_modes)
    big = DisturbanceModel(
        np.column_stack([2 * a, -(a**2)]),
        np.full(n_modes, 100.0),
        np.zeros((n_modes, 0)),
        np.zeros((n_modes, 0)),
        np.zeros((n_modes, 0)),
        fs=FS,
    )
    ss_big = lqg_state_space(big, latency_frames=LATENCY, noise_variance=NOISE_STD**2)
    m_big = rng.standard_normal((20 if args.quick else 60, n_modes)) * 50.0
    t0 = time.perf_counter()
    mpc_big = MPCBank(ss_big, HORIZON, command_limit=1.0, skip_inactive=False)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    ref_big = MPCBank(ss_big, HORIZON, command_limit=1.0, skip_inactive=False, solver="qpoases")
    t_build_ref = time.perf_counter() - t0
    t_big_lqg = time_steps(LQGBank(ss_big), m_big)
    t_big = time_steps(mpc_big, m_big)
    t_big_ref = time_steps(ref_big, m_big)
    mpc_free = MPCBank(ss_big, HORIZON, command_limit=1e9)
    t_big_short = time_steps(mpc_free, m_big)
    assert mpc_free.n_solves.sum() == 0  # the shortcut was taken on every frame
    print(f"  540 modes: building 540 QPs [s]   DAQP {t_build:5.2f}, qpOASES {t_build_ref:5.1f}")
    print(f"  540 modes LQG step                         {t_big_lqg * 1e6:9.1f}")
    for name, t in (("DAQP", t_big), ("qpOASES", t_big_ref)):
        print(
            f"  540 modes MPC, one QP per mode every frame, {name:<8} {t * 1e6:9.0f}   "
            f"({t / t_big_lqg:.0f}x LQG, {t / n_modes * 1e6:.0f} us per mode QP)"
        )
    print(
        f"  540 modes MPC, limits inactive (shortcut)  {t_big_short * 1e6:9.1f}   "
        f"({t_big_short / t_big_lqg:.1f}x LQG)"
    )


if __name__ == "__main__":
    main()
