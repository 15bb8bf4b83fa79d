"""The HTML report of a controller design (private; public in :mod:`aocontrol.study.report`).

The predicted residual of each controller against the bounds (total and per mode), the
certified margins per mode, the rejection for representative modes, the predicted residual
PSDs.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aocontrol._units import unit_label
from aocontrol.analysis import Margins, loop_response, residual_variance
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


@dataclass(frozen=True, eq=False)
class DesignReportData:
    """What a design report shows: plain arrays and controller banks.

    Parameters
    ----------
    plant : control.TransferFunction
        Loop plant the controllers were designed for.
    freqs : ndarray, shape (n_f,)
        Frequencies [Hz] of the PSDs, in [0, fs/2].
    psd : ndarray, shape (n_modes, n_f)
        Disturbance (pseudo-open-loop) PSD per mode, one-sided [unit^2/Hz].
    noise_psd : ndarray, shape (n_modes,)
        White measurement-noise level per mode, one-sided [unit^2/Hz].
    controllers : mapping label -> ControllerBank
        The design first, then references (e.g. the starting integrator), each of
        ``n_modes`` modes.
    predicted_rms : mapping label -> ndarray (n_modes,), optional
        Predicted residual per mode [unit RMS] of each controller (same labels); computed with
        :func:`aocontrol.analysis.residual_variance` when not given.
    margins : mapping label -> sequence of Margins, optional
        Certified margins per mode of each controller; computed with
        :func:`aocontrol.analysis.margins` when not given.
    bounds : mapping label -> ndarray (n_modes,)
        Lower bounds per mode [unit RMS], e.g. ``{"Wiener bound": ..., "constrained bound
        (MM 0.5)": ...}``.
    modulus_margin : float, optional
        The required modulus margin (drawn on the margins figure).
    title : str
        Page title.
    info : mapping str -> str
        Header lines (telemetry file, frames, fs, latency, estimator, ...).
    unit : str, default "nm"
        Unit of the telemetry and of every figure (``"a.u."`` when unknown).
    robust_margins : mapping label -> ndarray (n_modes,), optional
        Per mode, the modulus margin certified over an uncertainty set
        (:func:`aocontrol.analysis.robust_margin`) of the controllers that have one; the set
        is described in ``info``.

    Raises
    ------
    ValueError
        Shapes that do not agree (the message names the argument and the expected shape).
    """

    plant: Any
    freqs: np.ndarray
    psd: np.ndarray
    noise_psd: np.ndarray
    controllers: Mapping[str, Any]
    predicted_rms: Mapping[str, np.ndarray] | None = None
    margins: Mapping[str, Sequence[Margins]] | None = None
    bounds: Mapping[str, np.ndarray] = field(default_factory=dict)
    modulus_margin: float | None = None
    title: str = "aocontrol design"
    info: Mapping[str, Any] = field(default_factory=dict)
    unit: str = "nm"
    robust_margins: Mapping[str, np.ndarray] | None = None

    def __post_init__(self) -> None:
        f = np.asarray(self.freqs, dtype=float)
        psd = np.atleast_2d(np.asarray(self.psd, dtype=float))
        if f.ndim != 1 or psd.shape[1:] != f.shape:
            raise ValueError(
                f"psd must have shape (n_modes, {f.size}) to match freqs {f.shape}, got "
                f"{np.shape(self.psd)}"
            )
        n = psd.shape[0]
        noise = np.broadcast_to(np.asarray(self.noise_psd, dtype=float), (n,)).copy()
        if not self.controllers:
            raise ValueError("controllers must hold at least one bank (the design)")
        for label, bank in self.controllers.items():
            if getattr(bank, "n_modes", n) != n:
                raise ValueError(
                    f"controllers[{label!r}] has {bank.n_modes} modes, expected {n} (psd rows)"
                )
        for argname, mapping in (
            ("predicted_rms", self.predicted_rms),
            ("bounds", self.bounds),
            ("robust_margins", self.robust_margins),
        ):
            for label, v in (mapping or {}).items():
                if np.shape(v) != (n,):
                    raise ValueError(
                        f"{argname}[{label!r}] must have shape ({n},) [one per mode], got "
                        f"{np.shape(v)}"
                    )
        for label, mar in (self.margins or {}).items():
            if mar is not None and len(mar) != n:
                raise ValueError(f"margins[{label!r}] must hold {n} Margins, got {len(mar)}")
        object.__setattr__(self, "freqs", f)
        object.__setattr__(self, "psd", psd)
        object.__setattr__(self, "noise_psd", noise)

    @property
    def n_modes(self) -> int:
        """Number of modes."""
        return self.psd.shape[0]


def design_report_data(
    design: Any, *, title: str | None = None, info: Mapping[str, Any] | None = None
) -> DesignReportData:
    """The report's input from a telemetry design (``synthesis.design_from_telemetry``).

    Reads the attributes of that function's result by name (``controller_name``,
    ``controller``, ``reference``, ``plant``, ``fs``, ``latency_frames``, ``estimate`` with
    ``freqs``, ``psd``, ``noise_psd`` and ``method``, ``modulus_margin``, ``margins``,
    ``reference_margins``, ``residual_variance``, ``reference_residual_variance``,
    ``wiener_variance``, ``constrained_variance``); bounds that are all NaN (not computed)
    are left out.

    Parameters
    ----------
    design : TelemetryDesign
        Result of :func:`aocontrol.synthesis.design_from_telemetry`.
    title : str, optional
        Page title (default ``"aocontrol design: <controller>"``).
    info : mapping, optional
        Extra header lines (e.g. the telemetry file).

    Returns
    -------
    DesignReportData
    """
    est = design.estimate
    name = design.controller_name
    ref = "starting integrator (optimal gain)"
    bounds = {}
    for label, attr in (
        ("Wiener bound", "wiener_variance"),
        (f"constrained bound (MM {design.modulus_margin:g})", "constrained_variance"),
    ):
        var = np.asarray(getattr(design, attr), dtype=float)
        if np.isfinite(var).any():
            bounds[label] = np.sqrt(var)
    robust = {}
    for label, attr in ((name, "robust_margins"), (ref, "reference_robust_margins")):
        values = getattr(design, attr, None)  # duck typed: absent on older design objects
        if values is not None:
            robust[label] = np.array([r.value for r in values])
    uncertainty = getattr(design, "uncertainty", None)
    header = {
        "fs": f"{design.fs:g} Hz",
        "latency": f"{design.latency_frames:g} frame (beyond the WFS frame)",
        "estimator": getattr(est, "method", ""),
        "required modulus margin": f"{design.modulus_margin:g}",
        **({"robust margins over": uncertainty.describe()} if robust else {}),
        **(info or {}),
    }
    return DesignReportData(
        design.plant,
        est.freqs,
        est.psd,
        est.noise_psd,
        {name: design.controller, ref: design.reference},
        predicted_rms={
            name: np.sqrt(design.residual_variance),
            ref: np.sqrt(design.reference_residual_variance),
        },
        margins={name: design.margins, ref: design.reference_margins},
        bounds=bounds,
        modulus_margin=design.modulus_margin,
        title=title or f"aocontrol design: {name}",
        info=header,
        unit=unit_label(getattr(design, "unit", "nm")),
        robust_margins=robust or None,
    )


def design_report(data: DesignReportData, path: str | os.PathLike) -> str:
    """Write the HTML report of a controller design.

    Parameters
    ----------
    data : DesignReportData
        The design, its references, bounds and PSDs.
    path : str or os.PathLike
        The ``.html`` file (its folder exists).

    Returns
    -------
    str
        ``path``.
    """
    from aocontrol.study import plot

    n = data.n_modes
    labels = list(data.controllers)
    rms = dict(data.predicted_rms or {})
    for label in labels:
        if label not in rms:
            var = residual_variance(
                data.plant, data.controllers[label], data.freqs, data.psd, data.noise_psd
            )
            rms[label] = np.sqrt(np.atleast_1d(var))
    mar = dict(data.margins or {})
    for label in labels:
        if label not in mar:
            mar[label] = modal_margins(data.plant, data.controllers[label])
    bounds = {k: np.asarray(v, dtype=float) for k, v in data.bounds.items()}

    meta = {"modes": n, **data.info, **_stamp()}
    sections: list[tuple[str, list[str]]] = [("", [_meta(meta)])]

    totals = {k: float(np.sqrt(np.sum(np.square(v)))) for k, v in bounds.items()}
    srows = []
    for label in labels:
        total = float(np.sqrt(np.sum(np.square(rms[label]))))
        row = {"controller": label, "rms": total, **_margin_summary(mar[label])}
        for i, t in enumerate(totals.values()):
            row[f"ratio{i}"] = total / t if t > 0 else math.nan
        srows.append(row)
    for b, t in totals.items():
        srows.append({"controller": b, "rms": t})
    scols: list[Column] = [
        ("controller", "controller", ""),
        ("rms", f"predicted residual [{data.unit} RMS]", ".2f"),
        *[(f"ratio{i}", f"/ {b}", ".3f") for i, b in enumerate(totals)],
        *_MARGIN_COLUMNS,
    ]
    body = [
        _table(srows, scols, "summary"),
        _p(
            "Residual over all modes predicted from the PSDs (disturbance through S, noise "
            "through T), as a ratio to each bound; margins over the modes (certified: "
            "aocontrol.analysis.margins)."
        ),
    ]
    sections.append(("Summary", body))

    first = labels[0]
    robust_labels = [label for label in labels if label in (data.robust_margins or {})]
    prows = []
    for i in range(n):
        m = mar[first][i] if mar[first] is not None else None
        row: dict[str, Any] = {"mode": i}
        if m is not None:
            row.update(
                stable=bool(m.stable),
                gm_down=m.gain_margin_down_db,
                gm=m.gain_margin_db,
                pm=m.phase_margin,
                mm=m.modulus_margin,
                dm_removed=m.delay_margin_removed,
                dm=m.delay_margin,
            )
        for j, label in enumerate(robust_labels):
            row[f"robust{j}"] = float(data.robust_margins[label][i])
        for j, label in enumerate(labels):
            row[f"rms{j}"] = float(rms[label][i])
        for j, b in enumerate(bounds.values()):
            row[f"b{j}"] = float(b[i])
        prows.append(row)
    pcols: list[Column] = [
        ("mode", "mode", "d"),
        ("stable", f"{first}: stable", ""),
        ("gm_down", "GM down [dB]", ".2f"),
        ("gm", "GM up [dB]", ".2f"),
        ("pm", "PM [deg]", ".1f"),
        ("mm", "MM [1]", ".3f"),
        ("dm_removed", "latency - [frames]", ".2f"),
        ("dm", "latency + [frames]", ".2f"),
        *[
            (f"robust{j}", f"{label}: MM over the set [1]", ".3f")
            for j, label in enumerate(robust_labels)
        ],
        *[(f"rms{j}", f"{label} [{data.unit}]", ".3f") for j, label in enumerate(labels)],
        *[(f"b{j}", f"{b} [{data.unit}]", ".3f") for j, b in enumerate(bounds)],
    ]
    body = [
        _table(prows, pcols, "modes"),
        _figure(
            lambda: plot.plot_modal_residuals(
                {k: rms[k] for k in labels},
                bounds=bounds,
                title="predicted residual per mode",
                unit=data.unit,
            ),
            "predicted residual per mode of each controller, bounds dashed",
        ),
    ]
    known = {k: v for k, v in mar.items() if v is not None}
    if known:
        body.append(
            _figure(
                lambda: plot.plot_modal_margins(known, required_modulus_margin=data.modulus_margin),
                "modulus and delay margins per mode (red crosses: unstable modes)",
            )
        )
    sections.append(("Per mode", body))

    sens = _sensitivities(data.plant, data.controllers, data.freqs)
    body = []
    if sens:
        body.append(
            _rejection_figure(
                data.freqs, data.psd, sens, representative_modes(n), "design", data.unit
            )
        )
        # The pseudo-open loop (disturbance + noise): what a loop without control would see,
        # and smooth where a noise-subtracted estimate is floored.
        series = {"open loop (disturbance + noise)": (data.psd + data.noise_psd[:, None]).sum(0)}
        for label in sens:
            lr = loop_response(data.plant, data.controllers[label], data.freqs)
            s2 = np.abs(np.atleast_2d(lr.sensitivity)) ** 2
            t2 = np.abs(np.atleast_2d(lr.complementary)) ** 2
            series[label] = (s2 * data.psd + t2 * data.noise_psd[:, None]).sum(axis=0)
        body.append(
            _figure(
                lambda: plot.plot_residual_psd(
                    data.freqs,
                    series,
                    title="predicted residual PSD (sum over modes)",
                    unit=data.unit,
                ),
                "predicted residual PSD, |S|^2 disturbance + |T|^2 noise, summed over the "
                f"modes, one-sided [{data.unit}^2/Hz]",
            )
        )
    else:
        body.append(_p("no controller with a transfer function: no rejection figure"))
    sections.append(("Rejection and residual PSDs", body))
    return _write(path, data.title, sections)
