"""The HTML report of a case comparison (private; public in :mod:`aocontrol.study.report`).

The table (Strehl, 4-6 lambda/D contrast, measured and predicted stage-2 residual per scheme and
controller), the margins of every stage-2 bank over its modes on the design plant, the
rejection ``|S|^2`` of each controller over the design's disturbance PSD for representative
modes, the stage-2 residual PSDs, the contrast curves, and for a case with a vibration the
tilt residual.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from aocontrol.study._report_common import (
    _MARGIN_COLUMNS,
    Column,
    _figure,
    _margin_summary,
    _meta,
    _p,
    _rejection_figure,
    _sensitivities,
    _stamp,
    _table,
    _write,
    modal_margins,
    representative_modes,
)

logger = logging.getLogger(__name__)


def _comparison_psds(comparison: Any) -> dict:
    """``{scheme: (freqs, {label: psd summed over modes})}`` from the cells' results files."""
    from aocontrol.study.results import read_psds

    out: dict = {}
    for c in comparison.cells:
        if c.path is None or not os.path.isfile(c.path):
            continue
        f, p = read_psds(c.path)
        if "residuals" not in p:
            continue
        freqs, series = out.setdefault(c.scheme, (f, {}))
        if "disturbance" in p and "stage-2 input" not in series:
            series["stage-2 input"] = p["disturbance"].sum(axis=0)
        series[c.controller] = p["residuals"].sum(axis=0)
    return out


