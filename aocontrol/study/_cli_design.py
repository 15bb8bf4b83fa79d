"""The ``aocontrol design`` command: telemetry files in, a certified controller bank out
(:mod:`aocontrol.study.cli` dispatches to it)."""

from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np

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


def _design_telemetry(args: argparse.Namespace) -> Any:
    """The telemetry of ``design``: an AOT loop, or our .npz/.h5 layouts."""
    from aocontrol.synthesis import LoopTelemetry

    path = args.telemetry
    if path.lower().endswith(_AOT_EXTENSIONS):
        from aocontrol.io import read_aot

        if args.stage is not None:
            raise UserError("--stage is for results files; an AOT file takes --loop NAME")
        return read_aot(path, args.loop, latency_frames=args.latency)
    if args.loop is not None:
        raise UserError(f"--loop is for AOT files (.fits), got {path!r}")
    m, u, info = read_telemetry(path, args.stage)
    fs = args.fs if args.fs is not None else info.get("fs")
    latency = args.latency if args.latency is not None else info.get("latency_frames")
    if fs is None or latency is None:
        raise UserError("--fs [Hz] and --latency [frames] are required for this telemetry file")
    return LoopTelemetry(m, u, fs, latency, source=path)


def _design(args: argparse.Namespace) -> int:
    from aocontrol.analysis import sensitivity
    from aocontrol.controllers import save_controller
    from aocontrol.synthesis import controller_names, design_from_telemetry, get_controller

    controller = _valid_name("controller", args.controller, sorted(controller_names()))
    telemetry = _design_telemetry(args)
    given = {
        "order": args.order,
        "control_weight": args.control_weight,
        "n_jobs": args.jobs,
        "progress": not args.no_progress,
    }
    # The registry says which options a design reads; the CLI offers them all.
    options = {k: v for k, v in given.items() if k in get_controller(controller).options}
    bounds = () if args.bounds == "none" else tuple(args.bounds.split(","))
    rep = design_from_telemetry(
        telemetry,
        controller,
        fs=args.fs,
        estimator=args.estimator,
        modulus_margin=args.modulus_margin,
        reference_gain=args.gain,
        options=options,
        bounds=bounds,
    )
    n_modes = rep.n_modes
    print(
        f"telemetry: {telemetry.n_frames} frames x {n_modes} modes, fs = {rep.fs:g} Hz, "
        f"latency = {rep.latency_frames:g} frame; controller: {controller}; estimator: "
        f"{rep.estimate.method}"
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
        ("rms", "resid[nm]", ".2f"),
        ("ref", "OMGI resid[nm]", ".2f"),
        ("wiener", "Wiener[nm]", ".2f"),
        ("bound", "MM-bound[nm]", ".2f"),
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
        f"predicted residual (all modes): {total:.2f} nm RMS; optimal-gain integrator "
        f"{total_ref:.2f} nm RMS (ratio {total / total_ref:.3f}); Wiener bound "
        f"{rep.wiener_rms:.2f} nm, modulus-margin bound {rep.constrained_rms:.2f} nm"
    )
    out = args.out
    folder = os.path.dirname(os.path.abspath(out))
    _out_dir(folder)
    path = save_controller(rep.controller, out)
    print(f"controller file: {path} (reload with aocontrol.load_controller)")
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
    )
    margins_path = stem + "_margins.png"
    plot.plot_margins(
        {f"mode {i}": rep.margins[i] for i in show},
        path=margins_path,
        required_modulus_margin=args.modulus_margin,
    )
    print(f"plot: {fig_path}")
    print(f"plot: {margins_path}")
    info = {"telemetry": args.telemetry, "frames": telemetry.n_frames}
    print(f"report: {_design_report(rep, stem + '_report.html', info=info)}")
    return 0
