"""The main job's short demo: design an integrator, the optimal-gain integrator and the
data-driven controller for one SAXO+ stage-2 mode, check margins, compare with the Wiener
bound, write the rejection plot.

Run with ``python -m aocontrol demo --output DIR`` (or ``make demo``).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np

from aocontrol.analysis import (
    Margins,
    margins,
    residual_variance,
    sensitivity,
    white_noise_psd,
    wiener_bound,
)
from aocontrol.controllers import Integrator
from aocontrol.disturbance import synthetic_turbulence_psd
from aocontrol.plant import loop_plant
from aocontrol.study.plot import plot_rejection, save_figure
from aocontrol.synthesis import datadriven, optimal_modal_gain

__all__ = ["DemoResult", "run_demo"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemoResult:
    """What the demo designed and measured.

    Parameters
    ----------
    fs : float
        Loop rate [Hz].
    latency_frames : float
        RTC latency beyond the WFS integration [frames].
    controllers : dict of str -> ControllerBank
        The designed controllers, by label.
    margins : dict of str -> Margins
        Stability margins of each controller.
    residual_rms : dict of str -> float
        Predicted residual of each controller [nm RMS].
    wiener_rms : float
        Wiener bound: residual of the best causal linear predictor [nm RMS].
    plot_path : str
        The rejection plot written (PNG).
    """

    fs: float
    latency_frames: float
    controllers: dict
    margins: dict[str, Margins]
    residual_rms: dict[str, float]
    wiener_rms: float
    plot_path: str


def _demo_psd(freqs: np.ndarray, fs: float) -> np.ndarray:
    """Temporal PSD [nm^2/Hz] of a mid-order turbulent mode (mode 6 of the synthetic bank)."""
    return synthetic_turbulence_psd(freqs, 10, fs=fs)[5]


def run_demo(
    output: str, *, fs: float = 3000.0, latency_frames: float = 0.83, noise_rms: float = 2.0
) -> DemoResult:
    """Design an integrator for one mode of a SAXO+-like stage 2 and write its rejection plot.

    Parameters
    ----------
    output : str
        Folder for ``rejection.png`` (created if needed).
    fs : float
        Loop rate [Hz].
    latency_frames : float
        RTC latency beyond WFS integration [frames].
    noise_rms : float
        Modal measurement noise per frame [nm RMS].
    """
    plant = loop_plant(fs, latency_frames)
    # Log-spaced at low frequency so that the PSD (and the Wiener bound) are resolved.
    freqs = np.concatenate([[0.0], np.geomspace(1e-2, fs / 2, 2000)])
    psd = _demo_psd(freqs, fs)
    noise = float(white_noise_psd(noise_rms**2, fs))
    ctrls: dict = {"integrator g=0.5 (hand-tuned)": Integrator(0.5, fs=fs)}
    ctrls["optimal-gain integrator"] = optimal_modal_gain(
        plant, freqs, psd, noise, modulus_margin=0.5
    )
    ctrls["data-driven (order 5)"] = datadriven(
        plant, freqs, psd, noise_psd=noise, order=5, progress=False, n_jobs=1
    ).controller
    bound = float(wiener_bound(plant, freqs, psd, noise))
    mar = {k: margins(plant, c) for k, c in ctrls.items()}
    rms = {
        k: float(np.sqrt(np.atleast_1d(residual_variance(plant, c, freqs, psd, noise))[0]))
        for k, c in ctrls.items()
    }
    os.makedirs(output, exist_ok=True)
    fig = plot_rejection(
        freqs,
        {k: sensitivity(plant, c, freqs)[0] for k, c in ctrls.items()},
        psd=psd,
        title=f"rejection, fs = {fs:g} Hz, latency {latency_frames} frame",
    )
    path = save_figure(fig, os.path.join(output, "rejection.png"))
    return DemoResult(fs, latency_frames, ctrls, mar, rms, float(np.sqrt(bound)), path)
