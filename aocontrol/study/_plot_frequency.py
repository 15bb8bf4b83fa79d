"""Frequency-domain plots: rejection, sensitivity, residual PSDs, the vibration case.

Private module of :mod:`aocontrol.study.plot` (its public names are there). Frequencies in Hz
on log axes (0 Hz dropped), PSDs one-sided [unit^2/Hz].
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import matplotlib.pyplot as plt
import numpy as np

from aocontrol.study._plot_common import _axes, _db, _finish, _floor_db_axis, _positive

# Disturbance-PSD axis of the rejection plot: at most this far below the PSD's peak.
_PSD_AXIS_RANGE = 1e-7


def plot_rejection(
    freqs: np.ndarray,
    sensitivities: Mapping[str, np.ndarray],
    *,
    psd: np.ndarray | None = None,
    ax: Any = None,
    title: str | None = None,
    path: str | os.PathLike | None = None,
    unit: str = "nm",
) -> Any:
    """Plot ``|S|^2`` [dB] of several controllers, with the disturbance PSD on a twin axis.

    Parameters
    ----------
    freqs : ndarray, shape (n,)
        Frequencies [Hz] (the zero frequency is dropped on the log axis).
    sensitivities : mapping label -> complex ndarray (n,)
        Sensitivity functions ``S`` on ``freqs``.
    psd : ndarray (n,), optional
        Disturbance PSD, one-sided [unit^2/Hz].
    ax : matplotlib Axes, optional
        Axes to draw on (default: a new figure).
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
    fig, ax = _axes(ax)
    freqs, keep = _positive(freqs)
    for label, S in sensitivities.items():
        ax.semilogx(freqs[keep], _db(np.asarray(S)[keep]), label=label)
    ax.axhline(0.0, color="0.6", lw=0.8)
    _floor_db_axis(ax)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(r"$|S|^2$ [dB]")
    ax.grid(True, which="both", alpha=0.3)
    if psd is not None:
        ax2 = ax.twinx()
        ax2.loglog(
            freqs[keep],
            np.asarray(psd)[keep],
            color="0.5",
            ls="--",
            lw=1.0,
            label="disturbance PSD",
        )
        ax2.set_ylabel(rf"disturbance PSD [{unit}$^2$/Hz]")
        ax2.legend(loc="lower right", fontsize="small")
        peak = float(np.nanmax(np.asarray(psd)[keep], initial=0.0))
        if peak > 0 and ax2.get_ylim()[0] < peak * _PSD_AXIS_RANGE:
            # An estimate floored where it fell below the noise dives by decades: keep the
            # axis on the part that the rejection acts on.
            ax2.set_ylim(bottom=peak * _PSD_AXIS_RANGE)
    ax.legend(loc="upper left", fontsize="small")
    if title:
        ax.set_title(title)
    return _finish(fig, path)


