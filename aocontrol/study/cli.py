"""Command line of aocontrol: science cases, simulations, comparisons, designs, sweeps.

Commands (``aocontrol COMMAND --help`` for each)::

    aocontrol cases                         the science cases and their parameters
    aocontrol run CASE --controller C --scheme S [--seconds S] [--seed N] [--out DIR]
    aocontrol compare CASE [--quick] [--out DIR]
    aocontrol design TELEMETRY [--loop NAME] [--fs F --latency L] [--controller datadriven]
                     [--order 5] [--out FILE.h5|.fits|.csv] [--export FILE.fits|.csv]
                     [--aot-out FILE] [--unit U] [--command-sign -1] [--override-metadata]
    aocontrol sweep SPEC.toml [--scheduler ADDRESS] [--out DIR]
    aocontrol adapt CASE [--scenario S] [--period 2] [--window T] [--seconds 60] [--quick]
    aocontrol demo [--output DIR]

Exit status 0 on success, 2 for a user error (bad name, unreadable file: one line on stderr,
no traceback), 1 when a run fails (e.g. a diverging loop).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from aocontrol.study._cli_common import (  # noqa: F401 - UserError is part of this module's API
    RUN_SCHEMES,
    RunFailed,
    UserError,
    _format_table,
    _out_dir,
    _plot_module,
    _valid_name,
    run_controller_names,
)
from aocontrol.study._cli_design import (  # noqa: F401 - read_telemetry is part of this API
    DESIGN_DESCRIPTION,
    _design,
    _design_report,
    design_arguments,
    read_telemetry,
)

__all__ = ["main", "UserError", "read_telemetry", "write_comparison"]

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- cases
def _cases(args: argparse.Namespace) -> int:
    from aocontrol.study.cases import list_cases, load_case

    rows = []
    for name in list_cases():
        c = load_case(name)
        rows.append(
            {
                "name": c.name,
                "seeing": c.atmosphere.seeing,
                "tau0_ms": c.atmosphere.tau0 * 1e3,
                "G": c.star.G,
                "J": c.star.J,
                "s1": f"{c.stage1.fs:g} Hz / {c.stage1.n_modes}",
                "s2": f"{c.stage2.fs:g} Hz / {c.stage2.n_modes}",
                "vib": "yes" if c.vibration is not None else "",
                "title": c.title,
            }
        )
    print(
        _format_table(
            rows,
            [
                ("name", "case", ""),
                ("seeing", 'seeing["]', ".2f"),
                ("tau0_ms", "tau0[ms]", ".1f"),
                ("G", "G[mag]", ".1f"),
                ("J", "J[mag]", ".1f"),
                ("s1", "stage 1 [fs/modes]", ""),
                ("s2", "stage 2 [fs/modes]", ""),
                ("vib", "vibration", ""),
                ("title", "title", ""),
            ],
        )
    )
    return 0


# ----------------------------------------------------------------------------- run
def _compare_module() -> Any:
    try:
        from aocontrol.study import compare
    except ImportError as exc:  # pragma: no cover - the module ships with the package
        raise RunFailed(f"the case comparison is not available: {exc}") from exc
    return compare


def _check_case(name: str) -> str:
    from aocontrol.study.cases import list_cases

    if os.path.exists(name) and name.endswith(".toml"):
        return name  # a case file of the user's
    return _valid_name("case", name, list_cases())


def _summary_line(label: str, summary: Any) -> str:
    get = summary.get if isinstance(summary, dict) else lambda k: getattr(summary, k, None)
    parts = []
    for key, text, fmt in (
        ("strehl", "Strehl", ".3f"),
        ("mean_contrast_4_6", "contrast(4-6 l/D)", ".2e"),
        ("residual_rms_nm", "residual", ".1f"),
    ):
        value = get(key)
        if value is not None:
            parts.append(
                f"{text} {format(float(value), fmt)}"
                + (" nm RMS" if key == "residual_rms_nm" else "")
            )
    return f"{label}: " + ", ".join(parts)


def _run(args: argparse.Namespace) -> int:
    from aocontrol.study.results import save_result

    compare = _compare_module()
    case = _check_case(args.case)
    controller = _valid_name("controller", args.controller, run_controller_names())
    scheme = _valid_name("scheme", args.scheme, compare.SCHEMES)
    if args.seconds is not None and not args.seconds > 0:
        raise UserError(f"--seconds must be > 0, got {args.seconds}")
    out = _out_dir(args.out)
    options = {} if args.seconds is None else {"seconds": args.seconds}
    try:
        outcome = compare.run_configuration(
            case,
            controller=controller,
            scheme=scheme,
            seed=args.seed,
            overrides=_settings(args.set),
            quick=args.quick,
            progress=not args.no_progress,
            sensor=args.sensor,
            optical_gain=args.optical_gain,
            **options,
        )
    except RuntimeError as exc:
        raise RunFailed(f"{type(exc).__name__}: {exc}") from exc
    stem = f"{os.path.splitext(os.path.basename(case))[0]}-{controller}-{scheme}-seed{args.seed}"
    path = save_result(
        outcome.result,
        os.path.join(out, stem + ".h5"),
        settings=outcome.settings,
        telemetry=args.telemetry,
    )
    plot = _plot_module()
    pngs = _result_plots(plot, {stem: outcome.result}, out, stem)
    print(_summary_line(f"{stem}", outcome.summary))
    print(f"results file: {path}")
    for p in pngs:
        print(f"plot: {p}")
    return 0


def _last_stage(result: Any) -> Any:
    stages = getattr(result, "stages", None)
    return stages[-1] if stages is not None else result


def _result_plots(plot: Any, results: dict[str, Any], out: str, stem: str) -> list[str]:
    """Contrast curve and residual PSD plots of ``run`` (one or more results, by label)."""
    pngs = []
    with_science = {k: r for k, r in results.items() if getattr(r, "science", None) is not None}
    if with_science:
        path = os.path.join(out, f"{stem}_contrast.png")
        plot.plot_contrast(None, with_science, title=stem, path=path)
        pngs.append(path)
    psds = {}
    freqs = None
    for label, r in results.items():
        last = _last_stage(r)
        if "residuals" in last.telemetry:
            freqs, p = last.psd("residuals")
            psds[label] = p
            if "disturbance" in last.telemetry and "open loop" not in psds:
                psds = {"open loop": last.psd("disturbance")[1], **psds}
    if psds:
        path = os.path.join(out, f"{stem}_residual_psd.png")
        plot.plot_residual_psd(
            freqs, psds, title=f"{stem}: residual PSD (sum over modes)", path=path
        )
        pngs.append(path)
    return pngs


# ----------------------------------------------------------------------------- compare
def _settings(items: list[str]) -> dict | None:
    """``--set KEY=VALUE`` items as case overrides (numbers as numbers, the rest strings);
    the case loader checks each key and value."""
    out: dict = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UserError(f"--set takes KEY=VALUE (e.g. stage2.latency_error=0.3), got {item!r}")
        value = value.strip()
        try:
            out[key.strip()] = int(value) if value.lstrip("-").isdigit() else float(value)
        except ValueError:
            out[key.strip()] = value.strip("'\"")
    return out or None


def _compare(args: argparse.Namespace) -> int:
    compare = _compare_module()
    case = _check_case(args.case)
    out = _out_dir(args.out)
    try:
        comparison = compare.compare_case(
            case,
            overrides=_settings(args.set),
            quick=args.quick,
            results_dir=out,
            progress=not args.no_progress,
            sensor=args.sensor,
            optical_gain=args.optical_gain,
        )
    except RuntimeError as exc:
        raise RunFailed(f"{type(exc).__name__}: {exc}") from exc
    for line in write_comparison(comparison, out):
        print(line)
    return 0


def write_comparison(comparison: Any, out: str) -> list[str]:
    """Write a case comparison's table (text and CSV) and plots; return the report lines.

    Parameters
    ----------
    comparison : CaseComparison
        Result of :func:`aocontrol.study.compare.compare_case` (``cells`` with their
        results files when it was given ``results_dir``).
    out : str
        Folder of the files (exists).

    Returns
    -------
    list of str
        The table, the reference gains and one line per file written.
    """
    import csv

    name = comparison.case
    table = comparison.table()
    lines = [table, ""]
    gains = ", ".join(f"{k} {v:g}" for k, v in comparison.reference_gains.items())
    lines.append(f"reference gain (scan for the best 4-6 lambda/D contrast): {gains}")
    txt = os.path.join(out, f"{name}_table.txt")
    with open(txt, "w", encoding="utf-8") as fh:
        fh.write(table + "\n")
    fields = (
        "scheme",
        "controller",
        "strehl",
        "mean_contrast_4_6",
        "residual_rms_nm",
        "residual_rms_se_nm",
        "predicted_rms_nm",
        "predicted_rms_se_nm",
        "path",
    )
    csv_path = os.path.join(out, f"{name}_table.csv")
    with open(csv_path, "w", encoding="utf-8", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(fields)
        for c in comparison.cells:
            writer.writerow([getattr(c, f) for f in fields])
    lines += [f"table: {txt}", f"table: {csv_path}"]
    lines += [f"plot: {p}" for p in _comparison_plots(comparison, out)]
    lines.append(f"report: {_comparison_report(comparison, out)}")
    return lines


def _comparison_report(comparison: Any, out: str) -> str:
    """The comparison's self-contained HTML report, ``<out>/<case>_report.html``."""
    from aocontrol.study.report import comparison_report

    _plot_module()  # selects the file backend
    return comparison_report(comparison, os.path.join(out, f"{comparison.case}_report.html"))


