"""Benchmark: the paper's five science cases and its vibration case, each table printed beside
the paper's numbers, with the orderings, the per-cell targets and the costs (issue 7).

Reference data: the paper's tables "Bright 1 best / Bright 1 worst / Red 1 fast / Red 3
medium / Red 5 best, performance comparison" (mean contrast 4-6 lambda/D and Strehl [%] for
standalone and dCAO with the reference integrator, the optimised modal gain and the
data-driven controller) and "Tilt residual RMS comparison in presence of vibrations"
(Dinis et al., SAXO+ paper, sections "Science cases results" and "Performance under
vibrations").

Checks printed (PASS/MISS, never asserted: a benchmark reports):
- data-driven best or equal in contrast in every case and scheme (equal: within 5 %);
- bright cases: dCAO reference worse than standalone reference, dCAO data-driven recovers it
  (within 10 % of the standalone reference);
- Strehl within 5 points and contrast within a factor 3 of the paper, per cell;
- vibration: tilt residual gain of data-driven over the integrator >= 30 %;
- costs: a 5.1-s two-stage exposure <= 20 s, one case <= 5 min, all six <= 10 min
  (issue 19; 2-core shared machine).

The vibration case runs the paper's protocol for it (:data:`VIBRATION_PROTOCOL`: one scheme,
the integrator against the data-driven controller), not the full table of the five cases: its
other cells are no figure of the paper.

Usage: python benchmarks/bench_paper_tables.py [--quick] [--cases bright1-best,vibration]
       [--seconds 5] [--results-dir DIR]
"""

from __future__ import annotations

import argparse
import logging
import time

from aocontrol.study.compare import compare_case, run_configuration
from aocontrol.study.scene import build_scene

# Paper tables: (contrast, Strehl %) per (scheme, controller), order: standalone reference,
# omgi, data-driven, dCAO reference, omgi, data-driven.
_ORDER = [
    ("standalone", "reference"),
    ("standalone", "omgi"),
    ("standalone", "datadriven"),
    ("dcao", "reference"),
    ("dcao", "omgi"),
    ("dcao", "datadriven"),
]
PAPER = {
    "bright1-best": (
        [2.62e-6, 2.62e-6, 2.49e-6, 6.99e-6, 6.28e-6, 2.61e-6],
        [98.19, 98.19, 98.20, 98.09, 98.05, 98.19],
    ),
    "bright1-worst": (
        [1.35e-5, 1.35e-5, 1.29e-5, 2.64e-5, 2.39e-5, 1.17e-5],
        [91.82, 91.84, 91.92, 91.54, 91.59, 91.90],
    ),
    "red1-fast": (
        [1.00e-4, 9.44e-5, 7.87e-5, 1.00e-4, 9.63e-5, 7.16e-5],
        [88.85, 89.22, 89.54, 88.70, 89.14, 89.85],
    ),
    "red3-medium": (
        [1.06e-4, 1.03e-4, 8.35e-5, 1.04e-4, 1.01e-4, 8.15e-5],
        [88.11, 88.77, 89.36, 88.16, 88.78, 89.39],
    ),
    "red5-best": (
        [6.23e-4, 5.58e-4, 5.74e-4, 6.18e-4, 5.65e-4, 5.69e-4],
        [78.01, 81.16, 81.95, 78.07, 80.29, 80.55],
    ),
}
#: Paper, "Tilt residual RMS comparison in presence of vibrations": integrator, data-driven [nm].
PAPER_VIBRATION = (9.09, 6.21, 0.317)
STREHL_POINTS, CONTRAST_FACTOR, EQUAL_RTOL, RECOVER_RTOL = 5.0, 3.0, 0.05, 0.10
#: Cost goals [s]: an exposure and a case (issue 7), the six cases (issue 19: was 1800 s).
GOALS = {"exposure": 20.0, "case": 300.0, "all": 600.0}
#: The paper's vibration experiment: stage 1 an integrator, stage 2 the integrator against the
#: data-driven controller, one scheme (the report reads the first). The other scheme and the
#: modal gain would be one more scan, calibration and data-driven bank for figures that the
#: paper does not report.
VIBRATION_PROTOCOL = {"schemes": ("standalone",), "controllers": ("reference", "datadriven")}


def _flag(ok: bool) -> str:
    return "PASS" if ok else "MISS"


