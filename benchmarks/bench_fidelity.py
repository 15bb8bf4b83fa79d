"""Benchmark: the pyramid in the loop (issue 15): linear vs diffractive stage 2, and its cost.

(a) Cost, per fast frame of a cascade (stage 2 at 3 kHz): the linear stage 2, the diffractive
    one (the case's pyramid: 80-px pupil, 40x40, 20 modulation points, then the
    reconstructor), and the diffractive one with optical-gain tracking; ratios measured in
    one run (wall and process CPU time; the machine may be shared).
(b) Fidelity: for each case and stage-2 setting (linear with calibrated gains, diffractive
    with none, calibrated, tracked gains), the paper's protocol (``compare_case``: reference
    gain scanned, calibration run, reference / optimised modal gain / data-driven, standalone
    and dCAO): Strehl and raw contrast beside the paper's values, the contrast orderings, the
    dCAO - standalone Strehl, and the stage-2 residual predicted from the calibration
    telemetry vs measured; printed as markdown.

    .venv/bin/python benchmarks/bench_fidelity.py [--quick] [--cost-only] [--seconds S]
        [--cases red5-best,bright1-best] [--settings linear/calibrated,diffractive/none]
        [--seed N] [--gain-grid 0.2,0.4]

``--quick``: quick scenes (24 stage-2 modes), 0.1-s exposures, one case.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

# The paper's tables (same folder: run as a script, its directory is on sys.path).
from bench_paper_tables import _ORDER as ORDER  # noqa: E402
from bench_paper_tables import PAPER  # noqa: E402

from aocontrol.controllers import Integrator
from aocontrol.sim.loop import Stage, run_cascade
from aocontrol.study.compare import compare_case
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


def _markdown(case: str, setting: str, comp, seconds: float, wall: float) -> list[str]:
    """The case's six cells beside the paper (markdown rows) and the orderings."""
    pc, ps = PAPER.get(case, (None, None))
    lines = [
        f"#### {case}, stage 2 {setting} ({seconds:g}-s exposures, reference gains "
        f"{ {k: round(v, 2) for k, v in comp.reference_gains.items()} }, {wall:.0f} s)",
        "",
        "| scheme controller | Strehl % | paper | diff | contrast 4-6 | paper | ratio "
        "| stage-2 residual nm | predicted nm | pred/meas |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for i, (scheme, ctrl) in enumerate(ORDER):
        try:
            c = comp.cell(ctrl, scheme)
        except KeyError:
            continue
        s_pap = f"{ps[i]:.2f}" if ps else "-"
        c_pap = f"{pc[i]:.2e}" if pc else "-"
        diff = f"{100 * c.strehl - ps[i]:+.2f}" if ps else "-"
        ratio = f"{c.mean_contrast_4_6 / pc[i]:.2f}" if pc else "-"
        pred = c.predicted_rms_nm
        pm = f"{pred / c.residual_rms_nm:.3f}" if pred == pred else "-"
        lines.append(
            f"| {scheme} {ctrl} | {100 * c.strehl:.2f} | {s_pap} | {diff} | "
            f"{c.mean_contrast_4_6:.3e} | {c_pap} | {ratio} | {c.residual_rms_nm:.2f} | "
            f"{pred:.2f} | {pm} |"
        )
    lines.append("")
    for scheme in sorted({c.scheme for c in comp.cells}):
        con = {c.controller: c.mean_contrast_4_6 for c in comp.cells if c.scheme == scheme}
        order = " < ".join(sorted(con, key=con.get))
        lines.append(f"- contrast ordering {scheme}: {order}")
    schemes = {c.scheme for c in comp.cells}
    if {"standalone", "dcao"} <= schemes:
        for ctrl in sorted({c.controller for c in comp.cells}):
            d = 100 * (comp.cell(ctrl, "dcao").strehl - comp.cell(ctrl, "standalone").strehl)
            lines.append(f"- {ctrl}: dCAO - standalone Strehl {d:+.2f} points")
    return lines


def fidelity(
    quick: bool,
    seconds: float,
    cases: tuple[str, ...],
    settings: tuple[tuple[str, str], ...],
    seed: int,
    gain_grid: tuple[float, ...] | None,
) -> None:
    """Part (b): the paper's protocol (:func:`compare_case`: gain scan, calibration, the three
    controllers, both schemes) per case and stage-2 setting, as markdown beside the paper."""
    for case in cases:
        for sensor, og in settings:
            t0 = time.perf_counter()
            comp = compare_case(
                case,
                controllers=CONTROLLERS,
                schemes=SCHEMES,
                seconds=seconds,
                seed=seed,
                quick=quick,
                gain_grid=gain_grid,
                sensor=sensor,
                optical_gain=og,
            )
            wall = time.perf_counter() - t0
            print("\n".join(_markdown(case, f"{sensor}/{og}", comp, seconds, wall)), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="quick scenes, short runs")
    parser.add_argument("--cost-only", action="store_true", help="only part (a)")
    parser.add_argument("--seconds", type=float, default=None, help="exposure [s]")
    parser.add_argument("--cases", default=None, help="comma-separated cases of part (b)")
    parser.add_argument(
        "--settings",
        default=None,
        help="comma-separated sensor/optical_gain of part (b), e.g. linear/calibrated,"
        "diffractive/none (default: all of SETTINGS)",
    )
    parser.add_argument("--seed", type=int, default=0, help="user seed of part (b)")
    parser.add_argument(
        "--gain-grid", default=None, help="comma-separated reference gains scanned (part b)"
    )
    args = parser.parse_args()
    quick = args.quick
    if not args.cases:
        cost("red5-best", quick, 300 if quick else 600)
    if args.cost_only:
        return
    seconds = args.seconds or (0.1 if quick else 5.0)
    cases = tuple(args.cases.split(",")) if args.cases else (CASES[:1] if quick else CASES)
    settings = (
        tuple(tuple(x.split("/")) for x in args.settings.split(",")) if args.settings else SETTINGS
    )
    grid = tuple(float(g) for g in args.gain_grid.split(",")) if args.gain_grid else None
    fidelity(quick, seconds, cases, settings, args.seed, grid)


if __name__ == "__main__":
    main()
