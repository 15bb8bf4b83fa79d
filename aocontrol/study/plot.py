"""Plots (the only module of the project that imports matplotlib).

Each function draws on a given ``matplotlib.axes.Axes`` (or creates a figure) and returns the
figure; nothing is shown or saved here.
"""

from __future__ import annotations

from collections.abc import Mapping

import matplotlib.pyplot as plt
import numpy as np

__all__ = ["plot_rejection", "plot_residual_psd", "plot_contrast", "save_figure"]


def _axes(ax):
    if ax is None:
        fig, ax = plt.subplots(figsize=(7.0, 4.5), constrained_layout=True)
        return fig, ax
    return ax.figure, ax


def plot_rejection(
    freqs: np.ndarray,
    sensitivities: Mapping[str, np.ndarray],
    *,
    psd: np.ndarray | None = None,
    ax=None,
    title: str | None = None,
):
    """Plot ``|S|^2`` [dB] of several controllers, with the disturbance PSD on a twin axis.

    Parameters
    ----------
    freqs : ndarray, shape (n,)
        Frequencies [Hz] (the zero frequency is dropped on the log axis).
    sensitivities : mapping label -> complex ndarray (n,)
        Sensitivity functions ``S`` on ``freqs``.
    psd : ndarray (n,), optional
        Disturbance PSD, one-sided [nm^2/Hz].
    """
    fig, ax = _axes(ax)
    keep = freqs > 0
    for label, S in sensitivities.items():
        ax.semilogx(freqs[keep], 20 * np.log10(np.maximum(np.abs(S[keep]), 1e-12)), label=label)
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(r"$|S|^2$ [dB]")
    ax.grid(True, which="both", alpha=0.3)
    if psd is not None:
        ax2 = ax.twinx()
        ax2.loglog(freqs[keep], psd[keep], color="0.5", ls="--", lw=1.0, label="disturbance PSD")
        ax2.set_ylabel(r"disturbance PSD [nm$^2$/Hz]")
        ax2.legend(loc="lower right", fontsize="small")
    ax.legend(loc="upper left", fontsize="small")
    if title:
        ax.set_title(title)
    return fig


def plot_residual_psd(
    freqs: np.ndarray, psds: Mapping[str, np.ndarray], *, ax=None, title: str | None = None
):
    """Plot one-sided PSDs [nm^2/Hz] (e.g. open loop and residuals) on log-log axes.

    Parameters
    ----------
    freqs : ndarray, shape (n,)
        Frequencies [Hz] (0 Hz dropped on the log axis).
    psds : mapping label -> ndarray (n,)
        One-sided PSDs [nm^2/Hz].
    ax : matplotlib Axes, optional
    title : str, optional
    """
    fig, ax = _axes(ax)
    keep = freqs > 0
    for label, p in psds.items():
        ax.loglog(freqs[keep], p[keep], label=label)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(r"PSD [nm$^2$/Hz]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    if title:
        ax.set_title(title)
    return fig


def plot_contrast(
    radii_ld: np.ndarray, profiles: Mapping[str, np.ndarray], *, ax=None, title: str | None = None
):
    """Plot raw-contrast radial profiles against separation [lambda/D].

    Parameters
    ----------
    radii_ld : ndarray, shape (n,)
        Separations [lambda/D].
    profiles : mapping label -> ndarray (n,)
        Raw contrast (relative to the star's peak).
    ax : matplotlib Axes, optional
    title : str, optional
    """
    fig, ax = _axes(ax)
    for label, prof in profiles.items():
        ax.semilogy(radii_ld, prof, label=label)
    ax.axvspan(4.0, 6.0, color="0.9", zorder=0)
    ax.set_xlabel(r"separation [$\lambda/D$]")
    ax.set_ylabel("raw contrast")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    if title:
        ax.set_title(title)
    return fig


def save_figure(fig, path: str, *, dpi: int = 120) -> str:
    """Save ``fig`` to ``path`` and close it (frees memory in long sweeps); returns ``path``.

    Parameters
    ----------
    fig : matplotlib Figure
    path : str
        Output file (format from the extension).
    dpi : int
    """
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