def _report_case(name: str, comp) -> list[str]:
    misses = []
    print(comp.table())
    print(
        f"  reference gains (scan): {comp.reference_gains}; times [s]: "
        f"{ {k: round(v, 1) for k, v in comp.seconds.items()} }"
    )
    if name in PAPER:
        pc, ps = PAPER[name]
        print(
            f"  {'configuration':24} {'contrast':>10} {'paper':>10} {'ratio':>6}  "
            f"{'Strehl%':>7} {'paper':>6} {'diff':>5}"
        )
        for (scheme, ctrl), c_ref, s_ref in zip(_ORDER, pc, ps, strict=True):
            cell = comp.cell(ctrl, scheme)
            ratio = cell.mean_contrast_4_6 / c_ref
            diff = 100 * cell.strehl - s_ref
            ok = abs(diff) <= STREHL_POINTS and 1 / CONTRAST_FACTOR <= ratio <= CONTRAST_FACTOR
            if not ok:
                misses.append(f"{name} {scheme} {ctrl}")
            print(
                f"  {scheme + ' ' + ctrl:24} {cell.mean_contrast_4_6:10.3e} {c_ref:10.2e} "
                f"{ratio:6.2f}  {100 * cell.strehl:7.2f} {s_ref:6.2f} {diff:+5.2f}  {_flag(ok)}"
            )
    for scheme in sorted({c.scheme for c in comp.cells}):
        con = {
            c.controller: c.mean_contrast_4_6
            for c in comp.cells
            if c.scheme == scheme and c.controller in ("reference", "omgi", "datadriven")
        }
        if "datadriven" in con:
            best = min(con.values())
            ok = con["datadriven"] <= best * (1 + EQUAL_RTOL)
            print(f"  ordering {scheme}: data-driven best or equal in contrast: {_flag(ok)}")
    if name.startswith("bright"):
        ref_s = comp.cell("reference", "standalone").mean_contrast_4_6
        ref_d = comp.cell("reference", "dcao").mean_contrast_4_6
        dd_d = comp.cell("datadriven", "dcao").mean_contrast_4_6
        print(
            f"  ordering: dCAO reference worse than standalone reference: {_flag(ref_d > ref_s)}"
            f" ({ref_d:.3e} vs {ref_s:.3e})"
        )
        print(
            f"  ordering: dCAO data-driven recovers it: "
            f"{_flag(dd_d <= ref_s * (1 + RECOVER_RTOL))} ({dd_d:.3e})"
        )
    for c in comp.cells:
        if c.predicted_rms_nm == c.predicted_rms_nm:  # not NaN
            print(
                f"  {c.scheme} {c.controller}: stage-2 residual measured "
                f"{c.residual_rms_nm:.2f} nm, predicted from telemetry {c.predicted_rms_nm:.2f}"
            )
    if comp.vibration is not None:
        v = comp.vibration
        a = v["tilt_rms_nm"].get("reference")
        b = v["tilt_rms_nm"].get("datadriven")
        if a is not None and b is not None:
            gain = v["relative_gain"]
            print(
                f"  vibration ({v['scheme']}): tilt residual integrator {a:.2f} nm, data-driven "
                f"{b:.2f} nm, gain {100 * gain:.1f} % (paper {PAPER_VIBRATION[0]} vs "
                f"{PAPER_VIBRATION[1]} nm, {100 * PAPER_VIBRATION[2]:.1f} %): "
                f"{_flag(gain >= 0.30)}"
            )
        others = {k: x for k, x in v["tilt_rms_nm"].items() if k not in ("reference", "datadriven")}
        if others:
            print(
                "  vibration, the other controllers' tilt residual: "
                + ", ".join(f"{k} {x:.2f} nm" for k, x in others.items())
            )
    return misses


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="quick scenes, short exposures")
    p.add_argument("--cases", default=",".join([*PAPER, "vibration"]))
    p.add_argument("--seconds", type=float, default=None, help="exposure [s] (default 5)")
    p.add_argument("--results-dir", default=None)
    p.add_argument(
        "--extra-controllers",
        default="",
        help="registered controllers run beside the paper's three (e.g. lqg,eof,"
        "datadriven-robust): their cells printed with the contrast at 1-2 and 4-6 lambda/D",
    )
    args = p.parse_args()
    extra = tuple(c for c in args.extra_controllers.split(",") if c)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    cases = [c for c in args.cases.split(",") if c]
    t_all = time.perf_counter()
    misses, costs = [], {}
    for name in cases:
        t0 = time.perf_counter()
        scene = build_scene(name, quick=args.quick)
        t_scene = time.perf_counter() - t0
        print(f"\n=== {name}: scene {t_scene:.1f} s {scene.settings()['stage2']}", flush=True)
        protocol = dict(VIBRATION_PROTOCOL) if scene.case.vibration is not None else {}
        if extra:
            # The vibration case keeps its protocol (one scheme) with the extras beside it.
            base = protocol.get("controllers", ("reference", "omgi", "datadriven"))
            protocol["controllers"] = (*base, *extra)
        comp = compare_case(
            name,
            quick=args.quick,
            seconds=args.seconds,
            results_dir=args.results_dir,
            **protocol,
        )
        costs[name] = time.perf_counter() - t0
        misses += _report_case(name, comp)
        print(
            f"  case wall time {costs[name]:.1f} s (goal {GOALS['case']:.0f} s): "
            f"{_flag(costs[name] <= GOALS['case'])}",
            flush=True,
        )
    t_total = time.perf_counter() - t_all
    # One 5.1-s two-stage exposure, 1200 + 540 modes at 3 kHz (bright 1 worst, reusing its
    # cached scene), timed alone.
    if not args.quick and "bright1-worst" in cases:
        out = run_configuration("bright1-worst", controller="reference", scheme="dcao", seconds=5.0)
        t_exp = out.summary["run_seconds"]
        print(
            f"\n5.1-s two-stage exposure (1200 + 540 modes, 3 kHz): {t_exp:.1f} s "
            f"(goal {GOALS['exposure']:.0f} s): {_flag(t_exp <= GOALS['exposure'])}"
        )
    print(
        f"all cases: {t_total:.1f} s (goal {GOALS['all']:.0f} s): "
        f"{_flag(t_total <= GOALS['all'])} (2-core shared machine)"
    )
    print(f"cells outside the per-cell targets: {len(misses)}: {misses}")


if __name__ == "__main__":
    main()
