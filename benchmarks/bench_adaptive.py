"""Benchmark of adaptive control under drifting turbulence (issue 17). A script, not a test.

    python benchmarks/bench_adaptive.py [--quick] [--seconds 60] [--period 1] [--window 1]

(a) Residual over a run where the wind doubles (ramp between 20 % and 50 % of the run), on
    stage 2 of ``bright1-best`` seeing the whole turbulence: the adaptive data-driven loop
    (redesigned every T from the last W of its own telemetry) / the fixed design from the
    first window (goal <= 0.8) and / the oracle redesigned every T from the coming disturbance
    (goal <= 1.05); the adaptive modal gain for reference.
(b) Certificates and switch transients: uncertified banks and modes (never switched in:
    counted), and the residual energy in the 50 frames after each switch / the 50 before,
    pooled over switches (goal <= 1 within noise).
(c) Cost of one warm-started redesign of an ``--n-modes`` bank (default 540) after the wind
    went from 10 to 12 m/s (synthetic turbulence PSDs), as the adaptive loop runs it: only the
    modes predicted to gain (``--select``, ``--max-modes``), warm-started, each switched mode
    certified; against the full warm redesign (time and residual) and the cold design. Goal
    <= 10 s on 2 cores (``--jobs 2``).

Timings are wall-clock on a shared machine: compare the ratios measured in one run.
"""

from __future__ import annotations

import argparse
import logging
import time
import warnings

import numpy as np

from aocontrol import loop_plant
from aocontrol.adaptive import (
    AdaptiveController,
    datadriven_designer,
    redesign,
    residual_shift,
)
from aocontrol.analysis import residual_variance
from aocontrol.controllers import IIRBank, Integrator
from aocontrol.disturbance import synthetic_turbulence_psd
from aocontrol.sim.loop import ModalTimeSeries, Stage, run_loop
from aocontrol.study.adapt import drifting_disturbance, run_adapt, scenario_drift
from aocontrol.study.scene import build_scene
from aocontrol.synthesis import TelemetryPSD, datadriven


def part_a(args: argparse.Namespace) -> None:
    opts = dict(n_grid=24, max_iter=8) if args.quick else {}
    study = run_adapt(
        "bright1-best",
        scenario="wind-doubles",
        periods=(args.period,),
        windows=(args.window,),
        duration=args.seconds,
        strategies=("fixed", "adaptive", "oracle", "modal-gain"),
        latency=args.latency,
        order=2 if args.quick else 5,
        quick=args.quick,
        n_jobs=args.jobs,
        design_options=opts,
    )
    print(study.table())
    a, f, o = (study.row(s).residual for s in ("adaptive", "fixed", "oracle"))
    print(
        f"(a) adaptive / fixed = {a / f:.3f} (goal <= 0.8); adaptive / oracle = {a / o:.3f} "
        "(goal <= 1.05)"
    )
    r = study.row("adaptive")
    print(
        f"(b) uncertified banks {r.n_rejected_banks}, modes kept by certificate "
        f"{r.n_rejected_modes} (none switched in by construction)"
    )


def part_b(args: argparse.Namespace) -> None:
    """Switch transients of the adaptive data-driven loop on the same scenario."""
    scene = build_scene("bright1-best", quick=args.quick)
    st = scene.stage2
    duration = args.seconds
    n = int(round(duration * st.fs))
    d = drifting_disturbance(
        scene, scenario_drift("wind-doubles", duration, scene.case.atmosphere.seeing), n, 0
    )
    opts = dict(n_grid=24, max_iter=8) if args.quick else {}
    ctrl = AdaptiveController(
        Integrator(st.spec.gain, fs=st.fs, n_modes=st.n_modes),
        st.plant,
        datadriven_designer(order=2 if args.quick else 5, n_jobs=args.jobs, **opts),
        period=args.period,
        window=args.window,
        latency=args.latency,
    )
    res = run_loop(
        Stage(ctrl, st.sensor, st.spec.latency_frames),
        ModalTimeSeries(d, st.fs),
        n,
        rng=1,
        record=("residuals",),
    )
    e = res.telemetry["residuals"].astype(float)
    ks = [k for k in ctrl.last_run.switch_frames if 50 <= k <= n - 50]
    before = np.mean([np.sum(e[k - 50 : k] ** 2) for k in ks])
    after = np.mean([np.sum(e[k : k + 50] ** 2) for k in ks])
    print(
        f"(b) {len(ks)} switches: residual energy 50 frames after / before = "
        f"{after / before:.3f} (goal <= 1 within noise)"
    )


