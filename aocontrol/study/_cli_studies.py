"""The study commands: ``sweep``, ``demo`` and ``adapt`` (:mod:`aocontrol.study.cli` parses
and dispatches to them)."""

from __future__ import annotations

import argparse
import dataclasses
import os

from aocontrol.study._cli_common import (
    RunFailed,
    UserError,
    _out_dir,
    _valid_name,
)
from aocontrol.study._cli_simulate import _check_case, write_comparison


# ----------------------------------------------------------------------------- sweep
def _sweep(args: argparse.Namespace) -> int:
    from aocontrol.study.sweep import run_sweep

    if not os.path.isfile(args.spec):
        raise UserError(f"sweep spec {args.spec!r} does not exist (expected a TOML file)")
    report = run_sweep(
        args.spec, out=args.out, scheduler=args.scheduler, progress=not args.no_progress
    )
    print(
        f"sweep {args.spec}: {len(report.ran)} run, {len(report.skipped)} already present, "
        f"{len(report.failed)} failed in {report.wall_s:.1f} s"
    )
    for hash_, error in report.failed:
        print(f"failed {hash_}: {error} (details in {os.path.join(args.out, hash_)}.error.json)")
    print(f"summary table ({len(report.table)} rows): {os.path.join(args.out, 'summary.csv')}")
    return 1 if report.failed else 0


# ----------------------------------------------------------------------------- demo
def _demo(args: argparse.Namespace) -> int:
    from aocontrol.study.demo import run_demo

    res = run_demo(args.output, fs=args.fs, latency_frames=args.latency, noise_rms=args.noise_rms)
    print(
        f"Loop: fs = {res.fs:g} Hz, latency = {res.latency_frames} frame (+1 frame WFS integration)"
    )
    header = (
        f"{'controller':34s} {'stable':>6s} {'GM-[dB]':>8s} {'GM+[dB]':>8s} {'PM[deg]':>8s} "
        f"{'MM':>6s} {'lat-[fr]':>8s} {'lat+[fr]':>8s} {'resid[nm]':>9s}"
    )
    print(header)
    print("-" * len(header))
    for name, m in res.margins.items():
        print(
            f"{name:34s} {str(m.stable):>6s} {m.gain_margin_down_db:8.2f} "
            f"{m.gain_margin_db:8.2f} {m.phase_margin:8.1f} {m.modulus_margin:6.3f} "
            f"{m.delay_margin_removed:8.2f} {m.delay_margin:8.2f} {res.residual_rms[name]:9.2f}"
        )
    print(f"{'physical limit (Wiener bound)':34s} {'':>{len(header) - 45}s} {res.wiener_rms:9.2f}")
    print(
        "GM-/GM+: how far the loop gain can fall / rise; PM: smallest over every crossover; "
        "MM: certified min |1 + GK|; lat-/lat+: latency that can be removed / added [frames]"
    )
    print(f"Rejection plot written to {res.plot_path}")
    if args.no_comparison:
        return 0
    from aocontrol.study import demo

    case = _check_case(args.case)
    print(
        f"\nShort comparison on {case} (stage 2: {demo.DEMO_STAGE2_MODES} modes, "
        f"{demo.DEMO_SECONDS:g} s exposures, scheme {demo.DEMO_SCHEME}; about a minute):"
    )
    try:
        comparison = demo.demo_comparison(
            _out_dir(args.output), case=case, progress=not args.no_progress
        )
    except RuntimeError as exc:
        raise RunFailed(f"{type(exc).__name__}: {exc}") from exc
    for line in write_comparison(comparison, args.output):
        print(line)
    return 0


