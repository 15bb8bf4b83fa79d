"""Plots: the public names of the plotting functions.

They live in private modules by topic, the only modules of the project that import matplotlib:
frequency-domain plots (``_plot_frequency``), science images and contrast (``_plot_science``),
margins and residuals per controller and mode (``_plot_margins``), the studies' tables
(``_plot_studies``), and the shared axes and saving helpers (``_plot_common``).

Each function takes data (arrays, result objects), draws on a given ``matplotlib.axes.Axes``
or a new figure, and returns the :class:`matplotlib.figure.Figure`; with ``path=`` it also
writes a PNG (and closes the figure in pyplot, so that long sweeps do not keep figures alive).
Nothing is shown, and no backend is chosen here: the command line selects ``Agg``, notebooks
keep theirs.

Conventions: frequencies in Hz on log axes (0 Hz dropped), PSDs one-sided [nm^2/Hz],
separations in lambda/D, contrast relative to the star's peak.
"""

from aocontrol.study._plot_common import figure_png, save_figure, use_file_backend
from aocontrol.study._plot_frequency import (
    plot_rejection,
    plot_rejection_modes,
    plot_residual_psd,
    plot_sensitivity,
    plot_vibration,
)
from aocontrol.study._plot_margins import plot_margins, plot_modal_margins, plot_modal_residuals
from aocontrol.study._plot_science import plot_contrast, plot_images
from aocontrol.study._plot_studies import plot_adapt, plot_robustness

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
