"""Shared pieces of the command line (:mod:`aocontrol.study.cli`): its errors, names, tables
and output folders."""

from __future__ import annotations

import difflib
import os
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

#: Cascade schemes of ``run``.
RUN_SCHEMES = ("single", "standalone", "dcao")
# Fewest telemetry frames for a PSD estimate worth designing on (8 Welch segments of 16).
_MIN_TELEMETRY_FRAMES = 64
# Per-mode margins are printed up to this many modes, a min/median/max summary beyond.
_MAX_MODE_ROWS = 12


class UserError(Exception):
    """A mistake in the command line or its inputs: reported on stderr, exit status 2."""


class RunFailed(Exception):
    """A run that started and failed (e.g. a diverging loop): exit status 1."""


def run_controller_names() -> tuple[str, ...]:
    """The controller names ``run`` (and ``compare``, sweeps) accept: the registry's, then its
    aliases (:func:`aocontrol.synthesis.controller_names`, the one list), read when asked, so
    that a controller registered later is listed too."""
    from aocontrol.synthesis import controller_names

    return controller_names()


def _valid_name(kind: str, value: str, valid: Iterable[str]) -> str:
    valid = list(valid)
    if value in valid:
        return value
    close = difflib.get_close_matches(value, valid, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise UserError(f"unknown {kind} {value!r}{hint}; valid: {', '.join(valid)}")


def _format_table(rows: Sequence[dict], columns: Sequence[tuple[str, str, str]]) -> str:
    """Format ``rows`` as a fixed-width table; ``columns`` are (key, header, format)."""
    cells = [
        [
            (
                format(r[k], fmt)
                if isinstance(r.get(k), (int, float, np.number))
                else str(r.get(k, ""))
            )
            for k, _, fmt in columns
        ]
        for r in rows
    ]
    widths = [max([len(h)] + [len(c[i]) for c in cells]) for i, (_, h, _) in enumerate(columns)]
    lines = [
        "  ".join(
            h.rjust(w) if i else h.ljust(w)
            for i, ((_, h, _), w) in enumerate(zip(columns, widths, strict=True))
        )
    ]
    lines.append("-" * len(lines[0]))
    for c in cells:
        lines.append(
            "  ".join(
                x.rjust(w) if i else x.ljust(w)
                for i, (x, w) in enumerate(zip(c, widths, strict=True))
            )
        )
    return "\n".join(lines)


def _plot_module() -> Any:
    from aocontrol.study import plot

    plot.use_file_backend()  # files only: the command line never opens a window
    return plot


def _out_dir(path: str) -> str:
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {path!r}: cannot create the folder ({exc.strerror})") from exc
    return path


# Shown, documented and pickled under the command line module that exports them.
UserError.__module__ = RunFailed.__module__ = "aocontrol.study.cli"
