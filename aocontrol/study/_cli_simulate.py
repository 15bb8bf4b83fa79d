"""The commands that run the simulator on the science cases: ``cases``, ``run`` and
``compare`` (:mod:`aocontrol.study.cli` parses and dispatches to them)."""

from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np

from aocontrol.study._cli_common import (
    RunFailed,
    UserError,
    _format_table,
    _out_dir,
    _plot_module,
    _valid_name,
    run_controller_names,
)


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
