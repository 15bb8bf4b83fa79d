"""What both HTML reports share (private to :mod:`aocontrol.study.report`): the page's pieces
(tables, embedded figures, the atomic write) and the per-mode margins and rejection figure.
"""

from __future__ import annotations

import base64
import datetime
import html
import logging
import math
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from aocontrol._atomic import atomic_path
from aocontrol._version import __version__
from aocontrol.analysis import Margins, loop_response, margins

logger = logging.getLogger(__name__)

# Panels of the rejection figure: at most this many modes.
_MAX_REJECTION_MODES = 4
# Rows of a per-mode table shown open; longer tables are folded (<details>), never cut.
_OPEN_ROWS = 40
_CSS = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; color: #222;
       line-height: 1.4; padding: 0 1em; }
h1 { font-size: 1.6em; border-bottom: 2px solid #446; padding-bottom: .2em; }
h2 { font-size: 1.25em; margin-top: 1.8em; color: #335; }
table.data { border-collapse: collapse; margin: .8em 0; font-size: .9em; }
table.data th, table.data td { border: 1px solid #bbc; padding: .25em .6em; }
table.data th { background: #eef; }
table.data td.num { text-align: right; font-variant-numeric: tabular-nums; }
table.data td.bad { color: #b00; font-weight: bold; }
figure { margin: 1em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: .85em; color: #555; }
dl.meta { display: grid; grid-template-columns: max-content auto; gap: .1em 1em; }
dl.meta dt { font-weight: bold; } dl.meta dd { margin: 0; }
p.note { font-size: .9em; color: #555; }
"""


# ----------------------------------------------------------------------------- HTML pieces
Column = tuple[str, str, str]  # (key, header, format spec)


def _cell(value: Any, fmt: str) -> tuple[str, str]:
    """(text, css class) of one table cell."""
    if isinstance(value, bool | np.bool_):
        return ("yes", "") if value else ("NO", "bad")
    if isinstance(value, int | float | np.number):
        v = float(value)
        if math.isnan(v):
            return "n/a", "num"
        if math.isinf(v):
            return ("inf" if v > 0 else "-inf"), "num"
        return format(value, fmt), "num"
    return str(value if value is not None else ""), ""


def _table(rows: Sequence[Mapping[str, Any]], columns: Sequence[Column], table_id: str) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for _, h, _ in columns)
    body = []
    for r in rows:
        cells = []
        for key, _, fmt in columns:
            text, css = _cell(r.get(key), fmt)
            cls = f' class="{css}"' if css else ""
            cells.append(f"<td{cls}>{html.escape(text)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    table = (
        f'<table class="data" id="{html.escape(table_id)}"><thead><tr>{head}</tr></thead>'
        f"<tbody>{''.join(body)}</tbody></table>"
    )
    if len(rows) > _OPEN_ROWS:
        return f"<details><summary>{len(rows)} rows (click to open)</summary>{table}</details>"
    return table


def _figure(draw: Callable[[], Any], caption: str) -> str:
    """Draw a figure (a callable returning a matplotlib Figure), embed it as a PNG."""
    from aocontrol.study import plot

    png = plot.figure_png(draw())
    data = base64.b64encode(png).decode("ascii")
    cap = html.escape(caption)
    return (
        f'<figure><img src="data:image/png;base64,{data}" alt="{cap}">'
        f"<figcaption>{cap}</figcaption></figure>"
    )


def _meta(items: Mapping[str, Any]) -> str:
    rows = "".join(
        f"<dt>{html.escape(str(k))}</dt><dd>{html.escape(str(v))}</dd>" for k, v in items.items()
    )
    return f'<dl class="meta">{rows}</dl>'


def _p(text: str) -> str:
    return f'<p class="note">{html.escape(text)}</p>'


def _write(path: str | os.PathLike, title: str, sections: Sequence[tuple[str, list[str]]]) -> str:
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
    ]
    for heading, body in sections:
        if heading:
            parts.append(f"<h2>{html.escape(heading)}</h2>")
        parts.extend(body)
    parts.append("</body></html>")
    path = os.fspath(path)
    with atomic_path(path, suffix=".html.tmp") as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write("\n".join(parts) + "\n")
    logger.info("report written: %s", path)
    return path


def _stamp() -> dict:
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return {"written": now, "aocontrol": __version__}


# ----------------------------------------------------------------------------- shared parts
def modal_margins(plant: Any, bank: Any) -> list[Margins] | None:
    """Margins of every mode of a bank (:func:`aocontrol.analysis.margins`), or ``None``.

    Parameters
    ----------
    plant : control.TransferFunction
        Loop plant.
    bank : ControllerBank
        Controller bank.

    Returns
    -------
    list of Margins or None
        One per mode; ``None`` for a bank without a transfer function (a constrained MPC).
    """
    try:
        return [margins(plant, bank, mode=i) for i in range(bank.n_modes)]
    except (NotImplementedError, TypeError) as exc:
        logger.info("no margins for %r: %s", bank, exc)
        return None


def _margin_summary(mar: Sequence[Margins] | None) -> dict:
    """Stable modes and the worst margins over the modes (NaN when unknown).

    The worst of each side: the gain can rise least (``gm``) and fall least (``gm_down``,
    closest to 0 dB), the smallest phase margin over every crossover, the least latency that
    can be added (``dm``) and removed (``dm_removed``).
    """
    keys = ("gm", "gm_down", "pm", "mm", "mm_med", "dm", "dm_removed")
    if not mar:
        return {"stable": "n/a", **dict.fromkeys(keys, math.nan)}
    mm = np.array([m.modulus_margin for m in mar])
    return {
        "stable": f"{sum(bool(m.stable) for m in mar)}/{len(mar)}",
        "gm": min(m.gain_margin_db for m in mar),
        "gm_down": max(m.gain_margin_down_db for m in mar),
        "pm": min(m.phase_margin for m in mar),
        "mm": float(mm.min()),
        "mm_med": float(np.median(mm)),
        "dm": min(m.delay_margin for m in mar),
        "dm_removed": min(m.delay_margin_removed for m in mar),
    }


_MARGIN_COLUMNS: list[Column] = [
    ("stable", "stable modes", ""),
    ("gm_down", "GM down [dB]", ".2f"),
    ("gm", "GM up [dB]", ".2f"),
    ("pm", "min PM [deg]", ".1f"),
    ("mm", "min MM [1]", ".3f"),
    ("mm_med", "median MM [1]", ".3f"),
    ("dm_removed", "latency removable [frames]", ".2f"),
    ("dm", "latency addable [frames]", ".2f"),
]


def representative_modes(n_modes: int, extra: Sequence[int] = ()) -> list[int]:
    """Modes shown on the rejection figure: the first, ``extra``, the middle and the last.

    Parameters
    ----------
    n_modes : int
        Number of modes (> 0).
    extra : sequence of int
        Modes that must be shown (e.g. a vibration's), kept in range.

    Returns
    -------
    list of int
        Sorted, distinct, at most four.

    Examples
    --------
    >>> representative_modes(400, extra=[1])
    [0, 1, 200, 399]
    >>> representative_modes(1)
    [0]
    """
    if n_modes < 1:
        raise ValueError(f"n_modes must be >= 1, got {n_modes}")
    picks = [0, *[int(e) for e in extra if 0 <= int(e) < n_modes], n_modes // 2, n_modes - 1]
    return sorted(dict.fromkeys(picks))[:_MAX_REJECTION_MODES]


def _sensitivities(plant: Any, banks: Mapping[str, Any], freqs: np.ndarray) -> dict:
    """``{label: S (n_modes, n_f)}`` of the banks with a transfer function."""
    out = {}
    for label, bank in banks.items():
        try:
            out[label] = np.atleast_2d(loop_response(plant, bank, freqs).sensitivity)
        except (NotImplementedError, TypeError) as exc:
            logger.info("no sensitivity for %s: %s", label, exc)
    return out


def _rejection_figure(
    freqs: np.ndarray,
    psd: np.ndarray,
    sens: Mapping[str, np.ndarray],
    modes: Sequence[int],
    title: str,
    unit: str = "nm",
) -> str:
    from aocontrol.study import plot

    panels = {f"mode {i}": {k: s[i] for k, s in sens.items()} for i in modes}
    psds = {f"mode {i}": psd[i] for i in modes}
    return _figure(
        lambda: plot.plot_rejection_modes(freqs, panels, psds, unit=unit),
        f"{title}: |S|^2 of each controller (left axis, dB) over the mode's disturbance PSD "
        f"(dashed, right axis, {unit}^2/Hz), modes " + ", ".join(str(i) for i in modes),
    )
