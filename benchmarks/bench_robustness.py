"""Benchmark: what each controller keeps when the instrument differs from its model (issue 29).

Protocol, per case (stage 2, standalone cascade, the case's sensor settings):

1. one calibration run of the nominal instrument with the reference integrator; every
   controller is designed from its telemetry (the reference integrator at the case's gain,
   the optimised modal gains, the LQG, the data-driven design nominal, robust over
   ``aocontrol.synthesis.ROBUST_SET`` (loop gain +-30 %, latency +-0.3 frame) and with
   integral action);
2. each controller runs the exposure on the nominal instrument and under each model error
   (:mod:`aocontrol.sim.model_errors`, a case setting of the run: the designs keep the
   nominal plant) at 2-3 magnitudes; one error, ``pol-latency``, also runs the calibration
   under it (the pseudo-open loop rebuilt with the wrong plant) and redesigns from it;
3. printed per (error, magnitude, controller): the stage-2 residual RMS, the raw contrast at
   1-2 and 4-6 lambda/D, and the fraction of the nominal gain over the reference that remains,
   ``retained = (1 - v / v_ref)_error / (1 - v / v_ref)_nominal`` (``v`` residual variances),
   and the loss ``v_error / v_nominal`` of the controller itself; a diverged run is a row
   ("diverged"), never a crash. The plots: retained gain and loss against the error's
   magnitude, a line per controller, a panel per error;
4. for the latency and loop-gain errors, the analysis's verdict: "certified" when the error
   lies inside every mode's exact gain or delay interval (:func:`aocontrol.analysis.margins`
   on the design plant), else the closed-loop poles of the perturbed design plant (outside
   its interval a loop can be stable again); and how many runs agree with the simulator,
   whose own check (the closed-loop poles of the true stage) decides a diverged run.

Usage: python benchmarks/bench_robustness.py [--quick] [--cases bright1-best,red1-fast]
       [--seconds 1] [--out robustness-output] [--errors latency,gain,...]
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import time
import warnings

import numpy as np

from aocontrol.analysis import (
    UncertaintySet,
    is_stable,
    margins,
    multimode_closed_loop_poles,
    robust_margin,
)
from aocontrol.controllers import MultiModeBank
from aocontrol.plant import plant_latency, with_latency
from aocontrol.sim.loop import LoopDivergedError
from aocontrol.study._simulate import run_summary, simulate_scene
from aocontrol.study.cases import apply_overrides, load_case
from aocontrol.study.compare import calibration_seconds, design_inputs, run_configuration
from aocontrol.study.plot import plot_robustness
from aocontrol.study.scene import build_scene

CONTROLLERS = (
    "reference",
    "omgi",
    "lqg",
    "datadriven",
    "datadriven-robust",
    "datadriven-integral",
    "eof",
)
#: Model errors: name -> [(label, magnitude, case overrides)].
ERRORS = {
    "latency": [
        ("-0.3 frame", -0.3, {"stage2.latency_error": -0.3}),
        ("+0.3 frame", 0.3, {"stage2.latency_error": 0.3}),
        ("+0.6 frame", 0.6, {"stage2.latency_error": 0.6}),
        ("+1 frame", 1.0, {"stage2.latency_error": 1.0}),
        ("+2 frames", 2.0, {"stage2.latency_error": 2.0}),
    ],
    "loop gain": [
        ("x0.7", 0.7, {"stage2.optical_gain_error": 0.7}),
        ("x1.3", 1.3, {"stage2.optical_gain_error": 1.3}),
        ("x1.6", 1.6, {"stage2.optical_gain_error": 1.6}),
        ("x2.2", 2.2, {"stage2.optical_gain_error": 2.2}),
        ("x3", 3.0, {"stage2.optical_gain_error": 3.0}),
    ],
    "gain drift": [
        (
            "+-15 %",
            0.15,
            {"stage2.optical_gain_drift": 0.15, "stage2.optical_gain_drift_period": "0.5 s"},
        ),
        (
            "+-30 %",
            0.30,
            {"stage2.optical_gain_drift": 0.30, "stage2.optical_gain_drift_period": "0.5 s"},
        ),
    ],  # fmt: skip
    "DM lag": [
        ("0.1 ms", 0.1, {"stage2.dm_time_constant": "0.1 ms"}),
        ("0.3 ms", 0.3, {"stage2.dm_time_constant": "0.3 ms"}),
        ("1 ms", 1.0, {"stage2.dm_time_constant": "1 ms"}),
    ],
    "misregistration": [
        ("0.1 subap", 0.1, {"stage2.misregistration_shift_x": 0.1}),
        (
            "0.25 subap + 1 deg",
            0.25,
            {"stage2.misregistration_shift_x": 0.25, "stage2.misregistration_rotation": 1.0},
        ),
    ],  # fmt: skip
    "pol-latency": [
        ("+0.3 frame", 0.3, {"stage2.latency_error": 0.3}),
    ],
    # The corners of the robust design's set (ROBUST_SET): both errors at once.
    "gain at -0.3 frame": [
        ("x0.7, -0.3 frame", 0.7, {"stage2.optical_gain_error": 0.7, "stage2.latency_error": -0.3}),
        ("x1.3, -0.3 frame", 1.3, {"stage2.optical_gain_error": 1.3, "stage2.latency_error": -0.3}),
    ],
    "gain at +0.3 frame": [
        ("x0.7, +0.3 frame", 0.7, {"stage2.optical_gain_error": 0.7, "stage2.latency_error": 0.3}),
        ("x1.3, +0.3 frame", 1.3, {"stage2.optical_gain_error": 1.3, "stage2.latency_error": 0.3}),
    ],
}
#: The errors of the sensor itself: those run with ``--sensor diffractive`` by default.
SENSOR_ERRORS = ("gain drift", "misregistration")
#: The unit of each error's magnitude (the plots' axes).
UNITS = {"latency": "frames", "loop gain": "factor", "gain drift": "amplitude", "DM lag": "ms",
         "misregistration": "subapertures", "pol-latency": "frames",
         "gain at -0.3 frame": "factor", "gain at +0.3 frame": "factor"}  # fmt: skip


#: Errors the stability margins certify, and how: a latency change [frames] inside every
#: mode's delay interval, a loop-gain factor inside every mode's gain interval.
CERTIFIED = {
    "latency": lambda m, x: m.stable and m.delay_interval[0] < x < m.delay_interval[1],
    "loop gain": lambda m, x: m.stable and m.gain_interval[0] < x < m.gain_interval[1],
}


def _gain_and_latency(err: str, magnitude: float, overrides: dict) -> tuple[float, float]:
    """The loop-gain factor and latency change [frames] of an error the analysis decides."""
    if err == "latency":
        return 1.0, magnitude
    if err == "loop gain":
        return magnitude, 0.0
    return overrides["stage2.optical_gain_error"], overrides["stage2.latency_error"]


def _predicted(plant, bank, mar, err, magnitude, overrides) -> str:
    """The analysis's verdict on the loop under ``err`` of ``magnitude``: ``"certified"``
    when every mode's margin interval holds it (:func:`aocontrol.analysis.margins`), or,
    for a corner of both errors, every mode's certified margin over the box from the
    nominal to the corner (:func:`aocontrol.analysis.robust_margin`) is above 0; else
    ``"stable"`` / ``"unstable"`` from the closed-loop poles of the perturbed plant
    (:func:`aocontrol.analysis.is_stable`: outside its interval a loop may be stable again,
    a conditionally stable loop at a longer latency); ``""`` where the analysis does not
    decide (another error, a bank without per-mode transfer functions)."""
    if err not in CERTIFIED and not err.startswith("gain at "):
        return ""
    gain, shift = _gain_and_latency(err, magnitude, overrides)
    if isinstance(bank, MultiModeBank):  # the multivariable loop's poles, the plant changed
        poles = multimode_closed_loop_poles(
            bank, latency_frames=bank.latency_frames + shift, optical_gain=gain
        )
        return "stable" if np.abs(poles).max() < 1.0 else "unstable"
    if mar is None:
        return ""
    if err in CERTIFIED:
        certified = all(CERTIFIED[err](m, magnitude) for m in mar)
    else:
        box = UncertaintySet(gain=(min(gain, 1.0), max(gain, 1.0)),
                             latency=(min(shift, 0.0), max(shift, 0.0)))  # fmt: skip
        certified = all(
            (r := robust_margin(plant, bank, box, mode=i)).stable and r.value > 0
            for i in range(bank.n_modes)
        )
    if certified:
        return "certified"
    true = with_latency(plant, plant_latency(plant) + shift) * gain
    ok = all(is_stable(true, bank, mode=i) for i in range(bank.n_modes))
    return "stable" if ok else "unstable"


def _bank_margins(plant, bank):
    """Every mode's :class:`~aocontrol.analysis.Margins` on the design plant, or ``None``
    (a multi-mode bank: its certificate is multivariable)."""
    try:
        return [margins(plant, bank, mode=i) for i in range(bank.n_modes)]
    except (NotImplementedError, TypeError):
        return None


def _run(case, bank, seconds, quick, overrides, seed):
    """One exposure of ``bank`` on stage 2 of the instrument ``overrides`` makes of ``case``
    (the bank designed once, on the nominal instrument's telemetry)."""
    scene = build_scene(apply_overrides(load_case(case), overrides), quick=quick)
    try:
        res = simulate_scene(scene, bank, "standalone", seconds, seed, "exposure")
    except LoopDivergedError as exc:
        return {"status": "diverged", "detail": str(exc)[:120]}
    summary = run_summary(res)
    sci = res.science
    radii = np.asarray(sci.radii_ld)
    profile = np.asarray(sci.contrast_profile)
    return {
        "status": "ok",
        "residual_nm": summary["residual_rms_nm"],
        "contrast_1_2": float(np.mean(profile[(radii >= 1) & (radii <= 2)])),
        "contrast_4_6": summary["mean_contrast_4_6"],
        "strehl": summary["strehl"],
    }


def _design(case, name, quick, design, seed, base):
    """The bank of ``name`` designed from ``design`` (the registry's design, as the
    comparison runs it) on the instrument ``base`` makes of ``case``."""
    out = run_configuration(
        case, controller=name, scheme="standalone", seconds=0.05, seed=seed, quick=quick,
        design=design, overrides=base,
    )  # fmt: skip
    return out.controller


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--quick",
        action="store_true",
        default=True,
        help="quick scenes (24 stage-2 modes; the default, see --full)",
    )
    ap.add_argument("--full", action="store_true", help="the cases at full scale (hours)")
    ap.add_argument("--smoke", action="store_true", help="one error, two controllers")
    ap.add_argument("--cases", default="bright1-best,red1-fast")
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--errors", default=None,
                    help=f"default: every error (linear sensor), {','.join(SENSOR_ERRORS)} "
                    "(diffractive)")  # fmt: skip
    ap.add_argument("--sensor", choices=("linear", "diffractive"), default="linear",
                    help="stage 2's sensor, the calibration run's included")  # fmt: skip
    ap.add_argument("--controllers", default=",".join(CONTROLLERS))
    ap.add_argument("--out", default="robustness-output")
    args = ap.parse_args()
    quick = not args.full
    base = {"stage2.sensor": args.sensor}
    if args.errors is None:
        args.errors = ",".join(SENSOR_ERRORS if args.sensor == "diffractive" else ERRORS)
    errors = [e.strip() for e in args.errors.split(",") if e.strip()]
    unknown = sorted(set(errors) - set(ERRORS))
    if unknown:
        ap.error(f"--errors: unknown {unknown}, expected some of {list(ERRORS)}")
    ctrls = [c.strip() for c in args.controllers.split(",") if c.strip()]
    if args.smoke:
        errors, ctrls = errors[:1], ctrls[:2]
    os.makedirs(args.out, exist_ok=True)
    warnings.simplefilter("ignore")
    t_start, cpu_start = time.perf_counter(), time.process_time()
    print(f"load average at start: {os.getloadavg()}")
    rows = []
    for case in [c.strip() for c in args.cases.split(",") if c.strip()]:
        scene = build_scene(apply_overrides(load_case(case), base), quick=quick)
        cal = calibration_seconds(scene, quick)
        gain = scene.case.stage2.gain
        t0 = time.process_time()
        nominal_design = design_inputs(scene, "standalone", gain, seconds=cal, seed=args.seed)
        banks, mar = {}, {}
        for name in ctrls:
            t1 = time.process_time()
            banks[name] = _design(case, name, quick, nominal_design, args.seed, base)
            mar[name] = _bank_margins(nominal_design.plant, banks[name])
            nom = _run(case, banks[name], args.seconds, quick, base, args.seed)
            rows.append({"case": case, "error": "nominal", "label": "", "magnitude": 0.0,
                         "controller": name, **nom})  # fmt: skip
            print(f"{case} nominal {name}: {nom} (design + run {time.process_time() - t1:.0f} s)",
                  flush=True)  # fmt: skip
        print(f"{case}: calibration and designs {time.process_time() - t0:.0f} s CPU")
        for err in errors:
            for label, mag, ov in ERRORS[err]:
                run_banks = banks
                if err == "pol-latency":  # the calibration under the error too, redesigned
                    c = apply_overrides(load_case(case), {**base, **ov})
                    design = design_inputs(build_scene(c, quick=quick), "standalone", gain,
                                           seconds=cal, seed=args.seed)  # fmt: skip
                    run_banks = {n: _design(case, n, quick, design, args.seed, base) for n in ctrls}
                for name in ctrls:
                    r = _run(case, run_banks[name], args.seconds, quick, {**base, **ov}, args.seed)
                    pred = (
                        ""
                        if err == "pol-latency"
                        else _predicted(nominal_design.plant, banks[name], mar[name], err, mag, ov)
                    )
                    rows.append({"case": case, "error": err, "label": label, "magnitude": mag,
                                 "unit": UNITS[err], "controller": name, "predicted": pred,
                                 **r})  # fmt: skip
                    print(f"{case} {err} {label} {name}: {r}", flush=True)
    _retained(rows)
    _report(rows, args.out, args.sensor)
    _targets(rows)
    print(
        f"total: {time.perf_counter() - t_start:.0f} s wall, {time.process_time() - cpu_start:.0f}"
        f" s CPU (this process; load average now {os.getloadavg()})"
    )


