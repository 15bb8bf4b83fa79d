"""Shared pieces of the plots (private to :mod:`aocontrol.study.plot`): axes, dB, saving.

A plot module of the package (``plot`` and ``_plot_*``) is the only kind of module that imports
matplotlib (``tests/test_layers.py``).
"""

from __future__ import annotations

import io
import os
from typing import Any

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

# Floor of |S|, |T| before taking dB (a perfect zero would be -inf on the axis).
_DB_FLOOR = 1e-12
# Lowest level shown on a dB axis: deep notches (|T| = 0 at Nyquist for a half-frame latency)
# would otherwise squash the useful range.
_DB_AXIS_FLOOR = -80.0


def _axes(ax: Any, figsize: tuple[float, float] = (7.0, 4.5)) -> tuple[Any, Any]:
    if ax is None:
        fig, ax = plt.subplots(figsize=figsize, constrained_layout=True)
        return fig, ax
    return ax.figure, ax


def _finish(fig: Any, path: str | os.PathLike | None, dpi: int = 120) -> Any:
    if path is not None:
        save_figure(fig, os.fspath(path), dpi=dpi)
    return fig


def _db(x: np.ndarray) -> np.ndarray:
    return 20.0 * np.log10(np.maximum(np.abs(x), _DB_FLOOR))


def _floor_db_axis(ax: Any) -> None:
    lows = [np.nanmin(ln.get_ydata()) for ln in ax.get_lines() if len(ln.get_ydata()) > 1]
    if lows and min(lows) < _DB_AXIS_FLOOR:
        ax.set_ylim(bottom=_DB_AXIS_FLOOR)


def _positive(freqs: object) -> tuple[np.ndarray, np.ndarray]:
    f = np.asarray(freqs, dtype=float)
    if f.ndim != 1:
        raise ValueError(f"freqs must be 1-D [Hz], got shape {f.shape}")
    return f, f > 0


def figure_png(fig: Any, *, dpi: int = 96) -> bytes:
    """The PNG bytes of ``fig`` (then closed): figures embedded in an HTML report.

    Parameters
    ----------
    fig : matplotlib Figure
        Figure to encode.
    dpi : int
        Resolution [dots per inch].

    Returns
    -------
    bytes
        A complete PNG file.
    """
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return buf.getvalue()


def use_file_backend() -> None:
    """Select matplotlib's non-interactive ``Agg`` backend (the command line calls this).

    Library code never chooses a backend at import; a program that only writes files (the
    CLI, a batch job) calls this before drawing.
    """
    matplotlib.use("Agg")


def save_figure(fig: Any, path: str, *, dpi: int = 120) -> str:
    """Save ``fig`` to ``path`` and close it (frees memory in long sweeps); returns ``path``.

    Parameters
    ----------
    fig : matplotlib Figure
        Figure to write.
    path : str
        Output file (format from the extension).
    dpi : int
        Resolution [dots per inch].
    """
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
