"""Plots (the only module of the project that imports matplotlib).

Each function takes data (arrays, result objects), draws on a given ``matplotlib.axes.Axes``
or a new figure, and returns the :class:`matplotlib.figure.Figure`; with ``path=`` it also
writes a PNG (and closes the figure in pyplot, so that long sweeps do not keep figures alive).
Nothing is shown, and no backend is chosen here: the command line selects ``Agg``, notebooks
keep theirs.

Conventions: frequencies in Hz on log axes (0 Hz dropped), PSDs one-sided [nm^2/Hz],
separations in lambda/D, contrast relative to the star's peak.
"""

from __future__ import annotations

import io
import os
from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import MaxNLocator

__all__ = [
    "plot_rejection",
    "plot_sensitivity",
    "plot_residual_psd",
    "plot_contrast",
    "plot_images",
    "plot_margins",
    "plot_vibration",
    "plot_modal_margins",
    "plot_modal_residuals",
    "plot_adapt",
    "plot_rejection_modes",
    "figure_png",
    "save_figure",
    "use_file_backend",
    "plot_robustness",
]

# Floor of |S|, |T| before taking dB (a perfect zero would be -inf on the axis).
_DB_FLOOR = 1e-12
# Lowest level shown on a dB axis: deep notches (|T| = 0 at Nyquist for a half-frame latency)
# would otherwise squash the useful range.
_DB_AXIS_FLOOR = -80.0
# Contrast axis: its bottom is this factor times the lowest contrast beyond the inner radius
# [lambda/D] (inside it the perfect coronagraph leaves ~1e-14, which would flatten the halo).
_CONTRAST_INNER_LD = 1.0
# Disturbance-PSD axis of the rejection plot: at most this far below the PSD's peak.
_PSD_AXIS_RANGE = 1e-7
_CONTRAST_AXIS_MARGIN = 0.3


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


def _profile(item: Any) -> tuple[np.ndarray | None, np.ndarray]:
    sci = getattr(item, "science", item)
    if hasattr(sci, "contrast_profile"):
        return np.asarray(sci.radii_ld), np.asarray(sci.contrast_profile)
    return None, np.asarray(item, dtype=float)