def _retained(rows: list[dict]) -> None:
    """``retained`` of each row: its gain over the reference of the same (case, error,
    magnitude), over the nominal one's (``nan`` for a controller no better than the reference
    on the nominal instrument: its ratio would have no meaning); ``loss``: its residual
    variance over the same controller's on the nominal instrument."""
    key = {(r["case"], r["error"], r["label"], r["controller"]): r for r in rows}
    for r in rows:
        r["retained"] = r["loss"] = math.nan
        nom = key.get((r["case"], "nominal", "", r["controller"]))
        if nom is not None and r["status"] == "ok" and nom["status"] == "ok":
            r["loss"] = (r["residual_nm"] / nom["residual_nm"]) ** 2
        ref = key.get((r["case"], r["error"], r["label"], "reference"))
        nom = key.get((r["case"], "nominal", "", r["controller"]))
        nref = key.get((r["case"], "nominal", "", "reference"))
        if None in (ref, nom, nref) or "diverged" in (r["status"], ref["status"], nom["status"],
                                                        nref["status"]):  # fmt: skip
            continue
        g_err = 1 - (r["residual_nm"] / ref["residual_nm"]) ** 2
        g_nom = 1 - (nom["residual_nm"] / nref["residual_nm"]) ** 2
        if g_nom > 0:  # no nominal gain over the reference, nothing to retain: nan
            r["retained"] = g_err / g_nom