# ----------------------------------------------------------------------------- adapt
def _floats(name: str, text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise UserError(f"{name} must be comma-separated numbers [s], got {text!r}") from None
    if not values or any(not v > 0 for v in values):
        raise UserError(f"{name} must be positive numbers [s], got {text!r}")
    return values


#: The adaptive study's settings (docs/adaptive.md, "Recommended update period"): update
#: period T [s], window rule, design latency [s], data-driven order and design grid (quick
#: scene, full scene).
ADAPT_PERIOD, ADAPT_WINDOW, ADAPT_LATENCY = "2", "T", 0.5
ADAPT_ORDER = {True: 2, False: 5}
ADAPT_N_GRID = {True: 24, False: None}


def _adapt_pairs(periods: tuple[float, ...], rules: list[str]) -> list[tuple[float, tuple]]:
    """(period, windows) of each call of ``run_adapt``: one call for numeric windows (every
    pair run), one per period when a window is a rule of the period (``T``, ``max(T, x)``)."""
    from aocontrol.study.adapt import window_rule

    try:
        if not any("T" in r for r in rules):
            return [(periods, tuple(window_rule(r, periods[0]) for r in rules))]
        return [((p,), tuple(dict.fromkeys(window_rule(r, p) for r in rules))) for p in periods]
    except ValueError:
        text = ",".join(rules)
        raise UserError(
            f"--window must be comma-separated seconds > 0, 'T' or 'max(T, x)', got {text!r}"
        ) from None


def _adapt(args: argparse.Namespace) -> int:
    from aocontrol.study.adapt import (
        DIAGNOSTICS,
        PREDICTORS,
        STRATEGIES,
        AdaptStudy,
        check_adapt_settings,
        run_adapt,
        scenario_drift,
    )
    from aocontrol.study.cases import load_case
    from aocontrol.study.plot import plot_adapt, use_file_backend

    # Every argument is checked before anything is written or run.
    if not args.seconds > 0:
        raise UserError(f"--seconds must be > 0 [s], got {args.seconds:g}")
    periods = _floats("--period", args.period)
    calls = _adapt_pairs(periods, args.window.split(","))
    strategies = tuple(args.strategies.split(",")) if args.strategies else STRATEGIES
    for name in strategies:
        _valid_name("strategy", name, STRATEGIES + DIAGNOSTICS + PREDICTORS)
    latency = None if args.latency < 0 else args.latency
    if latency is not None and latency >= min(periods):
        raise UserError(f"--latency {latency:g} s must be shorter than every --period")
    order = ADAPT_ORDER[bool(args.quick)] if args.order is None else args.order
    n_grid = ADAPT_N_GRID[bool(args.quick)] if args.n_grid is None else args.n_grid
    design = {k: v for k, v in (("n_grid", n_grid), ("max_iter", args.max_iter)) if v}
    adaptive = {} if args.select is None else {"select": args.select}
    case = _check_case(args.case)
    c = load_case(case)
    scenarios = args.scenario.split(",")
    for scenario in scenarios:
        scenario_drift(
            scenario, args.seconds, c.atmosphere.seeing, case_drift=c.atmosphere.drift
        )  # a case without a drift, for "case"
        for ps, ws in calls:
            check_adapt_settings(
                scenario=scenario,
                periods=ps,
                windows=ws,
                duration=args.seconds,
                strategies=strategies,
                latency=latency,
                measure_from=args.measure_from,
            )
    out = _out_dir(args.out)
    tables = {}
    for scenario in scenarios:
        rows, settings, study = [], {}, None
        for ps, ws in calls:
            study = run_adapt(
                case,
                scenario=scenario,
                periods=ps,
                windows=ws,
                duration=args.seconds,
                strategies=strategies,
                latency=latency,
                order=order,
                quick=args.quick,
                seed=args.seed,
                n_jobs=args.jobs,
                design_options=design,
                adaptive_options=adaptive,
                measure_from=args.measure_from,
            )
            seen = {(r.strategy, r.period, r.window) for r in rows}
            rows += [r for r in study.rows if (r.strategy, r.period, r.window) not in seen]
            settings = study.settings
        study = AdaptStudy(study.case, study.scenario, study.duration, tuple(rows), settings)
        table = study.table()
        print(table)
        stem = os.path.join(out, f"adapt_{study.case}_{study.scenario}")
        with open(stem + ".txt", "w") as fh:
            fh.write(table + "\n")
        path = study.save(stem + ".h5")
        print(f"table: {stem}.txt, results: {path}")
        n_kept = sum(r.n_kept_modes for r in study.rows)
        if n_kept:
            print(
                f"{n_kept} mode redesign(s) were worse than the running controller, which "
                f"stayed (per row: n_kept_modes in {path})"
            )
        tables[scenario] = [dataclasses.asdict(r) for r in study.rows]
    use_file_backend()
    png = os.path.join(out, f"adapt_{study.case}.png")
    plot_adapt(tables, title=f"{study.case}, {args.seconds:g} s", path=png)
    print(f"plot: {png}")
    return 0
