"""Science-camera plots: raw-contrast profiles and PSF / coronagraphic images.

Private module of :mod:`aocontrol.study.plot` (its public names are there). Separations in
lambda/D, contrast relative to the star's peak.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import matplotlib.pyplot as plt
import numpy as np

from aocontrol.study._plot_common import _axes, _finish

# Contrast axis: its bottom is this factor times the lowest contrast beyond the inner radius
# [lambda/D] (inside it the perfect coronagraph leaves ~1e-14, which would flatten the halo).
_CONTRAST_INNER_LD = 1.0
_CONTRAST_AXIS_MARGIN = 0.3


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