def comparison_report(
    comparison: Any,
    path: str | os.PathLike,
    *,
    residual_psds: Mapping[str, tuple[np.ndarray, Mapping[str, np.ndarray]]] | None = None,
    title: str | None = None,
) -> str:
    """Write the HTML report of a case comparison.

    Parameters
    ----------
    comparison : CaseComparison
        Result of :func:`aocontrol.study.compare.compare_case`. Its ``designs`` (the design
        PSDs and plant per scheme) give the margins and the rejection figure; without them
        those sections say so.
    path : str or os.PathLike
        The ``.html`` file (its folder exists).
    residual_psds : mapping scheme -> (freqs, mapping label -> ndarray (n_f,) or (n_modes, n_f))
        Stage-2 residual PSDs [nm^2/Hz, one-sided] per scheme; default read from the cells'
        results files (``Cell.path``), summed over the modes.
    title : str, optional
        Page title (default ``"aocontrol compare: <case>"``).

    Returns
    -------
    str
        ``path``.
    """
    from aocontrol.study import plot

    name = comparison.case
    cells = list(comparison.cells)
    designs = dict(getattr(comparison, "designs", None) or {})
    schemes = list(dict.fromkeys(c.scheme for c in cells))
    first = cells[0].settings if cells and cells[0].settings else {}
    meta = {
        "case": name,
        "schemes": ", ".join(schemes),
        "controllers (stage 2)": ", ".join(dict.fromkeys(c.controller for c in cells)),
        "reference gain (scan)": ", ".join(
            f"{k} {v:g}" for k, v in comparison.reference_gains.items()
        ),
    }
    if first:
        meta["exposure"] = f"{first.get('seconds', float('nan')):g} s"
        meta["quick mode"] = "yes" if first.get("quick") else "no"
        stage2 = first.get("scene", {}).get("stage2", {})
        if "n_modes" in stage2:
            meta["stage-2 modes"] = stage2["n_modes"]
    if comparison.seconds:
        meta["wall time"] = ", ".join(f"{k} {v:.1f} s" for k, v in comparison.seconds.items())
    meta.update(_stamp())
    sections: list[tuple[str, list[str]]] = [("", [_meta(meta)])]

    rows = [
        {
            "scheme": c.scheme,
            "controller": c.controller,
            "strehl": 100.0 * c.strehl,
            "contrast": c.mean_contrast_4_6,
            "rms": c.residual_rms_nm,
            "rms_se": c.residual_rms_se_nm,
            "pred": c.predicted_rms_nm,
            "pred_se": c.predicted_rms_se_nm,
            "ratio": "{:.2f} [{:.2f}, {:.2f}]".format(*c.ratio_interval()),
            "file": os.path.basename(c.path) if c.path else "",
        }
        for c in cells
    ]
    columns: list[Column] = [
        ("scheme", "scheme", ""),
        ("controller", "controller", ""),
        ("strehl", "Strehl [%]", ".2f"),
        ("contrast", "contrast 4-6 l/D", ".3e"),
        ("rms", "stage-2 residual [nm]", ".2f"),
        ("rms_se", "+- s.e. [nm]", ".2f"),
        ("pred", "predicted [nm]", ".2f"),
        ("pred_se", "+- s.e. [nm]", ".2f"),
        ("ratio", "predicted / measured [2 s.e.]", ""),
        ("file", "results file", ""),
    ]
    body = [
        _table(rows, columns, "results"),
        _p(
            "Strehl and mean raw contrast over 4-6 lambda/D after a perfect coronagraph, at "
            "1.65 um; stage-2 modal residual measured in the run, and predicted from the "
            "calibration telemetry's PSDs (the design data). Standard errors: the calibration "
            "record and the exposure are each one draw of the atmosphere; their RMS scatter "
            "by the predicted residual PSD's sampling variance (Gaussian residual), "
            "combined in the ratio's interval (2 standard errors). That interval takes the "
            "modes as independent; the modes of a frozen-flow atmosphere move together, so "
            "the ratio scatters more from one exposure to the next than the interval says: "
            "on the demo's comparison (red 1 fast, 120 modes, 1-s exposures) it ranged "
            "0.92-1.02 over eight seeds (median 0.98; seed 0, the demo's, the lowest; seven "
            "of eight below 1: there the prediction also runs about 2 % low, a bias not yet "
            "explained). An interval that excludes 1 by a few per cent is that scatter; a "
            "ratio far outside 0.9-1.1 is worth a look."
        ),
    ]
    vib = comparison.vibration
    if vib and vib.get("tilt_rms_nm"):
        vrows = [{"controller": k, "tilt": v} for k, v in vib["tilt_rms_nm"].items()]
        body.append(
            _table(
                vrows,
                [("controller", "controller", ""), ("tilt", "tilt residual [nm RMS]", ".2f")],
                "vibration",
            )
        )
        if "relative_gain" in vib:
            body.append(
                _p(
                    f"Tilt (mode {vib['mode']}, {vib['scheme']}): data-driven vs reference "
                    f"gain {100 * vib['relative_gain']:.1f} % (the paper: 31.7 %)."
                )
            )
    sections.append(("Results", body))

    mrows, modal = [], {}
    for c in cells:
        d = designs.get(c.scheme)
        mar = modal_margins(d.plant, c.bank) if d is not None and c.bank is not None else None
        if mar is not None:
            modal[f"{c.scheme} {c.controller}"] = mar
        mrows.append({"scheme": c.scheme, "controller": c.controller, **_margin_summary(mar)})
    body = [
        _table(
            mrows,
            [("scheme", "scheme", ""), ("controller", "controller", ""), *_MARGIN_COLUMNS],
            "margins",
        ),
        _p(
            "Margins of each stage-2 bank over its modes, on the design plant (gain, phase, "
            "modulus and delay margins from aocontrol.analysis.margins; n/a: no design data or "
            "no linear transfer function)."
        ),
    ]
    if modal:
        body.append(
            _figure(
                lambda: plot.plot_modal_margins(modal, required_modulus_margin=0.5),
                "modulus and delay margins per mode (red crosses: unstable modes)",
            )
        )
    sections.append(("Margins", body))

    body = []
    for scheme in schemes:
        d = designs.get(scheme)
        if d is None or d.freqs.size == 0:
            continue
        banks = {c.controller: c.bank for c in cells if c.scheme == scheme and c.bank is not None}
        sens = _sensitivities(d.plant, banks, d.freqs)
        if sens:
            extra = [vib["mode"]] if vib and "mode" in vib else []
            modes = representative_modes(d.n_modes, extra)
            body.append(_rejection_figure(d.freqs, d.psd, sens, modes, f"{name} {scheme}"))
    if not body:
        body.append(_p("no design PSDs in this comparison: no rejection figure"))
    sections.append(("Rejection over the disturbance PSD", body))

    psds = residual_psds if residual_psds is not None else _comparison_psds(comparison)
    body = []
    for scheme, (f, series) in psds.items():
        body.append(
            _figure(
                lambda f=f, series=series, scheme=scheme: plot.plot_residual_psd(
                    f, series, title=f"{name} {scheme}: stage-2 PSDs (sum over modes)"
                ),
                f"{scheme}: stage-2 residual PSD of each controller, one-sided [nm^2/Hz]",
            )
        )
    if vib and vib.get("psd"):
        tilt = {k: v[1] for k, v in vib["psd"].items()}
        fv = next(iter(vib["psd"].values()))[0]
        body.append(
            _figure(
                lambda: plot.plot_vibration(fv, tilt, title=f"{name}: tilt residual"),
                f"tilt (mode {vib.get('mode', '?')}) residual PSD and reverse cumulative RMS",
            )
        )
    if not body:
        body.append(_p("no residual PSDs recorded (no results files)"))
    sections.append(("Residual PSDs", body))

    curves = {
        f"{c.scheme} {c.controller}": c
        for c in cells
        if np.size(c.contrast_profile) and np.isfinite(c.contrast_profile).any()
    }
    if curves:
        sections.append(
            (
                "Contrast curves",
                [
                    _figure(
                        lambda: plot.plot_contrast(None, curves, title=f"{name}: raw contrast"),
                        "long-exposure raw contrast after a perfect coronagraph against "
                        "separation; shaded: 4-6 lambda/D",
                    )
                ],
            )
        )
    return _write(path, title or f"aocontrol compare: {name}", sections)