def part_c(args: argparse.Namespace) -> None:
    """One redesign of an ``--n-modes`` bank after the wind went from 10 to 12 m/s, as the
    adaptive loop runs it (:func:`aocontrol.adaptive.redesign`: select, warm design, certify
    every switched mode), against the full warm redesign and the cold design."""
    fs, n = 3000.0, args.n_modes
    plant = loop_plant(fs, 0.83)
    f = np.linspace(0.0, fs / 2, 513)
    noise = np.full(n, 2.0 * 2.0**2 / fs)  # 2 nm RMS per frame, white

    def tel(wind: float) -> TelemetryPSD:
        psd = synthetic_turbulence_psd(f, n, wind_speed=wind, fs=fs)
        return TelemetryPSD(f, psd, noise, np.zeros((8, n)), psd, fs, (0.8, 1.0))

    before, after = tel(10.0), tel(12.0)
    # The running bank: the cold design of every --start-stride-th mode, each used by its
    # neighbours up to the next (a certified controller of the same plant; 1: every mode).
    rep = np.arange(0, n, args.start_stride)
    t = time.perf_counter()
    first = datadriven(
        plant,
        f,
        before.psd[rep],
        noise_psd=noise[rep],
        order=5,
        n_jobs=args.jobs,
        progress=False,
    )
    cold = (time.perf_counter() - t) * n / rep.size
    who = np.arange(n) // args.start_stride
    bank = IIRBank(first.controller.b[who], first.controller.a[who], fs)
    # The loop's record of each mode's design: rho = J / v on its design estimate.
    _, ratio = residual_shift(bank, plant, before, np.full(n, np.nan))
    design = datadriven_designer(order=5, n_jobs=args.jobs)
    t = time.perf_counter()
    sel = redesign(
        plant,
        bank,
        after,
        design,
        modulus_margin=0.5,
        last_ratio=ratio,
        select=args.select,
        max_modes=args.max_modes,
    )
    warm = time.perf_counter() - t
    print(
        f"(c) {n} modes, wind 10 -> 12 m/s, {args.jobs or 'all'} jobs: cold design "
        f"{cold:.1f} s{' (extrapolated)' if args.start_stride > 1 else ''}; selected redesign "
        f"(select={args.select}, max_modes={args.max_modes}) {warm:.1f} s "
        f"({int(sel.selected.sum())} modes redesigned, {int(sel.certified.sum())} switched; "
        "goal <= 10 s)",
        flush=True,
    )
    if args.no_full:
        return
    t = time.perf_counter()
    full = redesign(plant, bank, after, design, modulus_margin=0.5)
    warm_full = time.perf_counter() - t
    j = {
        name: float(residual_variance(plant, b, f, after.psd, noise).sum())
        for name, b in (("kept", bank), ("selected", sel.bank), ("full", full.bank))
    }
    forgone = (j["selected"] - j["full"]) / max(j["kept"] - j["full"], 1e-30)
    print(f"(c) full warm redesign {warm_full:.1f} s ({int(full.certified.sum())} switched)")
    print(
        f"(c) residual on the new PSD, summed [nm^2]: kept {j['kept']:.4g}, selected "
        f"{j['selected']:.4g}, full {j['full']:.4g}; selected / full = "
        f"{j['selected'] / j['full']:.4f}; share of the full redesign's gain forgone "
        f"{forgone:.3f}; warm / cold = {warm / cold:.3f}"
    )