def _comparison_plots(comparison: Any, out: str) -> list[str]:
    from aocontrol.study.results import read_psds

    plot = _plot_module()
    name = comparison.case
    pngs = []
    path = os.path.join(out, f"{name}_contrast.png")
    curves = {f"{c.scheme} {c.controller}": c for c in comparison.cells}
    plot.plot_contrast(None, curves, title=f"{name}: raw contrast", path=path)
    pngs.append(path)
    for scheme in dict.fromkeys(c.scheme for c in comparison.cells):
        psds, freqs = {}, None
        for c in comparison.cells:
            if c.scheme != scheme or c.path is None:
                continue
            f, p = read_psds(c.path)
            if "residuals" in p:
                if freqs is None and "disturbance" in p:
                    psds["stage-2 input"] = p["disturbance"]
                freqs = f
                psds[c.controller] = p["residuals"]
        if freqs is not None:
            path = os.path.join(out, f"{name}_{scheme}_residual_psd.png")
            plot.plot_residual_psd(
                freqs, psds, path=path, title=f"{name} {scheme}: stage-2 PSDs (sum over modes)"
            )
            pngs.append(path)
    vib = comparison.vibration
    if vib:
        tilt = {k: v[1] for k, v in vib["psd"].items()}
        freqs = next(iter(vib["psd"].values()))[0]
        path = os.path.join(out, f"{name}_tilt_psd.png")
        plot.plot_vibration(
            freqs,
            tilt,
            title=f"{name} {vib['scheme']}: tilt (mode {vib['mode']}) residual",
            path=path,
        )
        pngs.append(path)
        path = os.path.join(out, f"{name}_sensitivity.png")
        plot.plot_rejection(
            vib["freqs"],
            {k: np.sqrt(v) for k, v in vib["sensitivity2"].items()},
            psd=vib["disturbance_psd"],
            title=f"{name}: rejection and tilt disturbance PSD",
            path=path,
        )
        pngs.append(path)
    return pngs


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
        _valid_name("strategy", name, STRATEGIES + DIAGNOSTICS)
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


