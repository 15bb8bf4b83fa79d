"""Benchmark: frame synthesis of the multi-layer extruded atmosphere (aocontrol.sim.atmosphere).

For each configuration (pupil sampling, number of ESO-profile layers, frame rate), the time to
produce 15000 frames on the pupil pixels in chunks of 1000 (``phase_vectors``), wall clock
and process CPU time (the machine may be shared: CPU time does not count waiting for a core),
and the ratios measured in this one run: bicubic / bilinear and float32 / float64 costs, and
the real-time factor (simulated seconds per wall second). Seeing 0.8", tau0 3 ms, L0 25 m.

    .venv/bin/python benchmarks/bench_atmosphere.py [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from aocontrol.sim.profiles import eso_atmosphere
from aocontrol.sim.pupil import Pupil

CHUNK = 1000


def _time(
    n_pix: int,
    n_layers: int,
    fs: float,
    n_frames: int,
    **kwargs: object,
) -> tuple[float, float]:
    atm = eso_atmosphere(
        Pupil(n_pix=n_pix), seeing=0.8, tau0=3e-3, fs=fs, n_layers=n_layers, rng=0, **kwargs
    )
    atm.phase_vectors(10)  # warm-up (caches)
    atm.reset()
    wall, cpu = time.perf_counter(), time.process_time()
    done = 0
    while done < n_frames:
        step = min(CHUNK, n_frames - done)
        atm.phase_vectors(step)
        done += step
    return time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small configuration")
    args = parser.parse_args()
    if args.quick:
        configs, n_frames = [(32, 5, 3000.0)], 3000
    else:
        configs, n_frames = (
            [
                (64, 5, 3000.0),
                (64, 10, 3000.0),
                (64, 5, 1000.0),
                (64, 35, 3000.0),
                (128, 5, 3000.0),
            ],
            15000,
        )
    print(
        f"{'n_pix':>5} {'layers':>6} {'fs':>6} | {'wall s':>7} {'CPU s':>6} {'frames/s':>9} "
        f"{'x real time':>11} | {'cubic/lin':>9} {'f32/f64':>7}"
    )
    for n_pix, n_layers, fs in configs:
        wall, cpu = _time(n_pix, n_layers, fs, n_frames)
        wall_c, _ = _time(n_pix, n_layers, fs, n_frames, interpolation="cubic")
        wall_32, _ = _time(n_pix, n_layers, fs, n_frames, dtype=np.float32)
        print(
            f"{n_pix:>5} {n_layers:>6} {fs:>6.0f} | {wall:>7.2f} {cpu:>6.2f} "
            f"{n_frames / wall:>9.0f} {n_frames / fs / wall:>11.2f} | "
            f"{wall_c / wall:>9.2f} {wall_32 / wall:>7.2f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
