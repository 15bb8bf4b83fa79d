"""Benchmark: the pyramid in the loop (issue 15): linear vs diffractive stage 2, and its cost.

(a) Cost, per fast frame of a cascade (stage 2 at 3 kHz): the linear stage 2, the diffractive
    one (the case's pyramid: 80-px pupil, 40x40, 20 modulation points, then the
    reconstructor), and the diffractive one with optical-gain tracking; ratios measured in
    one run (wall and process CPU time; the machine may be shared).
(b) Fidelity: for each case, the comparison's cells (controllers x schemes) with stage 2
    linear (calibrated gains) and diffractive (none, calibrated, tracked), Strehl and raw
    contrast, beside the paper's values, and the stage-2 residual predicted from the
    calibration telemetry vs measured.

    .venv/bin/python benchmarks/bench_fidelity.py [--quick] [--cost-only] [--seconds S]
        [--cases red5-best,bright1-best]

``--quick``: quick scenes (24 stage-2 modes), 0.1-s exposures, one case, one scheme.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from aocontrol.controllers import Integrator
from aocontrol.sim.loop import Stage, run_cascade
from aocontrol.study.compare import run_configuration
from aocontrol.study.scene import build_scene

CASES = ("red5-best", "red3-medium", "bright1-best")
CONTROLLERS = ("reference", "omgi", "datadriven")
SCHEMES = ("standalone", "dcao")
SETTINGS = (
    ("linear", "calibrated"),
    ("diffractive", "none"),
    ("diffractive", "calibrated"),
    ("diffractive", "tracked"),
)


def _cascade_cost(scene, sensor: str, optical_gain: str, n_frames: int) -> tuple[float, float]:
    """Wall and CPU seconds per fast frame of a standalone cascade (reference integrators)."""
    st1, st2 = scene.stage1, scene.stage2
    s1 = Stage(
        Integrator(st1.spec.gain, fs=st1.fs, n_modes=st1.n_modes),
        st1.sensor,
        st1.spec.latency_frames,
        basis=st1.basis,
    )
    sens, tracker = st2.loop_sensor(sensor, optical_gain)
    s2 = Stage(
        Integrator(st2.spec.gain, fs=st2.fs, n_modes=st2.n_modes),
        sens,
        st2.spec.latency_frames,
        basis=st2.basis,
        gain_tracker=tracker,
    )
    ratio = scene.case.rate_ratio
    n = -(-n_frames // ratio) * ratio
    atm = scene.atmosphere(0)
    wall, cpu = time.perf_counter(), time.process_time()
    run_cascade(s1, s2, atm, n, scheme="standalone", rng=1, record=(), settle_frames=ratio)
    return (time.perf_counter() - wall) / n, (time.process_time() - cpu) / n


def cost(case: str, quick: bool, n_frames: int) -> None:
    scene = build_scene(case, quick=quick)
    st2 = scene.stage2
    pyr = st2.wfs
    opd = np.random.default_rng(0).standard_normal((pyr.pupil.n_pix,) * 2) * 50.0
    pyr.signals(opd)
    t = time.perf_counter()
    for _ in range(20):
        pyr.signals(opd)
    t_pyr = (time.perf_counter() - t) / 20
    print(
        f"(a) {case}{' quick' if quick else ''}: pyramid {pyr.pupil.n_pix} px, "
        f"{pyr.n_subapertures}x{pyr.n_subapertures}, {pyr.n_points} modulation points: "
        f"{t_pyr * 1e3:.2f} ms per frame (signals alone)"
    )
    rows = {}
    for sensor, og in (
        ("linear", "calibrated"),
        ("diffractive", "calibrated"),
        ("diffractive", "tracked"),
    ):
        rows[(sensor, og)] = _cascade_cost(scene, sensor, og, n_frames)
        w, c = rows[(sensor, og)]
        print(
            f"    fast frame, stage 2 {sensor:11s} {og:10s}: {w * 1e3:7.2f} ms wall, "
            f"{c * 1e3:7.2f} ms CPU"
        )
    lin = rows[("linear", "calibrated")][0]
    dif = rows[("diffractive", "calibrated")][0]
    trk = rows[("diffractive", "tracked")][0]
    print(
        f"    ratios (one run): diffractive / linear {dif / lin:.1f}x, "
        f"tracked / untracked {trk / dif:.3f}"
    )
    print(
        f"    5.1-s two-stage diffractive exposure at {st2.fs:g} Hz: "
        f"{5.1 * st2.fs * dif:.0f} s at this speed"
    )


def fidelity(quick: bool, seconds: float, cases: tuple[str, ...], schemes: tuple[str, ...]) -> None:
    print("(b) case scheme controller | sensor/optical_gain: Strehl, contrast 4-6, residual nm")
    for case in cases:
        for scheme in schemes:
            for controller in CONTROLLERS if not quick else ("reference",):
                cells = []
                for sensor, og in SETTINGS:
                    out = run_configuration(
                        case,
                        controller=controller,
                        scheme=scheme,
                        seconds=seconds,
                        quick=quick,
                        sensor=sensor,
                        optical_gain=og,
                    )
                    s = out.summary
                    cells.append(
                        f"{sensor[:3]}/{og}: {s['strehl']:.3f} {s['mean_contrast_4_6']:.2e} "
                        f"{s['residual_rms_nm']:.1f}"
                    )
                print(f"    {case} {scheme} {controller} | " + " | ".join(cells))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="quick scenes, short runs")
    parser.add_argument("--cost-only", action="store_true", help="only part (a)")
    parser.add_argument("--seconds", type=float, default=None, help="exposure [s]")
    parser.add_argument("--cases", default=None, help="comma-separated cases of part (b)")
    args = parser.parse_args()
    quick = args.quick
    if not args.cases:
        cost("red5-best", quick, 300 if quick else 600)
    if args.cost_only:
        return
    seconds = args.seconds or (0.1 if quick else 5.0)
    cases = tuple(args.cases.split(",")) if args.cases else (CASES[:1] if quick else CASES)
    fidelity(quick, seconds, cases, SCHEMES[:1] if quick else SCHEMES)


if __name__ == "__main__":
    main()