def study(args: argparse.Namespace) -> None:
    """The study (issue 17, part 3): every strategy at every period, per scenario, one
    period at a time (longest first) so that a partial run still gives whole rows; the
    rows of each scenario as HDF5 (:meth:`AdaptStudy.save`) and one plot."""
    import dataclasses
    import os

    from aocontrol.study.adapt import AdaptStudy
    from aocontrol.study.plot import plot_adapt, use_file_backend

    os.makedirs(args.out, exist_ok=True)
    opts = dict(n_grid=24, max_iter=8) if args.quick else {}
    periods = sorted((float(x) for x in args.periods.split(",")), reverse=True)
    windows = tuple(float(x) for x in args.windows.split(","))
    tables = {}
    use_file_backend()
    for scenario in args.scenarios.split(","):
        rows: list = []
        for i, period in enumerate(periods):
            strategies = ("adaptive", "oracle", "modal-gain", "lqg")
            part = run_adapt(
                "bright1-best",
                scenario=scenario,
                periods=(period,),
                windows=windows,
                duration=args.seconds,
                strategies=(("fixed",) if i == 0 else ()) + strategies,
                latency=args.latency,
                order=2 if args.quick else 5,
                quick=args.quick,
                n_jobs=args.jobs,
                design_options=opts,
                adaptive_options={"select": args.select} if args.select else {},
            )
            rows.extend(part.rows)
            whole = AdaptStudy(part.case, scenario, part.duration, tuple(rows), part.settings)
            stem = os.path.join(args.out, f"adapt_{part.case}_{scenario}")
            whole.save(stem + ".h5")
            with open(stem + ".txt", "w") as fh:
                fh.write(whole.table() + "\n")
            print(whole.table().splitlines()[-len(part.rows) :], flush=True)
            tables[scenario] = [dataclasses.asdict(r) for r in rows]
            plot_adapt(
                tables,
                title=f"{part.case}, {args.seconds:g} s",
                path=os.path.join(args.out, f"adapt_{part.case}.png"),
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="24 modes, short runs")
    parser.add_argument("--seconds", type=float, default=60.0, help="simulated time [s]")
    parser.add_argument("--period", type=float, default=1.0, help="update period T [s]")
    parser.add_argument("--window", type=float, default=1.0, help="telemetry window W [s]")
    parser.add_argument("--latency", type=float, default=0.5, help="design latency [s]")
    parser.add_argument("--n-modes", type=int, default=540, help="modes of part (c)")
    parser.add_argument("--jobs", type=int, default=None, help="worker processes per design")
    parser.add_argument(
        "--select", type=float, default=0.9, help="share of the residual shift redesigned"
    )
    parser.add_argument("--max-modes", type=int, default=None, help="mode budget of (c)")
    parser.add_argument(
        "--start-stride", type=int, default=1, help="(c): cold-design every k-th mode only"
    )
    parser.add_argument("--no-full", action="store_true", help="(c): no full warm redesign")
    parser.add_argument("--parts", default="abc", help="parts to run, e.g. 'ac'")
    parser.add_argument("--study", action="store_true", help="run the study instead of parts")
    parser.add_argument("--periods", default="1,2,5,10,30,60", help="study: periods T [s]")
    parser.add_argument("--windows", default="1", help="study: windows W [s]")
    parser.add_argument(
        "--scenarios", default="wind-doubles,seeing-worsens", help="study: scenarios"
    )
    parser.add_argument("--out", default="adapt-study", help="study: output folder")
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    logging.disable(logging.WARNING)
    if args.study:
        study(args)
        return
    for part, fun in (("a", part_a), ("b", part_b), ("c", part_c)):
        if part in args.parts:
            fun(args)


if __name__ == "__main__":
    main()
