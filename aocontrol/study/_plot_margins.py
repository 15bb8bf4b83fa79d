"""Margins and residuals per controller and per mode: bar charts and modal curves.

Private module of :mod:`aocontrol.study.plot` (its public names are there).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import MaxNLocator

from aocontrol.study._plot_common import _axes, _finish


def plot_margins(
    margins: Mapping[str, Any],
    *,
    required_modulus_margin: float | None = None,
    title: str | None = None,
    path: str | os.PathLike | None = None,
) -> Any:
    """Margins summary: one bar chart per margin, one bar per controller.

    Panels: gain margin [dB] (how far the loop gain can rise, up, and fall, down), phase
    margin [deg] (smallest over every crossover), modulus margin (dimensionless), delay
    margin [frames] (latency that can be added, up, and removed, down). Unstable loops are
    hatched red; infinite margins are drawn at the edge of the axis and marked "inf".

    Parameters
    ----------
    margins : mapping label -> Margins
        :class:`aocontrol.analysis.Margins` of each controller.
    required_modulus_margin : float, optional
        Draw the design requirement on the modulus-margin panel.
    title : str, optional
        Figure title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    if not margins:
        raise ValueError("margins must hold at least one controller")
    labels = list(margins)
    # (axis label, value above zero, value below zero or None)
    panels = (
        (
            "gain margin [dB]\n(up: gain can rise; down: fall)",
            "gain_margin_db",
            "gain_margin_down_db",
        ),
        ("phase margin [deg]", "phase_margin", None),
        ("modulus margin [1]", "modulus_margin", None),
        (
            "delay margin [frames]\n(up: latency added; down: removed)",
            "delay_margin",
            "delay_margin_removed",
        ),
    )
    fig, axes = plt.subplots(1, 4, figsize=(14.0, 4.3), constrained_layout=True)
    pos = np.arange(len(labels))
    colors = ["tab:blue" if margins[k].stable else "tab:red" for k in labels]
    for ax, (name, up, down) in zip(axes, panels, strict=True):
        sides = [(np.array([float(getattr(margins[k], up)) for k in labels]), 1.0)]
        if down is not None:
            low = np.array([float(getattr(margins[k], down)) for k in labels])
            # dB below 0 already carry their sign; removed latency is drawn below the axis.
            sides.append((low if down.endswith("db") else -low, -1.0))
        every = np.concatenate([v for v, _ in sides])
        finite = np.isfinite(every)
        top = float(np.max(np.abs(every[finite]))) * 1.2 if finite.any() else 1.0
        for vals, sign in sides:
            fin = np.isfinite(vals)
            shown = np.where(fin, vals, sign * top)
            bars = ax.bar(pos, np.nan_to_num(shown), color=colors, alpha=1.0 if sign > 0 else 0.6)
            for bar, k, ok, v in zip(bars, labels, fin, vals, strict=True):
                if not margins[k].stable:
                    bar.set_hatch("//")
                if not ok and not np.isnan(v):
                    ax.annotate(
                        "inf" if v > 0 else "-inf",
                        (bar.get_x() + bar.get_width() / 2, sign * top),
                        ha="center",
                        va="bottom" if sign > 0 else "top",
                        fontsize="small",
                    )
        if down is not None:
            ax.axhline(0.0, color="k", lw=0.8)
        if name.startswith("modulus") and required_modulus_margin is not None:
            ax.axhline(required_modulus_margin, color="r", ls=":", label="required")
            ax.legend(fontsize="small")
        ax.set_xticks(pos, labels, rotation=30, ha="right", fontsize="small")
        ax.set_ylabel(name)
        ax.grid(True, axis="y", alpha=0.3)
    if title:
        fig.suptitle(title)
    return _finish(fig, path)


def plot_modal_margins(
    modal_margins: Mapping[str, Sequence[Any]],
    *,
    required_modulus_margin: float | None = None,
    title: str | None = None,
    path: str | os.PathLike | None = None,
) -> Any:
    """Margins over the modes of controller banks: modulus margin and delay margins per mode.

    The delay panel shows the latency that can be added (above zero, solid) and removed
    (below zero, dotted) per mode. Unstable modes are marked with a red cross on both panels
    (their margins mean nothing).

    Parameters
    ----------
    modal_margins : mapping label -> sequence of Margins
        :class:`aocontrol.analysis.Margins` of every mode (index = mode) of each bank.
    required_modulus_margin : float, optional
        Draw the design requirement on the modulus-margin panel.
    title : str, optional
        Figure title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    if not modal_margins:
        raise ValueError("modal_margins must hold at least one controller")
    fig, (ax_m, ax_d) = plt.subplots(1, 2, figsize=(12.0, 4.0), constrained_layout=True)
    for label, mar in modal_margins.items():
        modes = np.arange(len(mar))
        mm = np.array([m.modulus_margin for m in mar], dtype=float)
        dm = np.array([m.delay_margin for m in mar], dtype=float)
        dm_rm = np.array([m.delay_margin_removed for m in mar], dtype=float)
        bad = ~np.array([m.stable for m in mar], dtype=bool)
        (line,) = ax_m.plot(modes, mm, ".-", ms=3, lw=0.8, label=label)
        ax_d.plot(modes, np.where(np.isfinite(dm), dm, np.nan), ".-", ms=3, lw=0.8)
        ax_d.plot(modes, -dm_rm, ".:", ms=2, lw=0.8, color=line.get_color())
        if bad.any():
            for ax, y in ((ax_m, mm), (ax_d, dm)):
                ax.plot(modes[bad], np.nan_to_num(y[bad], posinf=1.0), "x", color="r", ms=7)
    if required_modulus_margin is not None:
        ax_m.axhline(required_modulus_margin, color="r", ls=":", lw=1.0, label="required")
    ax_m.set_ylabel("modulus margin [1]")
    ax_d.axhline(0.0, color="k", lw=0.8)
    ax_d.set_ylabel("latency margin [frames]\n(added above 0, removed below)")
    for ax in (ax_m, ax_d):
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("mode")
        ax.grid(True, which="both", alpha=0.3)
    ax_m.legend(fontsize="small")
    if title:
        fig.suptitle(title)
    return _finish(fig, path)


def plot_modal_residuals(
    residuals: Mapping[str, np.ndarray],
    *,
    bounds: Mapping[str, np.ndarray] | None = None,
    title: str | None = None,
    path: str | os.PathLike | None = None,
    unit: str = "nm",
) -> Any:
    """Residual RMS per mode of several controllers, with lower bounds dashed (log axis).

    Parameters
    ----------
    residuals : mapping label -> ndarray (n_modes,)
        Residual of each controller per mode [unit RMS].
    bounds : mapping label -> ndarray (n_modes,), optional
        Bounds per mode [unit RMS] (e.g. the Wiener and margin-constrained bounds).
    title : str, optional
        Axes title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.
    unit : str, default "nm"
        Unit of the telemetry (axis labels: ``unit^2/Hz``, ``unit RMS``).

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig, ax = _axes(None, figsize=(8.0, 4.5))
    for label, r in residuals.items():
        r = np.asarray(r, dtype=float)
        ax.semilogy(np.arange(r.size), r, ".-", ms=3, lw=0.8, label=label)
    for label, b in (bounds or {}).items():
        b = np.asarray(b, dtype=float)
        ax.semilogy(np.arange(b.size), b, ls="--", lw=1.0, color="0.4", label=label)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("mode")
    ax.set_ylabel(f"residual [{unit} RMS]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    if title:
        ax.set_title(title)
    return _finish(fig, path)