# ----------------------------------------------------------------------------- parser
def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="aocontrol",
        description="Adaptive-optics control toolbox: design, analyse and score AO controllers.",
        epilog="Run 'aocontrol COMMAND --help' for the options of a command.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log INFO messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(
        name: str, func: Callable, help_: str, description: str | None = None
    ) -> argparse.ArgumentParser:
        p = sub.add_parser(
            name,
            help=help_,
            description=description or help_,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        p.set_defaults(func=func)
        return p

    def no_progress(p: argparse.ArgumentParser) -> None:
        p.add_argument("--no-progress", action="store_true", help="hide progress bars")

    def case_settings(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--set",
            action="append",
            default=[],
            metavar="KEY=VALUE",
            help="replace a case value for this run, e.g. --set seeing=0.6 or a model error "
            "--set stage2.latency_error=0.3 --set stage2.dm_time_constant='0.2 ms' "
            "(repeatable; keys of 'aocontrol cases', checked like a case file)",
        )

    def sensor_options(p: argparse.ArgumentParser) -> None:
        from aocontrol.study.cases import OPTICAL_GAIN_SETTINGS, SENSORS

        p.add_argument(
            "--sensor",
            choices=SENSORS,
            default=None,
            help="stage-2 sensor in the loop (default: the case's, linear)",
        )
        p.add_argument(
            "--optical-gain",
            choices=OPTICAL_GAIN_SETTINGS,
            default=None,
            help="stage-2 optical-gain handling (default: the case's, calibrated)",
        )

    add("cases", _cases, "list the science cases and their parameters")

    p = add("run", _run, "simulate one case with one controller; write a results file")
    p.add_argument("case", help="science case name (see 'aocontrol cases') or a case .toml")
    p.add_argument(
        "--controller",
        required=True,
        metavar="{" + ",".join(run_controller_names()) + "}",
        help="controller of the (fast) stage (aocontrol.synthesis.CONTROLLERS; integrator is "
        "an alias of reference)",
    )
    p.add_argument(
        "--scheme",
        required=True,
        metavar="{" + ",".join(RUN_SCHEMES) + "}",
        help="single stage, standalone cascade or dCAO cascade",
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=None,
        help="simulated time [s] (default: the comparison protocol's)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", default="results", help="folder of the results file and plots")
    p.add_argument("--quick", action="store_true", help="reduced modes and pupil (smoke runs)")
    p.add_argument("--telemetry", action="store_true", help="also store the telemetry")
    sensor_options(p)
    case_settings(p)
    no_progress(p)

    p = add("compare", _compare, "the paper's comparison of one case: table, plots, HTML report")
    p.add_argument("case", help="science case name (see 'aocontrol cases')")
    p.add_argument("--quick", action="store_true", help="short, reduced runs")
    p.add_argument("--out", default="compare-output", help="folder of the table and plots")
    sensor_options(p)
    case_settings(p)
    no_progress(p)

    p = add(
        "design",
        _design,
        "design a controller bank from closed-loop telemetry",
        description=DESIGN_DESCRIPTION,
    )
    design_arguments(p)
    no_progress(p)

    p = add("sweep", _sweep, "run a sweep spec (cases x controllers x schemes x seeds) on Dask")
    p.add_argument("spec", help="sweep spec (TOML)")
    p.add_argument(
        "--scheduler", default=None, help="Dask scheduler address (default: a local cluster)"
    )
    p.add_argument("--out", default="sweep-output", help="results folder")
    no_progress(p)

    p = add(
        "adapt",
        _adapt,
        "adaptive control under drifting turbulence: residual against update period and window",
    )
    p.epilog = (
        "Defaults are the study's recommended configuration (docs/adaptive.md): T = 2 s, "
        "W = T, design latency 0.5 s, order 2 and a 24-point design grid with --quick (order 5 "
        "and the synthesis' grid otherwise). A multi-knot drift: a case file's "
        '[atmosphere.drift] kind = "knots" with --scenario case. Cost: a 60-s quick run '
        "(24 modes, five strategies) takes a few CPU minutes per scenario."
    )
    p.add_argument("case", help="science case name (see 'aocontrol cases') or a case .toml")
    p.add_argument(
        "--scenario",
        default="wind-doubles",
        help="wind-doubles, seeing-worsens, stochastic, or case (the case file's "
        "[atmosphere.drift], any number of knots); comma-separated for several "
        "(default wind-doubles)",
    )
    p.add_argument(
        "--period",
        default=ADAPT_PERIOD,
        help=f"update periods T [s], comma-separated (default {ADAPT_PERIOD})",
    )
    p.add_argument(
        "--window",
        default=ADAPT_WINDOW,
        help="telemetry windows W: seconds, 'T' (the period) or 'max(T, x)', comma-separated "
        f"(default {ADAPT_WINDOW}: each redesign from all the telemetry since the last)",
    )
    p.add_argument("--seconds", type=float, default=60.0, help="simulated time [s] (default 60)")
    p.add_argument(
        "--strategies",
        default=None,
        help="comma-separated among fixed, adaptive, oracle, modal-gain, lqg (default all)",
    )
    p.add_argument(
        "--latency",
        type=float,
        default=ADAPT_LATENCY,
        help=f"design latency [s] (default {ADAPT_LATENCY:g}; negative: the measured compute time)",
    )
    p.add_argument(
        "--order",
        type=int,
        default=None,
        help=f"data-driven controller order (default {ADAPT_ORDER[True]} with --quick, "
        f"{ADAPT_ORDER[False]} otherwise)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--jobs", type=int, default=1, help="worker processes of each design (default 1)"
    )
    p.add_argument(
        "--quick", action="store_true", help="reduced modes and pupil (24 stage-2 modes)"
    )
    p.add_argument(
        "--select",
        type=float,
        default=None,
        help="redesign only the modes covering this share of the residual shift, e.g. 0.9 "
        "(default: every mode)",
    )
    p.add_argument(
        "--n-grid",
        type=int,
        default=None,
        help=f"data-driven design grid size (default {ADAPT_N_GRID[True]} with --quick, the "
        "synthesis' own otherwise)",
    )
    p.add_argument(
        "--max-iter",
        type=int,
        default=None,
        help="data-driven iterations of a cold design (default: the synthesis' own)",
    )
    p.add_argument(
        "--measure-from",
        type=float,
        default=None,
        help="time [s] from which every row's residual is averaged (default: each row's own "
        "window; the study's tables use 6 s of 60)",
    )
    p.add_argument(
        "--out",
        default="adapt-output",
        help="folder of the table, HDF5 and plot (default adapt-output)",
    )

    p = add(
        "demo",
        _demo,
        "design controllers for one mode and plot the rejection, then a short comparison "
        "on a science case (table and contrast plot)",
    )
    p.add_argument("--output", default="demo-output", help="folder for the plots and tables")
    p.add_argument("--case", default="red1-fast", help="science case of the comparison")
    p.add_argument(
        "--no-comparison", action="store_true", help="only the one-mode design (seconds)"
    )
    p.add_argument("--fs", type=float, default=3000.0, help="loop rate [Hz]")
    p.add_argument(
        "--latency", type=float, default=0.83, help="RTC latency beyond WFS integration [frames]"
    )
    p.add_argument(
        "--noise-rms", type=float, default=2.0, help="modal measurement noise [nm RMS per frame]"
    )
    no_progress(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``aocontrol`` command (console script and ``python -m aocontrol``).

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name (default ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status: 0 success, 1 failed run, 2 user error (argparse also exits with 2).
    """
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return args.func(args)
    except (UserError, ValueError, TypeError, OSError) as exc:
        print(f"aocontrol {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except RunFailed as exc:
        print(f"aocontrol {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"aocontrol {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