def plot_contrast(
    radii_ld: np.ndarray | None,
    profiles: Mapping[str, Any],
    *,
    ax: Any = None,
    title: str | None = None,
    path: str | os.PathLike | None = None,
) -> Any:
    """Plot raw-contrast radial profiles against separation [lambda/D] (log contrast axis).

    Parameters
    ----------
    radii_ld : ndarray, shape (n,), or None
        Separations [lambda/D]; ``None`` when every profile is a result with its own radii.
    profiles : mapping label -> ndarray (n,), ScienceResult or run result
        Raw contrast (relative to the star's peak), or objects with a ``science`` /
        ``contrast_profile`` (``ScienceResult``, ``LoopResult``, ``CascadeResult``).
    ax : matplotlib Axes, optional
        Axes to draw on (default: a new figure).
    title : str, optional
        Axes title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig, ax = _axes(ax)
    lows = []
    for label, item in profiles.items():
        r, prof = _profile(item)
        if r is None and radii_ld is not None:
            r = np.asarray(radii_ld, dtype=float)
        if r is None or r.shape != prof.shape:
            raise ValueError(
                f"profiles[{label!r}] has shape {prof.shape}; radii_ld must give one "
                f"separation per bin"
            )
        ax.semilogy(r, prof, label=label)
        outer = prof[(r >= _CONTRAST_INNER_LD) & np.isfinite(prof) & (prof > 0)]
        if outer.size:
            lows.append(float(outer.min()))
    if lows:
        # The perfect coronagraph leaves ~0 at the star: scale the axis on the halo.
        ax.set_ylim(bottom=_CONTRAST_AXIS_MARGIN * min(lows))
    ax.axvspan(4.0, 6.0, color="0.9", zorder=0)
    ax.set_xlabel(r"separation [$\lambda/D$]")
    ax.set_ylabel("raw contrast [star peak = 1]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    if title:
        ax.set_title(title)
    return _finish(fig, path)


def plot_images(
    images: Mapping[str, np.ndarray],
    *,
    pixel_scale: float,
    floor: float = 1e-8,
    title: str | None = None,
    path: str | os.PathLike | None = None,
) -> Any:
    """Show PSF and coronagraphic images side by side on a log colour scale.

    Parameters
    ----------
    images : mapping label -> ndarray (n, n)
        Images normalised to the star's (diffraction-limited) peak, e.g. ``{"PSF":
        exposure.psf, "coronagraph": exposure.coronagraphic}``, centred on the star.
    pixel_scale : float
        Pixel size [lambda/D] (``ScienceCamera.pixel_scale``).
    floor : float
        Lowest value shown (log scale; smaller values are clipped to it).
    title : str, optional
        Figure title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.colors import LogNorm

    if not images:
        raise ValueError("images must hold at least one image")
    if not pixel_scale > 0:
        raise ValueError(f"pixel_scale must be > 0 [lambda/D], got {pixel_scale!r}")
    fig, axes = plt.subplots(
        1, len(images), figsize=(4.2 * len(images), 4.0), constrained_layout=True, squeeze=False
    )
    for ax, (label, img) in zip(axes[0], images.items(), strict=True):
        img = np.asarray(img, dtype=float)
        if img.ndim != 2:
            raise ValueError(f"images[{label!r}] must be 2-D, got shape {img.shape}")
        half_x = img.shape[1] * pixel_scale / 2
        half_y = img.shape[0] * pixel_scale / 2
        vmax = max(float(img.max()), floor * 10)
        im = ax.imshow(
            np.maximum(img, floor),
            origin="lower",
            norm=LogNorm(floor, vmax),
            extent=(-half_x, half_x, -half_y, half_y),
            cmap="inferno",
        )
        ax.set_xlabel(r"x [$\lambda/D$]")
        ax.set_ylabel(r"y [$\lambda/D$]")
        ax.set_title(label)
        fig.colorbar(im, ax=ax, label="intensity [star peak = 1]", shrink=0.85)
    if title:
        fig.suptitle(title)
    return _finish(fig, path)


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
    title: str | None = None,
    path: str | os.PathLike | None = None,
) -> Any:
    """Gain retained under model errors: a panel per (case, error), a line per controller.

    Parameters
    ----------
    rows : sequence of mapping
        One per run: ``case``, ``error`` (``"nominal"`` for the reference point), ``magnitude``
        (the error's size, in its own unit), ``controller``, ``status`` (``"ok"`` or
        ``"diverged"``) and ``retained`` (the fraction of the nominal gain over the reference
        integrator that remains). A diverged run is a red cross at 0.
    title : str, optional
        Figure title.
    path : str or os.PathLike, optional
        Also write the figure to this PNG file.

    Returns
    -------
    matplotlib.figure.Figure
    """
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
                y = np.array([r["retained"] if r["status"] == "ok" else np.nan for _, r in pts])
                ax.plot(x, y, "o-", ms=3, lw=1.0, color=colors[c],
                        label=c if (i, j) == (0, 0) else None)  # fmt: skip
                bad = np.array([r["status"] != "ok" for _, r in pts])
                if bad.any():
                    ax.plot(x[bad], np.zeros(bad.sum()), "x", color="r", ms=8)
            ax.axhline(1.0, color="k", lw=0.6, ls=":")
            ax.set_title(f"{case}: {err}", fontsize="small")
            ax.set_xlabel("error magnitude")
            ax.set_ylabel("gain retained [1]")
            ax.grid(True, alpha=0.3)
    fig.legend(loc="outside lower center", ncol=min(len(ctrls), 6), fontsize="small")
    if title:
        fig.suptitle(title)
    return _finish(fig, path)