def _targets(rows: list[dict]) -> None:
    """Issue 29's targets for the robust design (latency +-0.3 frame, loop gain +-30 %):
    no diverged run on that grid, the retained gain at its worst corner, its cost at the
    nominal point; the nominal design's and the LQG's figures at the same corners."""
    grid = ("latency", "loop gain", "gain at -0.3 frame", "gain at +0.3 frame")
    inside = {"-0.3 frame", "+0.3 frame", "x0.7", "x1.3"}
    for case in dict.fromkeys(r["case"] for r in rows):
        nominal = {
            r["controller"]: r for r in rows if r["case"] == case and r["error"] == "nominal"
        }
        for name in ("datadriven-robust", "datadriven", "lqg", "omgi"):
            runs = [r for r in rows if r["case"] == case and r["controller"] == name
                    and r["error"] in grid and (r["error"].startswith("gain at ")
                                                or r["label"] in inside)]  # fmt: skip
            if not runs:
                continue
            worst = min(runs, key=lambda r: r["retained"] if r["status"] == "ok" else -math.inf)
            bad = sum(r["status"] != "ok" for r in runs)
            line = (
                f"{case} {name}: on the set's grid ({len(runs)} runs) {bad} diverged; worst "
                f"retained {worst['retained']:.2f} ({worst['error']} {worst['label']})"
            )
            ref = nominal.get("datadriven")
            if name == "datadriven-robust" and ref and name in nominal:
                cost = (nominal[name]["residual_nm"] / ref["residual_nm"]) ** 2
                line += f"; nominal residual variance / the nominal design's {cost:.3f}"
            print(line)


