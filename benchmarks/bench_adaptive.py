"""Benchmark of adaptive control under drifting turbulence (issue 17). A script, not a test.

    python benchmarks/bench_adaptive.py [--quick] [--seconds 60] [--period 1] [--window 1]

(a) Residual over a run where the wind doubles (ramp between 20 % and 50 % of the run), on
    stage 2 of ``bright1-best`` seeing the whole turbulence: the adaptive data-driven loop
    (redesigned every T from the last W of its own telemetry) / the fixed design from the
    first window (goal <= 0.8) and / the oracle redesigned every T from the coming disturbance
    (goal <= 1.05); the adaptive modal gain for reference.
(b) Certificates and switch transients, per scenario and seed (``--scenarios``, ``--seeds``):
    uncertified banks and modes (never switched in: counted), and the residual energy in the
    50 frames after each switch / the 50 before (median and worst over switches; goal <= 1
    within noise), against the same ratio at the midpoints between switches, where no switch
    happened (the noise), with a Mann-Whitney test of the switches above it. The study prints
    the same for every redesigning strategy.
(c) Cost of one warm-started redesign of an ``--n-modes`` bank (default 540) after the wind
    went from 10 to 12 m/s (synthetic turbulence PSDs), as the adaptive loop runs it: only the
    modes predicted to gain (``--select``, ``--max-modes``), warm-started, each switched mode
    certified; against the full warm redesign (time and residual) and the cold design. Goal
    <= 10 s on 2 cores (``--jobs 2``).

The study (``--study``): every strategy at every period (``--periods``) and window rule
(``--windows``: ``1``, ``T``, ``max(T,2)``) per scenario; ``--seeds 0,1,2`` repeats it per
seed (turbulence, noise and the stochastic drift) and prints the adaptive loop's ratios per
seed with their mean and spread; ``--strategies fixed,adaptive,oracle`` runs only those;
``--measure-from 6`` averages every row's residual from the same time (rows of different
windows comparable).

The cascade study (``--cascade``): :func:`aocontrol.study.adapt.run_adapt_cascade` on
``bright1-best`` at full scale unless ``--quick``, one strategy at a time (``--strategies``
among fixed, adaptive, oracle; ``--periods``, ``--window``, ``--seconds``, ``--seeds``,
``--scheme``, ``--scenarios``' first): residual, contrast over 4-6 and ``--inner-band``
lambda/D with their ratios to the fixed design, Strehl, stage-2 clip count, CPU per strategy.

Timings are wall-clock on a shared machine: compare the ratios measured in one run.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import time
import warnings

import numpy as np

from aocontrol import loop_plant
from aocontrol.adaptive import (
    datadriven_designer,
    recoverable_gain,
    redesign,
    residual_shift,
)
from aocontrol.analysis import residual_variance
from aocontrol.controllers import IIRBank
from aocontrol.disturbance import synthetic_turbulence_psd
from aocontrol.study.adapt import run_adapt
from aocontrol.synthesis import TelemetryPSD, datadriven


def _quick_options(args: argparse.Namespace) -> dict:
    """Design options of a quick run: a coarser grid, but the cold design's iterations not
    capped (capped at 8, the first design left tip and tilt 2.5x above their converged residual
    and the warm redesigns at T = 2 s never recovered: 1.70x the oracle instead of 1.02x on
    the seeing-worsens scenario, docs/adaptive.md)."""
    return dict(n_grid=24) if args.quick else {}


def part_a(args: argparse.Namespace) -> None:
    opts = _quick_options(args)
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
    """Certificates and switch transients of the adaptive data-driven loop, per scenario and
    seed (``--scenarios``, ``--seeds``), at ``--period`` and ``--window``: the study's runs
    (:func:`aocontrol.study.adapt.run_adapt`, the case's DM) with only the adaptive strategy."""
    opts = _quick_options(args)
    for scenario in args.scenarios.split(","):
        studies = [
            run_adapt(
                "bright1-best",
                scenario=scenario,
                periods=(args.period,),
                windows=(args.window,),
                duration=args.seconds,
                strategies=("adaptive",),
                latency=args.latency,
                order=2 if args.quick else 5,
                quick=args.quick,
                seed=int(seed),
                n_jobs=args.jobs,
                design_options=opts,
            )
            for seed in args.seeds.split(",")
        ]
        _print_transients(scenario, studies)


def _emit(lines: list[str]) -> str:
    """Print ``lines`` (flushed) and return them as one text."""
    text = "\n".join(lines)
    print(text, flush=True)
    return text


def _print_transients(scenario: str, studies: list) -> str:
    """Per strategy, period, window and seed: switches, uncertified banks and modes, and the
    residual energy 50 frames after a switch / before (median, worst) against the same ratio
    where no switch happened (median, worst) and the test's p-value (text)."""
    lines = [
        f"(b) {scenario}: switch transients, 50 frames after / before (reference: midpoints "
        "between switches); p: Mann-Whitney, switches above the reference",
        f"{'strategy':<11} {'T':>4} {'W':>4} {'seed':>4} {'switch':>6} {'banks':>5} "
        f"{'modes':>5} {'median':>7} {'worst':>7} {'ref med':>7} {'ref max':>7} {'p':>7}",
    ]
    for study in studies:
        for r in study.rows:
            if r.strategy == "fixed":
                continue
            lines.append(
                f"{r.strategy:<11} {r.period:>4g} {r.window:>4g} {study.settings.get('seed'):>4} "
                f"{r.n_switches:>6d} {r.n_rejected_banks:>5d} {r.n_rejected_modes:>5d} "
                f"{r.transient_median:>7.3f} {r.transient_worst:>7.3f} "
                f"{r.reference_median:>7.3f} {r.reference_worst:>7.3f} {r.transient_p:>7.3f}"
            )
    return _emit(lines)


def _cpu_seconds() -> float:
    """CPU time [s] of this process and its live children (the synthesis' workers)."""
    import psutil

    me = psutil.Process()
    total = 0.0
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
        except psutil.Error:
            continue
        total += t.user + t.system
    return total


def _timed(fun):
    """``fun()`` and its wall and CPU time [s]."""
    c, t = _cpu_seconds(), time.perf_counter()
    out = fun()
    return out, time.perf_counter() - t, _cpu_seconds() - c


# (c) settings swept by --sweep: (label, rank, select, max_modes, warm n_grid, warm max_iter).
SWEEP = (
    ("every mode, 64 pts, 8 it", None, None, None, 64, 8),
    ("every mode, 32 pts, 1 it", None, None, None, 32, 1),
    ("shift, 40 modes, 32 pts, 1 it", "shift", 1.0, 40, 32, 1),
    ("bound, 40 modes, 32 pts, 1 it", "bound", 1.0, 40, 32, 1),
    ("bound, 40 modes, 64 pts, 2 it", "bound", 1.0, 40, 64, 2),
    ("bound, 80 modes, 32 pts, 1 it", "bound", 1.0, 80, 32, 1),
    ("bound, 120 modes, 32 pts, 1 it", "bound", 1.0, 120, 32, 1),
    ("bound, 230 modes, 32 pts, 1 it", "bound", 1.0, 230, 32, 1),
    ("shift, 230 modes, 32 pts, 1 it", "shift", 1.0, 230, 32, 1),
    ("every mode, 24 pts, 1 it", None, None, None, 24, 1),
)


def part_c(args: argparse.Namespace) -> None:
    """One redesign of an ``--n-modes`` bank after the wind went from 10 to 12 m/s, as the
    adaptive loop runs it (:func:`aocontrol.adaptive.redesign`: select, warm design, certify
    every switched mode), against the full warm redesign and the cold design. With
    ``--sweep``, every setting of :data:`SWEEP`: wall and CPU time (this process and its
    workers), and the share of the full redesign's gain it recovers on the new PSD."""
    fs, n = 3000.0, args.n_modes
    plant = loop_plant(fs, 0.83)
    f = np.linspace(0.0, fs / 2, 513)
    noise = np.full(n, 2.0 * 2.0**2 / fs)  # 2 nm RMS per frame, white

    # --every k: the modes 0, k, 2k... of the n-mode turbulence (with --start-stride 1, a
    # running bank designed exactly on the old PSD: the gain measured is the drift's alone).
    keep = np.arange(0, n, args.every)
    n = keep.size
    noise = noise[keep]

    def tel(wind: float) -> TelemetryPSD:
        psd = synthetic_turbulence_psd(f, args.n_modes, wind_speed=wind, fs=fs)[keep]
        return TelemetryPSD(f, psd, noise, np.zeros((8, n)), psd, fs, (0.8, 1.0))

    before, after = tel(10.0), tel(12.0)
    # The running bank: the cold design of every --start-stride-th mode, each used by its
    # neighbours up to the next (a certified controller of the same plant; 1: every mode).
    cache = None
    if args.cache:
        cache = os.path.join(
            args.cache, f"bench_adaptive_c_{args.n_modes}_{args.every}_{args.start_stride}.npz"
        )
    rep = np.arange(0, n, args.start_stride)
    if cache and os.path.exists(cache):
        z = np.load(cache)
        b0, a0, cold = z["b"], z["a"], float(z["cold"])
    else:
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
        b0, a0 = first.controller.b, first.controller.a
        if cache:
            np.savez(cache, b=b0, a=a0, cold=cold)
    who = np.arange(n) // args.start_stride
    bank = IIRBank(b0[np.minimum(who, b0.shape[0] - 1)], a0[np.minimum(who, a0.shape[0] - 1)], fs)
    print(
        f"(c) {n} modes, wind 10 -> 12 m/s, {args.jobs or 'all'} jobs: cold design "
        f"{cold:.1f} s{' (extrapolated)' if args.start_stride > 1 else ''}",
        flush=True,
    )
    # The loop's record of each mode's design, on its design estimate: rho = J / v
    # (rank="shift") and eta = J / B (rank="bound").
    ratios = {
        "shift": residual_shift(bank, plant, before, np.full(n, np.nan))[1],
        "bound": recoverable_gain(bank, plant, before, np.full(n, np.nan))[1],
    }

    def resid(b: IIRBank) -> float:
        return float(residual_variance(plant, b, f, after.psd, noise).sum())

    def run(rank, select, max_modes, n_grid, max_iter):
        design = datadriven_designer(
            order=5, n_jobs=args.jobs, warm_n_grid=n_grid, warm_max_iter=max_iter
        )
        return _timed(
            lambda: redesign(
                plant,
                bank,
                after,
                design,
                modulus_margin=0.5,
                last_ratio=None if rank is None else ratios[rank],
                select=select,
                max_modes=max_modes,
                rank=rank or "bound",
            )
        )

    kept = resid(bank)
    sweep = SWEEP
    if args.only:
        sweep = tuple(SWEEP[int(i)] for i in args.only.split(","))
    settings = (
        sweep
        if args.sweep
        else (
            ("full warm redesign", None, None, None, 64, 8),
            (
                f"rank {args.rank}, select {args.select}, max_modes {args.max_modes}, "
                f"{args.warm_n_grid} pts, {args.warm_max_iter} it",
                args.rank,
                args.select,
                args.max_modes,
                args.warm_n_grid,
                args.warm_max_iter,
            ),
        )
    )
    rows = []
    for label, rank, select, max_modes, n_grid, max_iter in settings:
        if max_modes is not None and args.every > 1:  # SWEEP's budgets are for --n-modes
            max_modes = max(1, round(max_modes * n / args.n_modes))
            label = f"{label} -> {max_modes}"
        up, wall, cpu = run(rank, select, max_modes, n_grid, max_iter)
        rows.append((label, up, wall, cpu, resid(up.bank)))
        print(
            f"(c) {label}: {wall:.1f} s wall, {cpu:.1f} s CPU, "
            f"{int(up.certified.sum())} modes switched, residual {rows[-1][-1]:.5g}",
            flush=True,
        )
    full = rows[0][-1]
    print(f"(c) residual on the new PSD, summed [nm^2]: kept {kept:.5g}, {rows[0][0]} {full:.5g}")
    print(f"{'setting':<34} {'wall s':>7} {'CPU s':>7} {'modes':>6} {'resid':>9} {'gain %':>7}")
    for label, up, wall, cpu, j in rows:
        share = 100 * (kept - j) / max(kept - full, 1e-30)
        print(
            f"{label:<34} {wall:>7.1f} {cpu:>7.1f} {int(up.certified.sum()):>6d} {j:>9.5g} "
            f"{share:>7.1f}"
        )


def _options(text: str | None) -> dict:
    """``key=value,...`` as a dict of numbers (``None``, ``none``: None)."""
    out: dict = {}
    for item in filter(None, (text or "").split(",")):
        key, _, value = item.partition("=")
        value = value.strip()
        if value.lower() == "none":
            out[key.strip()] = None
        else:
            out[key.strip()] = float(value) if any(c in value for c in ".eE") else int(value)
    return out


def _print_seed_summary(scenario: str, studies: list, fixed_window: float | None) -> str:
    """The per-seed ratios of the adaptive loop and their mean and spread (text)."""
    from aocontrol.study.adapt import seed_summary

    ref = "same W" if fixed_window is None else f"W = {fixed_window:g} s"
    lines = [f"{scenario}: adaptive / fixed ({ref}) and adaptive / oracle over seeds"]
    for r in seed_summary(studies, fixed_window=fixed_window):
        per = " ".join(f"{a:.3f}/{b:.3f}" for a, b in zip(r["fixed"], r["oracle"], strict=True))
        lines.append(
            f"T {r['period']:g} W {r['window']:g}: /fixed {r['fixed_mean']:.3f} "
            f"+- {r['fixed_std']:.3f} [{min(r['fixed']):.3f}, {max(r['fixed']):.3f}], "
            f"/oracle {r['oracle_mean']:.3f} +- {r['oracle_std']:.3f} "
            f"[{min(r['oracle']):.3f}, {max(r['oracle']):.3f}]; per seed "
            f"{r['seeds']}: {per}"
        )
    return _emit(lines)


def _design_args(args: argparse.Namespace, seed: int, opts: dict) -> dict:
    """The design arguments shared by the study and the cascade study."""
    return dict(
        latency=args.latency,
        order=2 if args.quick else 5,
        quick=args.quick,
        seed=seed,
        n_jobs=args.jobs,
        design_options=opts,
        adaptive_options={"select": args.select} if args.select else {},
    )


def study(args: argparse.Namespace) -> None:
    """The study (issue 17, part 3): the strategies at every period, per scenario and seed,
    one period at a time (longest first) so that a partial run still gives whole rows; the
    rows of each scenario (and seed, unless the only seed is 0) as HDF5
    (:meth:`AdaptStudy.save`) and one plot. With several ``--seeds`` (drift realisation,
    turbulence and noise), the adaptive loop's ratios per seed and their mean and spread.
    ``--windows`` are rules (:func:`aocontrol.study.adapt.window_rule`: ``1``, ``T``,
    ``max(T,2)``); the fixed design is run once per window."""
    import dataclasses
    import os

    from aocontrol.study.adapt import AdaptStudy, window_rule
    from aocontrol.study.plot import plot_adapt, use_file_backend

    os.makedirs(args.out, exist_ok=True)
    opts = {**_quick_options(args), **_options(args.design_options)}
    periods = sorted((float(x) for x in args.periods.split(",")), reverse=True)
    rules = [x for x in re.split(r",(?![^(]*\))", args.windows) if x.strip()]
    seeds = [int(x) for x in args.seeds.split(",")]
    chosen = tuple(x.strip() for x in args.strategies.split(","))
    tables = {}
    use_file_backend()
    for scenario in args.scenarios.split(","):
        studies = []
        for seed in seeds:
            rows: list = []
            fixed_done: set = set()
            tag = "" if seeds == [0] else f"_seed{seed}"
            for period in periods:
                windows = tuple(dict.fromkeys(window_rule(r, period) for r in rules))
                new = [w for w in windows if w not in fixed_done] if "fixed" in chosen else []
                fixed_done.update(new)
                others = tuple(s for s in chosen if s != "fixed")
                calls = [(others, windows)] if others else []
                if new:  # first: the same order of rows as one call with both
                    calls.insert(0, (("fixed",), tuple(new)))
                for strategies, ws in calls:
                    part = run_adapt(
                        "bright1-best",
                        scenario=scenario,
                        periods=(period,),
                        windows=ws,
                        duration=args.seconds,
                        strategies=strategies,
                        **_design_args(args, seed, opts),
                        measure_from=args.measure_from,
                    )
                    rows.extend(part.rows)
                    whole = AdaptStudy(
                        part.case, scenario, part.duration, tuple(rows), part.settings
                    )
                    stem = os.path.join(args.out, f"adapt_{part.case}_{scenario}{tag}")
                    whole.save(stem + ".h5")
                    with open(stem + ".txt", "w") as fh:
                        fh.write(whole.table() + "\n")
                    print(whole.table().splitlines()[-len(part.rows) :], flush=True)
                    tables[scenario + tag] = [dataclasses.asdict(r) for r in rows]
                    plot_adapt(
                        tables,
                        title=f"{part.case}, {args.seconds:g} s",
                        path=os.path.join(args.out, f"adapt_{part.case}.png"),
                    )
            studies.append(whole)
        text = _print_transients(scenario, studies)
        with open(os.path.join(args.out, f"adapt_transients_{scenario}.txt"), "w") as fh:
            fh.write(text + "\n")
        if len(seeds) > 1:
            # Every ratio to the fixed design of the first rule if it is a number of seconds.
            first = rules[0].strip()
            fixed_window = float(first) if first.replace(".", "", 1).isdigit() else None
            text = _print_seed_summary(scenario, studies, fixed_window)
            with open(os.path.join(args.out, f"adapt_seeds_{scenario}.txt"), "w") as fh:
                fh.write(text + "\n")


def cascade(args: argparse.Namespace) -> None:
    """The cascade study (issue 17): every strategy of ``--strategies`` run on its own (its
    CPU time: this process and its design workers), the rows of each seed as one table."""
    from aocontrol.study.adapt import AdaptCascadeStudy, run_adapt_cascade

    periods = tuple(float(x) for x in args.periods.split(","))
    band = tuple(float(x) for x in args.inner_band.split(","))
    opts = {**_quick_options(args), **_options(args.design_options)}
    for seed in (int(x) for x in args.seeds.split(",")):
        rows: list = []
        cpu: list = []
        for strategy in (x.strip() for x in args.strategies.split(",")):
            part, wall, c = _timed(
                lambda strategy=strategy, seed=seed: run_adapt_cascade(
                    "bright1-best",
                    scenario=args.scenarios.split(",")[0],
                    periods=periods,
                    window=args.window,
                    duration=args.seconds,
                    strategies=(strategy,),
                    scheme=args.scheme,
                    **_design_args(args, seed, opts),
                    inner_band=band,
                )
            )
            rows.extend(part.rows)
            cpu.append(f"{strategy} {c:.0f} s CPU ({wall:.0f} s wall)")
            print(f"seed {seed}: {cpu[-1]}, load {os.getloadavg()[0]:.1f}", flush=True)
        whole = AdaptCascadeStudy(
            part.case, part.scenario, part.scheme, part.duration, tuple(rows), part.settings
        )
        print(f"seed {seed}, inner band {band[0]:g}-{band[1]:g} lambda/D", flush=True)
        print(whole.table(), flush=True)
        print("; ".join(cpu), flush=True)


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
    parser.add_argument("--rank", default="bound", help="(c): ranking of the selected modes")
    parser.add_argument("--warm-n-grid", type=int, default=32, help="(c): warm design grid")
    parser.add_argument("--warm-max-iter", type=int, default=1, help="(c): warm iterations")
    parser.add_argument("--sweep", action="store_true", help="(c): every setting of SWEEP")
    parser.add_argument(
        "--only", default=None, help="(c): indices of SWEEP to run (the first is the reference)"
    )
    parser.add_argument(
        "--every", type=int, default=1, help="(c): only the modes 0, k, 2k... of --n-modes"
    )
    parser.add_argument("--cache", default=None, help="(c): folder caching the start bank")
    parser.add_argument("--parts", default="abc", help="parts to run, e.g. 'ac'")
    parser.add_argument("--study", action="store_true", help="run the study instead of parts")
    parser.add_argument("--periods", default="1,2,5,10,30,60", help="study: periods T [s]")
    parser.add_argument(
        "--windows", default="1", help="study: window rules W [s], e.g. '1,2,T,max(T,2)'"
    )
    parser.add_argument("--seeds", default="0", help="study: seeds, e.g. '0,1,2'")
    parser.add_argument(
        "--strategies",
        default="fixed,adaptive,oracle,modal-gain,lqg",
        help="study: strategies, e.g. 'fixed,adaptive,oracle'",
    )
    parser.add_argument(
        "--measure-from",
        type=float,
        default=None,
        help="study: residual averaged from this time [s] for every row (default: own window)",
    )
    parser.add_argument(
        "--design-options",
        default=None,
        help="study: more datadriven_designer options, e.g. 'warm_max_iter=32,warm_n_grid=48'",
    )
    parser.add_argument(
        "--scenarios", default="wind-doubles,seeing-worsens", help="study: scenarios"
    )
    parser.add_argument("--out", default="adapt-study", help="study: output folder")
    parser.add_argument("--cascade", action="store_true", help="run the cascade study")
    parser.add_argument("--scheme", default="standalone", help="cascade: standalone or dcao")
    parser.add_argument(
        "--inner-band", default="1,2", help="cascade: second contrast annulus [lambda/D]"
    )
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    logging.disable(logging.WARNING)
    if args.study:
        study(args)
        return
    if args.cascade:
        cascade(args)
        return
    for part, fun in (("a", part_a), ("b", part_b), ("c", part_c)):
        if part in args.parts:
            fun(args)


if __name__ == "__main__":
    main()