def plot_sensitivity(
    freqs: np.ndarray,
    sensitivities: Mapping[str, np.ndarray],
    *,
    complementary: Mapping[str, np.ndarray] | None = None,
    disturbance_psd: np.ndarray | None = None,
    noise_psd: float | np.ndarray | None = None,
    modulus_margin: float | None = None,
    title: str | None = None,
    path: str | os.PathLike | None = None,
    unit: str = "nm",
) -> Any:
    """Sensitivity ``|S|`` and complementary sensitivity ``|T|`` [dB] over the disturbance PSD.

    Two panels sharing the frequency axis: top ``|S|`` (disturbance rejection) with the
    disturbance PSD on a twin log axis; bottom ``|T|`` (noise propagation) with the noise PSD.

    Parameters
    ----------
    freqs : ndarray, shape (n,)
        Frequencies [Hz] (0 Hz dropped on the log axis).
    sensitivities : mapping label -> complex ndarray (n,)
        ``S = 1 / (1 + G K)`` of each controller on ``freqs``.
    complementary : mapping label -> complex ndarray (n,), optional
        ``T = G K / (1 + G K)``; default ``1 - S`` (exact for the loop ``S + T = 1``).
    disturbance_psd : ndarray (n,), optional
        One-sided disturbance PSD [unit^2/Hz].
    noise_psd : float or ndarray (n,), optional
        One-sided measurement-noise PSD [unit^2/Hz].
    unit : str, default "nm"
        Unit of the telemetry (the PSD axes' ``unit^2/Hz``).
    modulus_margin : float, optional
        Draw the bound ``|S| < 1 / modulus_margin`` (dimensionless, in (0, 1]).
    title : str, optional
        Figure title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    freqs, keep = _positive(freqs)
    fig, (ax_s, ax_t) = plt.subplots(2, 1, sharex=True, figsize=(7.0, 6.5), constrained_layout=True)
    comp = complementary or {k: 1.0 - np.asarray(S) for k, S in sensitivities.items()}
    for label, S in sensitivities.items():
        ax_s.semilogx(freqs[keep], _db(np.asarray(S)[keep]), label=label)
    for label, T in comp.items():
        ax_t.semilogx(freqs[keep], _db(np.asarray(T)[keep]), label=label)
    if modulus_margin is not None:
        ax_s.axhline(
            _db(np.array(1.0 / modulus_margin)),
            color="r",
            ls=":",
            lw=1.0,
            label=f"1/modulus margin ({modulus_margin:g})",
        )
    for ax, name in ((ax_s, r"$|S|$ [dB]"), (ax_t, r"$|T|$ [dB]")):
        ax.axhline(0.0, color="0.6", lw=0.8)
        _floor_db_axis(ax)
        ax.set_ylabel(name)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper left", fontsize="small")
    ax_t.set_xlabel("frequency [Hz]")
    for ax, spec, name in ((ax_s, disturbance_psd, "disturbance"), (ax_t, noise_psd, "noise")):
        if spec is None:
            continue
        twin = ax.twinx()
        twin.loglog(
            freqs[keep],
            np.broadcast_to(np.asarray(spec, dtype=float), freqs.shape)[keep],
            color="0.5",
            ls="--",
            lw=1.0,
            label=f"{name} PSD",
        )
        twin.set_ylabel(rf"{name} PSD [{unit}$^2$/Hz]")
        twin.legend(loc="lower right", fontsize="small")
    if title:
        fig.suptitle(title)
    return _finish(fig, path)


def plot_residual_psd(
    freqs: np.ndarray,
    psds: Mapping[str, np.ndarray],
    *,
    ax: Any = None,
    title: str | None = None,
    path: str | os.PathLike | None = None,
    unit: str = "nm",
) -> Any:
    """Plot one-sided PSDs [unit^2/Hz] (e.g. open loop and each controller's residual), log-log.

    Parameters
    ----------
    freqs : ndarray, shape (n,)
        Frequencies [Hz] (0 Hz dropped on the log axis).
    psds : mapping label -> ndarray (n,) or (n_modes, n)
        One-sided PSDs [unit^2/Hz]; a 2-D array is summed over modes (the PSD of the total
        residual of those modes).
    ax : matplotlib Axes, optional
        Axes to draw on (default: a new figure).
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
    fig, ax = _axes(ax)
    freqs, keep = _positive(freqs)
    for label, p in psds.items():
        p = np.asarray(p, dtype=float)
        p = p.sum(axis=0) if p.ndim == 2 else p
        ax.loglog(freqs[keep], p[keep], label=label)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(rf"PSD [{unit}$^2$/Hz]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    if title:
        ax.set_title(title)
    return _finish(fig, path)


def plot_vibration(
    freqs: np.ndarray,
    tilt_psds: Mapping[str, np.ndarray],
    *,
    open_loop_psd: np.ndarray | None = None,
    vibration_hz: float | None = None,
    title: str | None = None,
    path: str | os.PathLike | None = None,
) -> Any:
    """Vibration case: tilt residual PSDs per controller and their reverse cumulative RMS.

    Left: one-sided PSDs [nm^2/Hz] (log-log), with the open-loop tilt PSD and the vibration
    frequency marked. Right: ``sqrt(integral_f^{fs/2} PSD)`` [nm RMS] against ``f``, which
    shows how much of each controller's residual sits at the vibration.

    Parameters
    ----------
    freqs : ndarray, shape (n,)
        Frequencies [Hz].
    tilt_psds : mapping label -> ndarray (n,)
        Residual tilt PSD of each controller, one-sided [nm^2/Hz].
    open_loop_psd : ndarray (n,), optional
        Open-loop (disturbance) tilt PSD [nm^2/Hz].
    vibration_hz : float, optional
        Vibration frequency [Hz] (a vertical line on both panels).
    title : str, optional
        Figure title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    freqs, keep = _positive(freqs)
    fig, (ax_p, ax_c) = plt.subplots(1, 2, figsize=(12.0, 4.5), constrained_layout=True)
    series = dict(tilt_psds)
    if open_loop_psd is not None:
        series = {"open loop": open_loop_psd, **series}
    for label, p in series.items():
        p = np.asarray(p, dtype=float)
        if p.shape != freqs.shape:
            raise ValueError(f"tilt_psds[{label!r}] must have shape {freqs.shape}, got {p.shape}")
        style = {"color": "0.5", "ls": "--"} if label == "open loop" else {}
        ax_p.loglog(freqs[keep], p[keep], label=label, **style)
        # Reverse cumulative variance: trapezoid from f to fs/2.
        seg = 0.5 * (p[1:] + p[:-1]) * np.diff(freqs)
        rev = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])
        ax_c.semilogx(freqs[keep], np.sqrt(rev[keep]), label=label, **style)
    for ax in (ax_p, ax_c):
        if vibration_hz is not None:
            ax.axvline(
                vibration_hz, color="r", ls=":", lw=1.0, label=f"vibration {vibration_hz:g} Hz"
            )
        ax.set_xlabel("frequency [Hz]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize="small")
    ax_p.set_ylabel(r"tilt PSD [nm$^2$/Hz]")
    ax_c.set_ylabel(r"tilt RMS above $f$ [nm]")
    if title:
        fig.suptitle(title)
    return _finish(fig, path)


def plot_rejection_modes(
    freqs: np.ndarray,
    sensitivities: Mapping[str, Mapping[str, np.ndarray]],
    psds: Mapping[str, np.ndarray],
    *,
    title: str | None = None,
    path: str | os.PathLike | None = None,
    unit: str = "nm",
) -> Any:
    """One :func:`plot_rejection` panel per mode: ``|S|^2`` of each controller over its PSD.

    Parameters
    ----------
    freqs : ndarray, shape (n,)
        Frequencies [Hz].
    sensitivities : mapping panel label -> (mapping controller label -> complex ndarray (n,))
        ``S`` of each controller for the mode of each panel (e.g. ``{"mode 0": {...}}``).
    psds : mapping panel label -> ndarray (n,)
        Disturbance PSD of each panel's mode, one-sided [unit^2/Hz] (same keys).
    title : str, optional
        Figure title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.
    unit : str, default "nm"
        Unit of the telemetry (axis labels: ``unit^2/Hz``, ``unit RMS``).

    Returns
    -------
    matplotlib.figure.Figure
    """
    if not sensitivities:
        raise ValueError("sensitivities must hold at least one mode")
    n = len(sensitivities)
    cols = 1 if n == 1 else 2
    rows = -(-n // cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(7.0 * cols, 4.0 * rows), constrained_layout=True, squeeze=False
    )
    for ax, (label, sens) in zip(axes.flat[:n], sensitivities.items(), strict=True):
        plot_rejection(freqs, sens, psd=psds.get(label), ax=ax, title=label, unit=unit)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    return _finish(fig, path)
