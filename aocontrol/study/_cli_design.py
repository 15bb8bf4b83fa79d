"""The ``aocontrol design`` command: telemetry files in, a certified controller bank out
(:mod:`aocontrol.study.cli` dispatches to it)."""

from __future__ import annotations

import argparse
import contextlib
import os
import time
from typing import Any

import numpy as np

from aocontrol.controllers import MultiModeBank
from aocontrol.study._cli_common import (
    _MAX_MODE_ROWS,
    _MIN_TELEMETRY_FRAMES,
    UserError,
    _format_table,
    _out_dir,
    _plot_module,
    _valid_name,
)


def _design_report(design: Any, path: str, info: dict | None = None) -> str:
    """The design's self-contained HTML report at ``path``.

    ``design``: a ``report.DesignReportData``, or the result of
    ``synthesis.design_from_telemetry`` (converted by ``report.design_report_data`` with the
    header lines ``info``).
    """
    from aocontrol.study.report import DesignReportData, design_report, design_report_data

    _plot_module()  # selects the file backend
    if not isinstance(design, DesignReportData):
        design = design_report_data(design, info=info)
    return design_report(design, path)


# ----------------------------------------------------------------------------- design
def read_telemetry(path: str, stage: str | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read closed-loop telemetry (measurements and commands) from a file.

    Parameters
    ----------
    path : str
        A ``.npz`` with arrays ``measurements`` and ``commands`` of shape
        ``(n_frames, n_modes)`` [nm], or an aocontrol results file (HDF5) written with
        telemetry (``telemetry_measurements``, ``telemetry_commands``).
    stage : str, optional
        ``"stage1"`` or ``"stage2"`` for a cascade results file (default ``"stage2"``).

    Returns
    -------
    measurements, commands : ndarray, shape (n_frames, n_modes)
        Float64 [nm].
    info : dict
        ``fs`` [Hz] and ``latency_frames`` when the file knows them (results files).

    Raises
    ------
    UserError
        Unreadable file, missing arrays, wrong shapes, non-finite values: the message says
        what was expected.
    """
    expect = (
        "expected a .npz with arrays 'measurements' and 'commands' of shape (n_frames, "
        "n_modes), or an aocontrol results file saved with telemetry"
    )
    if not os.path.isfile(path):
        raise UserError(f"telemetry file {path!r} does not exist; {expect}")
    info: dict = {}
    if path.endswith(".npz"):
        try:
            with np.load(path, allow_pickle=False) as data:
                missing = [k for k in ("measurements", "commands") if k not in data.files]
                if missing:
                    raise UserError(
                        f"telemetry file {path!r} has arrays {sorted(data.files)}, missing "
                        f"{missing}; {expect}"
                    )
                m, u = data["measurements"], data["commands"]
        except (OSError, ValueError) as exc:
            raise UserError(f"telemetry file {path!r} cannot be read ({exc}); {expect}") from exc
    else:
        import h5py

        try:
            fh = h5py.File(path, "r")
        except OSError as exc:
            raise UserError(f"telemetry file {path!r} is neither .npz nor HDF5; {expect}") from exc
        with fh:
            group = fh
            if "stage1" in fh or "stage2" in fh:
                name = stage or "stage2"
                if name not in fh:
                    raise UserError(f"--stage must be one of {sorted(fh)}, got {stage!r}")
                group = fh[name]
            keys = ("telemetry_measurements", "telemetry_commands")
            missing = [k for k in keys if k not in group]
            if missing:
                raise UserError(f"telemetry file {path!r} has no {missing}; {expect}")
            m, u = group[keys[0]][()], group[keys[1]][()]
            if "fs" in group.attrs:
                info["fs"] = float(np.ravel(group.attrs["fs"])[0])
            meta = group.attrs.get("metadata_json")
            if meta is not None:
                import json

                lat = json.loads(meta if isinstance(meta, str) else meta.decode()).get(
                    "latency_frames"
                )
                if lat is not None:
                    info["latency_frames"] = float(lat)
    m = np.asarray(m, dtype=float)
    u = np.asarray(u, dtype=float)
    if m.ndim != 2 or m.shape != u.shape:
        raise UserError(
            f"telemetry file {path!r}: measurements {m.shape} and commands {u.shape} must both "
            "be 2-D (n_frames, n_modes) of the same shape"
        )
    if m.shape[0] < _MIN_TELEMETRY_FRAMES:
        raise UserError(
            f"telemetry file {path!r}: {m.shape[0]} frames, at least {_MIN_TELEMETRY_FRAMES} "
            "expected (rows are frames: is the array transposed?)"
        )
    if not (np.isfinite(m).all() and np.isfinite(u).all()):
        raise UserError(f"telemetry file {path!r}: measurements or commands contain NaN/inf")
    return m, u, info


_AOT_EXTENSIONS = (".fits", ".fit", ".fits.gz", ".fts")
#: Formats of ``design --out`` by extension: the controller file (HDF5, reloaded with
#: ``aocontrol.load_controller``) or the real-time export (FITS table or CSV,
#: ``aocontrol.io.export_controller``).
OUT_FORMATS = {".h5": "hdf5", ".hdf5": "hdf5", ".fits": "fits", ".fit": "fits", ".csv": "csv"}


def _out_format(option: str, path: str, formats: dict) -> str:
    """The format a file name's extension says, or a UserError naming the valid ones."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in formats:
        raise UserError(
            f"{option} {path!r}: extension {ext!r} does not say the format; expected one of "
            f"{', '.join(sorted(formats))} (.h5/.hdf5: controller file for "
            "aocontrol.load_controller; .fits/.csv: real-time export for "
            "aocontrol.io.read_exported_controller)"
        )
    return formats[ext]


def _design_telemetry(args: argparse.Namespace) -> Any:
    """The telemetry of ``design``: an AOT loop, or our .npz/.h5 layouts, in nm when the unit
    is a known length (``--unit``, the file's), with ``--command-sign`` applied."""
    from aocontrol._units import NM, nm_per_unit
    from aocontrol.synthesis import LoopTelemetry

    path = args.telemetry
    if path.lower().endswith(_AOT_EXTENSIONS):
        from aocontrol.io import read_aot

        if args.stage is not None:
            raise UserError("--stage is for results files; an AOT file takes --loop NAME")
        return read_aot(
            path,
            args.loop,
            latency_frames=args.latency,
            command_sign=float(args.command_sign),
            unit=args.unit,
            override_metadata=args.override_metadata,
        )
    if args.loop is not None:
        raise UserError(f"--loop is for AOT files (.fits), got {path!r}")
    m, u, info = read_telemetry(path, args.stage)
    # The file's own rate and latency (results files) stay in the telemetry: a --fs or
    # --latency that contradicts them is refused by design_from_telemetry.
    fs = info.get("fs", args.fs)
    latency = info.get("latency_frames", args.latency)
    if fs is None or latency is None:
        raise UserError("--fs [Hz] and --latency [frames] are required for this telemetry file")
    unit = args.unit or NM  # our layouts are documented in nm
    results_file = not path.endswith(".npz")  # an aocontrol results file: nm, by its writer
    if results_file and args.unit is not None and not args.override_metadata:
        if nm_per_unit(args.unit) != 1.0:
            raise UserError(
                f"--unit {args.unit!r} contradicts the results file {path!r} (its telemetry is "
                "in nm); pass --override-metadata to use the given unit"
            )
    factor = nm_per_unit(unit)
    if factor is not None:
        if factor != 1.0:  # (x * 1.0 is x: no copies of a 66-MB record for nothing)
            m, u = m * factor, u * factor
        unit = NM
    sign = float(args.command_sign)
    return LoopTelemetry(m, u if sign == 1.0 else sign * u, fs, latency, source=path, unit=unit)


def _design(args: argparse.Namespace) -> int:
    from aocontrol.io import EXPORT_FORMATS
    from aocontrol.synthesis import controller_names, get_controller

    controller = _valid_name("controller", args.controller, sorted(controller_names()))
    # File names are checked before the design (minutes) is made.
    out_format = _out_format("--out", args.out, OUT_FORMATS)
    if args.export:
        _out_format("--export", args.export, EXPORT_FORMATS)
    with contextlib.ExitStack() as stack:
        client = _design_client(args, get_controller(controller), stack)
        return _design_with(args, controller, out_format, client)


def _design_client(args: argparse.Namespace, spec: Any, stack: contextlib.ExitStack) -> Any:
    """The Dask client of ``design --scheduler/--workers`` (None without them), connected
    before anything is read or designed; closed with ``stack``."""
    if args.scheduler is None and args.workers is None:
        return None
    from aocontrol.study._sweep_cluster import _connect
    from aocontrol.study.sweep import CONNECT_TIMEOUT_S

    if not spec.distributed:
        raise UserError(
            f"--scheduler/--workers: controller {spec.name!r} does not run on a Dask cluster "
            "(the data-driven designs do)"
        )
    if args.scheduler is not None and args.workers is not None:
        raise UserError("--workers starts a local cluster; it cannot go with --scheduler")
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    return _connect(args.scheduler, args.workers or 2, CONNECT_TIMEOUT_S, stack)


def _design_with(args: argparse.Namespace, controller: str, out_format: str, client: Any) -> int:
    """``design`` once the names are checked and the cluster (if any) is connected."""
    from aocontrol._units import unit_label
    from aocontrol.analysis import sensitivity
    from aocontrol.controllers import save_controller
    from aocontrol.synthesis import design_from_telemetry, get_controller

    t_start = time.perf_counter()
    telemetry = _design_telemetry(args)
    t_read = time.perf_counter() - t_start
    given = {
        "order": args.order,
        "control_weight": args.control_weight,
        "n_jobs": args.jobs,
        "progress": not args.no_progress,
    }
    uncertainty = _uncertainty(args)
    if uncertainty is not None:  # the robust design's own set, where it takes one
        given["gain_interval"] = uncertainty.gain
        given["latency_interval"] = uncertainty.latency
    # The registry says which options a design reads; the CLI offers them all.
    options = {k: v for k, v in given.items() if k in get_controller(controller).options}
    bounds = () if args.bounds == "none" else tuple(args.bounds.split(","))
    try:
        rep = design_from_telemetry(
            telemetry,
            controller,
            fs=args.fs,
            latency_frames=args.latency,
            estimator=args.estimator,
            modulus_margin=args.modulus_margin,
            reference_gain=args.gain,
            options=options,
            bounds=bounds,
            check_telemetry=not args.no_telemetry_check,
            override_metadata=args.override_metadata,
            uncertainty=uncertainty,
            client=client,
            n_jobs=args.jobs,
        )
    except MemoryError as exc:  # the cluster's workers refused before designing
        raise UserError(str(exc)) from None
    t_files = time.perf_counter()
    n_modes = rep.n_modes
    unit = unit_label(rep.unit)
    print(
        f"telemetry: {telemetry.n_frames} frames x {n_modes} modes, fs = {rep.fs:g} Hz, "
        f"latency = {rep.latency_frames:g} frame; controller: {controller}; estimator: "
        f"{rep.estimate.method}"
    )
    print(_units_line(rep.unit, args))
    if rep.telemetry_check is not None:
        chk = rep.telemetry_check
        print(
            f"command sign {int(args.command_sign):+d}: {chk.sign} (innovation variance of "
            f"m + G u / m - G u = {chk.sign_statistic:.3g}, < 1 for the loop's own sign); "
            f"rms(G u) / rms(m) = {chk.scale:.3g}"
        )
    rows = [
        {
            "mode": r["mode"],
            "stable": "yes" if r["stable"] else "NO",
            "gm_down": r["gain_margin_down_db"],
            "gm_db": r["gain_margin_db"],
            "pm": r["phase_margin_deg"],
            "mm": r["modulus_margin"],
            "dm_removed": r["delay_margin_removed_frames"],
            "dm": r["delay_margin_frames"],
            "robust": r["robust_margin"],
            "rms": r["residual_nm"],
            "ref": r["reference_nm"],
            "wiener": r["wiener_nm"],
            "bound": r["constrained_nm"],
        }
        for r in rep.rows()
    ]
    columns = [
        ("mode", "mode", "d"),
        ("stable", "stable", ""),
        ("gm_down", "GM-[dB]", ".2f"),
        ("gm_db", "GM+[dB]", ".2f"),
        ("pm", "PM[deg]", ".1f"),
        ("mm", "MM[1]", ".3f"),
        ("dm_removed", "lat-[fr]", ".2f"),
        ("dm", "lat+[fr]", ".2f"),
        *([("robust", "MMset[1]", ".3f")] if rep.robust_margins is not None else []),
        ("rms", f"resid[{unit}]", ".2f"),
        ("ref", f"OMGI resid[{unit}]", ".2f"),
        ("wiener", f"Wiener[{unit}]", ".2f"),
        ("bound", f"MM-bound[{unit}]", ".2f"),
    ]
    if n_modes > _MAX_MODE_ROWS:
        summary = []
        for label, fn in (("min", np.min), ("median", np.median), ("max", np.max)):
            summary.append(
                {
                    c[0]: (label if c[0] == "mode" else fn([r[c[0]] for r in rows]))
                    for c in columns
                    if c[0] != "stable"
                }
            )
            summary[-1]["stable"] = f"{sum(r['stable'] == 'yes' for r in rows)}/{n_modes}"
        columns[0] = ("mode", "over modes", "")
        rows = summary
    print(_format_table(rows, columns))
    total, total_ref = rep.residual_rms, rep.reference_residual_rms
    print(
        f"predicted residual (all modes): {total:.2f} {unit} RMS; optimal-gain integrator "
        f"{total_ref:.2f} {unit} RMS (ratio {total / total_ref:.3f}); Wiener bound "
        f"{rep.wiener_rms:.2f} {unit}, modulus-margin bound {rep.constrained_rms:.2f} {unit}"
    )
    if uncertainty is not None:
        print(_robust_line(rep))
    if rep.bound_failures:
        first = next(iter(rep.bound_failures.items()))
        print(
            f"modulus-margin bound not computed for modes {list(rep.bound_failures)[:10]} "
            f"(mode {first[0]}: {first[1]})"
        )
    out = args.out
    folder = os.path.dirname(os.path.abspath(out))
    _out_dir(folder)
    if out_format == "hdf5":
        path = save_controller(rep.controller, out)
        print(f"controller file: {path} (reload with aocontrol.load_controller)")
    else:
        from aocontrol.io import export_controller

        path = export_controller(
            rep.controller,
            out,
            latency_frames=rep.latency_frames,
            modulus_margin=rep.achieved_modulus_margin,
            format=out_format,
        )
        print(
            f"controller file: {path} ({out_format.upper()} real-time export; read with "
            "aocontrol.io.read_exported_controller)"
        )
    if args.export:
        from aocontrol.io import export_controller

        exported = export_controller(
            rep.controller,
            args.export,
            latency_frames=rep.latency_frames,
            modulus_margin=rep.achieved_modulus_margin,
        )
        print(f"real-time export: {exported} (read with aocontrol.io.read_exported_controller)")
    if args.aot_out:
        from aocontrol.io import write_aot_filter

        if not args.telemetry.lower().endswith(_AOT_EXTENSIONS):
            raise UserError("--aot-out needs an AOT telemetry file (its loop gets the filter)")
        written = write_aot_filter(args.telemetry, rep.controller, args.loop, out=args.aot_out)
        print(f"AOT file with the designed temporal filter: {written}")
    plot = _plot_module()
    stem = os.path.splitext(out)[0]
    show = sorted({0, n_modes // 2, n_modes - 1})
    freqs, psd = rep.estimate.freqs, rep.estimate.psd
    multimode = isinstance(rep.controller, MultiModeBank)
    if multimode:
        # Each mode's own sensitivity, the diagonal of S = I - G F (the nominal loop a
        # multi-mode predictor is certified for; its modes couple off the diagonal).
        F = rep.controller.predictor_response(freqs)
        g = rep.controller.plant_response(freqs)
        S = (1.0 - g[:, None] * np.diagonal(F, axis1=1, axis2=2)).T
    else:
        S = sensitivity(rep.plant, rep.controller, freqs)
    fig_path = stem + "_sensitivity.png"
    plot.plot_sensitivity(
        freqs,
        {f"mode {i}": S[i] for i in show},
        disturbance_psd=psd[show[0]],
        noise_psd=float(rep.estimate.noise_psd[show[0]]),
        modulus_margin=args.modulus_margin,
        title=f"{controller}: disturbance and noise PSD of mode {show[0]}",
        path=fig_path,
        unit=unit,
    )
    print(f"plot: {fig_path}")
    if multimode:
        from aocontrol.analysis import multimode_certificate

        cert = multimode_certificate(rep.controller)
        print(
            f"multi-mode loop: stable {cert.stable}, multivariable modulus margin "
            f"min sigma(I + G K) >= {cert.margin:.3f} (certified lower bound)"
        )
    else:
        margins_path = stem + "_margins.png"
        plot.plot_margins(
            {f"mode {i}": rep.margins[i] for i in show},
            path=margins_path,
            required_modulus_margin=args.modulus_margin,
        )
        print(f"plot: {margins_path}")
    info = {"telemetry": args.telemetry, "frames": telemetry.n_frames, "unit": unit}
    print(f"report: {_design_report(rep, stem + '_report.html', info=info)}")
    print(_time_line(rep.timings, t_read, time.perf_counter() - t_files))
    return 0


def _time_line(timings: dict, read: float, files: float) -> str:
    """One line: the command's wall time by step (:attr:`TelemetryDesign.timings` and the
    CLI's own reading and output), the interpreter's start and imports not counted."""
    t = dict(timings)
    steps = [
        ("reading", read),
        ("check and estimate", t.pop("estimate", 0.0)),
        ("design", t.pop("design", 0.0)),
        ("certificates and bounds", sum(t.values())),  # reference, margins, robust, bounds
        ("files and report", files),  # tables, controller file, plots, HTML
    ]
    total = sum(v for _, v in steps)
    return (
        "wall time: "
        + ", ".join(f"{label} {v:.1f} s" for label, v in steps)
        + f"; {total:.1f} s in all (the interpreter's start and imports not counted)"
    )


def _uncertainty(args: argparse.Namespace) -> Any:
    """The :class:`~aocontrol.analysis.UncertaintySet` of ``--robust-gain`` and
    ``--robust-latency`` (``None`` when neither is given)."""
    from aocontrol.analysis import UncertaintySet

    if args.robust_gain is None and args.robust_latency is None:
        return None
    pairs = {}
    for option, text, default in (
        ("--robust-gain", args.robust_gain, (1.0, 1.0)),
        ("--robust-latency", args.robust_latency, (0.0, 0.0)),
    ):
        if text is None:
            pairs[option] = default
            continue
        try:
            lo, hi = (float(x) for x in text.split(","))
        except ValueError:
            raise UserError(f"{option}: expected LOW,HIGH (two numbers), got {text!r}") from None
        pairs[option] = (lo, hi)
    try:
        return UncertaintySet(gain=pairs["--robust-gain"], latency=pairs["--robust-latency"])
    except ValueError as exc:
        raise UserError(f"--robust-gain / --robust-latency: {exc}") from None


def _robust_line(rep: Any) -> str:
    """One line: what the robust margins cover and their smallest values."""
    u = rep.uncertainty
    head = (
        f"certified over loop gain [{u.gain[0]:g}, {u.gain[1]:g}] x latency change "
        f"[{u.latency[0]:+g}, {u.latency[1]:+g}] frames (exact in both, "
        "aocontrol.analysis.robust_margin): "
    )
    parts = []
    for label, robust in (("design", rep.robust_margins), ("OMGI", rep.reference_robust_margins)):
        if robust is None:
            parts.append(f"{label} not computed (a multi-mode bank or a measured plant)")
            continue
        values = np.array([r.value for r in robust])
        ok = sum(r.stable and r.value >= rep.modulus_margin - 1e-9 for r in robust)
        parts.append(
            f"{label} min {values.min():.3f}, {ok}/{len(robust)} modes >= {rep.modulus_margin:g}"
            f" and stable over the set"
        )
    return head + "; ".join(parts)


def _units_line(unit: str | None, args: argparse.Namespace) -> str:
    """What unit the figures are in, and where it came from."""
    if unit == "nm":
        return (
            "units: nm (modal coefficients of 1 nm RMS; a file's lengths converted, AOT "
            "commands from metres)"
        )
    if unit is None:
        return (
            "units: a.u. (the file does not state the unit of its modal values; state it "
            "with --unit, e.g. --unit m)"
        )
    return f"units: {unit} (not a length: figures in {unit})"


#: ``aocontrol design --help``: what the command reads and writes, and in which conventions.
DESIGN_DESCRIPTION = """\
Design a controller bank from closed-loop telemetry, certify it and write it.

Units. Figures are printed in the unit of the telemetry, named in every column. A unit that
is a length is converted to nm (modal coefficients of 1 nm RMS, the project's convention):
an AOT file's commands are in metres on the actuators (the standard's unit), its modal
coefficients and matrices in the unit their BUNIT states; a .npz or results file is in nm.
A unit that is not a length is printed as it is; one nobody states is printed 'a.u.': state
it with --unit (e.g. --unit m). A --unit that contradicts the file is refused.

Sign. u = K m and the correction is subtracted: m = pol - G u (G the loop plant, pol the
pseudo-open loop). Telemetry whose commands enter with the other sign (m + G u then less
predictable than m - G u), or whose commands and measurements are not in one unit, is
refused before the design: read it with --command-sign -1 (--no-telemetry-check to design
anyway).

Metadata. --fs and --latency that contradict the file's frame rate or delay (AOT: latency
= delay - 1 frame) are refused unless --override-metadata.

Temporal filter. --aot-out writes the loop's time_filter_num/den in aotpy's documented
convention, sys(z) = sum b_i z^i / sum a_j z^j (ascending powers of z; an integrator of gain
g is num [0, g], den [-1, 1]), stated in the images' TFCONV keyword. --export and --out
.fits/.csv write the real-time table: b0..bn, a1..an in powers of z^-1 (Direct Form I,
u[k] = sum b_i m[k-i] - sum a_i u[k-i]). --out .h5 writes the controller file that
aocontrol.load_controller reloads."""


def design_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``aocontrol design`` (:func:`aocontrol.study.cli.main`)."""
    p.add_argument(
        "telemetry",
        help="AOT file (.fits, with --loop NAME when it has several loops), .npz with "
        "'measurements' and 'commands' (n_frames, n_modes), or a results file saved with "
        "--telemetry",
    )
    p.add_argument("--loop", default=None, help="control loop of an AOT file (its uid)")
    p.add_argument(
        "--fs", type=float, default=None, help="loop rate [Hz] (refused if it contradicts the file)"
    )
    p.add_argument(
        "--latency",
        type=float,
        default=None,
        help="RTC latency beyond the WFS integration [frames] (AOT: delay - 1 by default; "
        "refused if it contradicts the file)",
    )
    p.add_argument(
        "--override-metadata",
        action="store_true",
        help="let --fs, --latency and --unit replace the file's values",
    )
    p.add_argument(
        "--unit",
        default=None,
        metavar="UNIT",
        help="unit of the telemetry's modal values when the file does not state it: a length "
        "(m, um, nm) is converted to nm, another (rad, V) is printed as it is (default: the "
        "file's; nm for .npz and results files; 'a.u.' when unknown)",
    )
    p.add_argument(
        "--command-sign",
        type=int,
        choices=(1, -1),
        default=1,
        help="multiply the commands by this sign (-1 for a system whose commands enter with the "
        "other sign; default 1)",
    )
    p.add_argument(
        "--no-telemetry-check",
        action="store_true",
        help="design even when the command sign or scale looks wrong",
    )
    p.add_argument(
        "--controller",
        default="datadriven",
        metavar="NAME",
        help="registered controller to design (default datadriven; see "
        "aocontrol.synthesis.CONTROLLERS)",
    )
    p.add_argument(
        "--estimator",
        default="prewhitened",
        choices=("prewhitened", "welch"),
        help="disturbance PSD estimator (default prewhitened)",
    )
    p.add_argument("--order", type=int, default=5, help="data-driven controller order")
    p.add_argument(
        "--modulus-margin", type=float, default=0.5, help="required modulus margin (default 0.5)"
    )
    p.add_argument("--gain", type=float, default=0.5, help="gain of --controller integrator")
    p.add_argument(
        "--control-weight",
        type=float,
        default=0.0,
        help="LQ weight of u^2 for --controller lqg (default 0: minimum variance)",
    )
    p.add_argument(
        "--robust-gain",
        default=None,
        metavar="LOW,HIGH",
        help="report every mode's modulus margin certified over loop-gain factors in "
        "[LOW, HIGH] (e.g. 0.7,1.3), the design's and the reference's; the set of "
        "--controller datadriven-robust when given (its default: 0.7,1.3 and -0.3,0.3)",
    )
    p.add_argument(
        "--robust-latency",
        default=None,
        metavar="LOW,HIGH",
        help="the same over latency changes [frames] in [LOW, HIGH] (a negative LOW after an "
        "equals sign: --robust-latency=-0.3,0.3)",
    )
    p.add_argument("--stage", default=None, help="stage group of a cascade results file")
    p.add_argument(
        "--jobs",
        type=int,
        default=None,
        help="worker processes of the data-driven design and of the margins and bounds (default: "
        "every core; 1: none)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run the data-driven design's modes on the Dask scheduler at ADDRESS (e.g. "
        "tcp://host:8786; refused within 5 s if none answers, before anything is designed)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="run the data-driven design's modes on a local Dask cluster of N processes",
    )
    p.add_argument(
        "--bounds",
        default="wiener,constrained",
        help="bounds to report: 'wiener', 'constrained' (one SOCP per mode), both "
        "comma-separated (default), or 'none'",
    )
    p.add_argument(
        "--out",
        default="controller.h5",
        help="controller file, its format by extension: .h5/.hdf5 (aocontrol.load_controller), "
        ".fits or .csv (real-time export); another extension is refused",
    )
    p.add_argument(
        "--export",
        default=None,
        help="also write the filters for a real-time computer (.fits table or .csv)",
    )
    p.add_argument(
        "--aot-out",
        default=None,
        help="AOT input only: copy it with the designed filter in the loop's time_filter_* "
        "(aotpy's convention, ascending powers of z)",
    )
