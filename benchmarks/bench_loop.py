"""Benchmark: fast single-stage loop, 540 modes at 3 kHz, a 5-s exposure with Strehl and contrast.

Goal (issue 4): the whole 5-s exposure (15,000 frames) with contrast and Strehl in <= 30 s
on a 2-core machine. Calibration (DM, KL modes) is timed separately.

Prints the time of each part measured in one run, frames/s, the ratio of the run time to the
30-s goal, and the speed-up of the vectorised loop over a per-mode Python loop (the naive
reference, measured on a few hundred frames in the same run).

Usage: python benchmarks/bench_loop.py [--frames 15000] [--modes 540] [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from aocontrol.controllers import Integrator
from aocontrol.sim.atmosphere import Atmosphere
from aocontrol.sim.dm import SAXO_PLUS_N_ACTUATORS, DeformableMirror
from aocontrol.sim.loop import LinearModalSensor, Stage, TurbulenceSource, run_loop
from aocontrol.sim.modes import kl_basis
from aocontrol.sim.profiles import eso_median_profile, scale_to_tau0
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.sim.science import ScienceCamera
from aocontrol.sim.turbulence import r0_from_seeing

GOAL_SECONDS = 30.0


def _naive_loop(ctrl_gain: np.ndarray, d: np.ndarray, latency: float) -> np.ndarray:
    """Reference: the same integrator loop with a Python loop per mode per frame."""
    n_frames, n_modes = d.shape
    k0 = int(np.floor(latency))
    f = latency - k0
    u = np.zeros((n_frames + k0 + 2, n_modes))
    e = np.zeros((n_frames, n_modes))
    e_prev = np.zeros(n_modes)
    for k in range(n_frames):
        for i in range(n_modes):
            u[k + k0 + 2, i] = u[k + k0 + 1, i] + ctrl_gain[i] * e_prev[i]
            y = (1 - f) * u[k + 2, i] + f * u[k + 1, i]
            e[k, i] = d[k, i] - y
        e_prev = e[k]
    return e


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=15000)
    p.add_argument("--modes", type=int, default=540)
    p.add_argument("--n-pix", type=int, default=64)
    p.add_argument("--science-every", type=int, default=10)
    p.add_argument("--quick", action="store_true", help="3000 frames, 200 modes")
    args = p.parse_args()
    if args.quick:
        args.frames, args.modes = 3000, 200

    fs, latency = 3000.0, 0.83
    seeing, tau0 = 0.4, 9e-3  # bright 1 best
    t0 = time.perf_counter()
    pupil = vlt_pupil(args.n_pix)
    dm = DeformableMirror(pupil, n_actuators=SAXO_PLUS_N_ACTUATORS)
    basis = kl_basis(dm, args.modes, r0=r0_from_seeing(seeing))
    t_cal = time.perf_counter() - t0

    r0 = r0_from_seeing(seeing)
    layers = scale_to_tau0(eso_median_profile(4), r0, tau0)
    atm = Atmosphere(pupil, r0, layers, fs, rng=1)
    camera = ScienceCamera(pupil, field_of_view=20.0)
    stage = Stage(
        Integrator(0.5, fs=fs, n_modes=args.modes),
        LinearModalSensor(1.0, 1.0),
        latency,
        name="stage 2",
    )

    t0 = time.perf_counter()
    res = run_loop(
        stage,
        TurbulenceSource(atm, basis),
        args.frames,
        rng=2,
        science=camera.long_exposure(),
        basis=basis,
        science_every=args.science_every,
        record=("measurements", "commands"),
    )
    t_run = time.perf_counter() - t0

    # Parts measured separately in the same run (fresh atmosphere, same sizes).
    atm2 = Atmosphere(pupil, r0, layers, fs, rng=1)
    t0 = time.perf_counter()
    maps = atm2.phase_vectors(1000)
    t_atm = (time.perf_counter() - t0) * args.frames / 1000
    t0 = time.perf_counter()
    d = basis.project(maps)
    t_proj = (time.perf_counter() - t0) * args.frames / 1000
    t0 = time.perf_counter()
    exp = camera.long_exposure()
    exp.add(pupil.to_map(maps[:: args.science_every] - basis.synthesize(d[:: args.science_every])))
    t_sci = (time.perf_counter() - t0) * args.frames / 1000

    n_ref = 300
    gains = np.full(args.modes, 0.5)
    t0 = time.perf_counter()
    _naive_loop(gains, d[:n_ref], latency)
    t_naive = (time.perf_counter() - t0) / n_ref
    from aocontrol.sim.loop import ModalTimeSeries

    t0 = time.perf_counter()
    run_loop(
        Stage(Integrator(gains, fs=fs), latency_frames=latency), ModalTimeSeries(d), 1000, record=()
    )
    t_vec = (time.perf_counter() - t0) / 1000

    sci = res.science
    print(
        f"single-stage fast loop: {args.modes} modes, {args.frames} frames at {fs:g} Hz "
        f"({args.frames / fs:g} s), pupil {args.n_pix}x{args.n_pix}, "
        f"PSF every {args.science_every} frames"
    )
    print(f"  calibration (DM + {args.modes} KL modes): {t_cal:7.2f} s")
    print(
        f"  closed-loop run incl. atmosphere, science: {t_run:7.2f} s "
        f"({args.frames / t_run:,.0f} frames/s)"
    )
    print(
        f"    of which (measured separately, scaled to the run): atmosphere {t_atm:.2f} s, "
        f"projection {t_proj:.2f} s, science {t_sci:.2f} s"
    )
    print(f"  run time / goal ({GOAL_SECONDS:g} s): {t_run / GOAL_SECONDS:.2f}")
    print(
        f"  vectorised loop vs per-mode Python loop: {t_naive / t_vec:,.0f}x faster "
        f"({t_vec * 1e6:.0f} us/frame vs {t_naive * 1e3:.1f} ms/frame)"
    )
    print(
        f"  Strehl @1.65um: {sci.strehl:.4f}, mean contrast 4-6 l/D: "
        f"{sci.mean_contrast_4_6:.3e}, residual {res.residual_rms:.1f} nm RMS (modal)"
    )


if __name__ == "__main__":
    main()