def _report(rows: list[dict], out: str, sensor: str = "linear") -> None:
    fields = ["case", "error", "label", "magnitude", "controller", "status", "predicted",
              "residual_nm", "contrast_1_2", "contrast_4_6", "strehl", "retained",
              "loss"]  # fmt: skip
    with open(os.path.join(out, "robustness.csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    print(f"\n{'case':14s} {'error':18s} {'magnitude':20s} {'controller':20s} "
          f"{'resid[nm]':>9s} {'C1-2':>9s} {'C4-6':>9s} {'retained':>8s} {'loss':>6s} "
          f"{'analysis':>9s}")  # fmt: skip
    for r in rows:
        head = f"{r['case']:14s} {r['error']:18s} {r['label']:20s} {r['controller']:20s} "
        pred = r.get("predicted", "")
        if r["status"] != "ok":
            print(f"{head}{'DIVERGED':>9s} {'':>9s} {'':>9s} {'':>8s} {'':>6s} {pred:>9s}")
            continue
        print(
            f"{head}{r['residual_nm']:9.2f} {r['contrast_1_2']:9.2e} "
            f"{r['contrast_4_6']:9.2e} {r['retained']:8.2f} {r['loss']:6.2f} {pred:>9s}"
        )
    decided = [r for r in rows if r.get("predicted")]
    agree = [r for r in decided if (r["predicted"] != "unstable") == (r["status"] == "ok")]
    n_cert = sum(r["predicted"] == "certified" for r in decided)
    print(f"stability from the analysis (latency, loop gain, both): {len(agree)} of {len(decided)} "
          f"runs agree with the simulator; {n_cert} certified by the margin intervals "
          f"({sum(r['predicted'] == 'certified' and r['status'] == 'ok' for r in decided)} of "
          f"them ran stable)")  # fmt: skip
    for r in decided:
        if r not in agree:
            print(f"  disagree: {r['case']} {r['error']} {r['label']} {r['controller']}: "
                  f"predicted {r['predicted']}, run {r['status']}")  # fmt: skip
    diverged = [r for r in rows if r["status"] != "ok"]
    print(f"diverged runs: {len(diverged)} of {len(rows)}")
    for r in diverged:
        print(f"  {r['case']} {r['error']} {r['label']} {r['controller']}: {r['detail']}")
    path = os.path.join(out, "robustness.png")
    plot_robustness(rows, title=f"Gain over the reference integrator retained ({sensor} WFS)",
                    path=path)  # fmt: skip
    loss = os.path.join(out, "robustness-loss.png")
    plot_robustness(rows, value="loss",
                    title=f"Residual variance over the nominal instrument's ({sensor} WFS)",
                    path=loss)  # fmt: skip
    print(f"table: {os.path.join(out, 'robustness.csv')}; plots: {path}, {loss}")


if __name__ == "__main__":
    main()
