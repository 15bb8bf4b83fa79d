"""Plots of the studies' tables: adaptive control against the update period, robustness.

Private module of :mod:`aocontrol.study.plot` (its public names are there).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from aocontrol.study._plot_common import _finish


def plot_adapt(
    tables: Mapping[str, Sequence[Mapping[str, Any]]],
    *,
    title: str | None = None,
    path: str | os.PathLike | None = None,
) -> Any:
    """Residual against the update period, one panel per scenario, one line per strategy.

    Parameters
    ----------
    tables : mapping scenario -> sequence of rows
        Rows with keys ``strategy``, ``period`` [s], ``window`` [s] and ``residual`` [nm^2]
        (e.g. ``dataclasses.asdict`` of :class:`aocontrol.study.adapt.AdaptRow`). The fixed
        design (strategy ``"fixed"``: no period) is drawn as a dashed horizontal line, every
        other strategy as markers at its periods joined by a line, each (strategy, window)
        in its own colour.
    title : str, optional
        Figure title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    n = max(len(tables), 1)
    fig, axes = plt.subplots(1, n, figsize=(5.0 * n, 4.2), squeeze=False)
    for ax, (scenario, rows) in zip(axes[0], tables.items(), strict=False):
        lines: dict[tuple[str, float], list[tuple[float, float]]] = {}
        for r in rows:
            lines.setdefault((r["strategy"], r["window"]), []).append((r["period"], r["residual"]))
        ax.set_xscale("log")
        for k, ((strategy, window), pts) in enumerate(sorted(lines.items())):
            pts.sort()
            t, v = np.array(pts).T
            label = f"{strategy} (W = {window:g} s)"
            color = f"C{k % 10}"
            if strategy == "fixed":
                ax.axhline(v.mean(), ls="--", lw=1.0, color=color, label=label)
            else:
                ax.plot(t, v, "o-", ms=5, lw=1.0, color=color, label=label)
        periods = sorted({r["period"] for r in rows if r["strategy"] != "fixed"})
        if periods:
            ax.set_xticks(periods, [f"{p:g}" for p in periods])
            ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
            ax.set_xlim(periods[0] / 1.5, periods[-1] * 1.5)
        ax.set_xlabel("update period T [s]")
        ax.set_ylabel("residual variance [nm$^2$]")
        ax.set_title(scenario)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize="x-small")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _finish(fig, path)


def plot_robustness(
    rows: Sequence[Mapping[str, Any]],
    *,
    value: str = "retained",
    title: str | None = None,
    path: str | os.PathLike | None = None,
) -> Any:
    """Gain retained (or loss) under model errors: a panel per (case, error), a line per
    controller.

    Parameters
    ----------
    rows : sequence of mapping
        One per run: ``case``, ``error`` (``"nominal"`` for the reference point), ``magnitude``
        (the error's size, in its own unit), ``controller``, ``status`` (``"ok"`` or
        ``"diverged"``) and ``retained`` (the fraction of the nominal gain over the reference
        integrator that remains) or ``loss`` (the residual variance over the same
        controller's on the nominal instrument), as ``value`` says. A diverged run is a red
        cross at the bottom of its panel.
    value : {"retained", "loss"}, default "retained"
        The figure plotted (the loss on a log axis where it spans more than 20x).
    title : str, optional
        Figure title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    labels = {"retained": "gain retained [1]", "loss": "residual variance / nominal [1]"}
    if value not in labels:
        raise ValueError(f"value must be one of {list(labels)}, got {value!r}")
    errors = [e for e in dict.fromkeys(r["error"] for r in rows) if e != "nominal"]
    cases = list(dict.fromkeys(r["case"] for r in rows))
    if not errors or not cases:
        raise ValueError("rows must hold runs under at least one model error")
    ctrls = list(dict.fromkeys(r["controller"] for r in rows))
    fig, axes = plt.subplots(
        len(cases), len(errors), figsize=(3.2 * len(errors), 2.9 * len(cases)),
        constrained_layout=True, squeeze=False,
    )  # fmt: skip
    colors = {c: f"C{i}" for i, c in enumerate(ctrls)}
    for i, case in enumerate(cases):
        for j, err in enumerate(errors):
            ax = axes[i, j]
            for c in ctrls:
                pts = sorted(
                    (float(r["magnitude"]), r)
                    for r in rows
                    if r["case"] == case and r["error"] == err and r["controller"] == c
                )  # fmt: skip
                if not pts:
                    continue
                x = np.array([m for m, _ in pts])
                y = np.array([r[value] if r["status"] == "ok" else np.nan for _, r in pts])
                ax.plot(x, y, "o-", ms=3, lw=1.0, color=colors[c],
                        label=c if (i, j) == (0, 0) else None)  # fmt: skip
                bad = np.array([r["status"] != "ok" for _, r in pts])
                if bad.any():  # at the bottom of the axis, whatever its scale
                    ax.plot(x[bad], np.zeros(bad.sum()), "x", color="r", ms=8,
                            transform=ax.get_xaxis_transform())  # fmt: skip
            ax.axhline(1.0, color="k", lw=0.6, ls=":")
            finite = [
                r[value]
                for r in rows
                if r["case"] == case and r["error"] == err and r["status"] == "ok"
                and np.isfinite(r[value]) and r[value] > 0
            ]  # fmt: skip
            if value == "loss" and finite and max(finite) / min(finite) > 20:
                ax.set_yscale("log")  # only where the spread needs it
            ax.set_title(f"{case}: {err}", fontsize="small")
            units = {r.get("unit") for r in rows if r["error"] == err} - {None, ""}
            ax.set_xlabel(f"error [{units.pop()}]" if len(units) == 1 else "error magnitude")
            ax.set_ylabel(labels[value])
            ax.grid(True, alpha=0.3)
    fig.legend(loc="outside lower center", ncol=min(len(ctrls), 6), fontsize="small")
    if title:
        fig.suptitle(title)
    return _finish(fig, path)
