"""The main job's short demo, in two parts.

1. :func:`run_demo`: design an integrator, the optimal-gain integrator and the data-driven
   controller for one SAXO+ stage-2 mode, check margins, compare with the Wiener bound, write
   the rejection plot (seconds).
2. :func:`demo_comparison`: the paper's protocol on a case where the controllers differ as in
   the paper: "red 1 fast" (0.7" seeing, tau0 = 2 ms, stage 1 at 300 Hz), standalone cascade,
   stage 2 with :data:`DEMO_STAGE2_MODES` of its 540 modes so that the 4-6 lambda/D region is
   corrected (the quick scene's 24 modes leave it to the fitting error, and every controller
   gives the same contrast), 1-s exposures (the paper: 5 s). About a minute on 2 cores; the
   paper's ordering shows: reference integrator, then optimised modal gains, then the
   data-driven controller, best in contrast by about 30 %.

Run with ``python -m aocontrol demo --output DIR`` (or ``make demo``).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any

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

__all__ = [
    "DEMO_CASE",
    "DEMO_GAIN_GRID",
    "DEMO_SCHEME",
    "DEMO_SECONDS",
    "DEMO_STAGE2_MODES",
    "DemoResult",
    "demo_comparison",
    "run_demo",
]

logger = logging.getLogger(__name__)

#: Case of the demo's comparison: fast wind, where the temporal error dominates the contrast.
DEMO_CASE = "red1-fast"
#: Stage-2 modes of the demo's comparison (the case has 540; 120 reach past 6 lambda/D).
DEMO_STAGE2_MODES = 120
#: The demo's scheme, exposure [s] and reference gains scanned.
DEMO_SCHEME = "standalone"
DEMO_SECONDS = 1.0
DEMO_GAIN_GRID = (0.2, 0.3, 0.4, 0.5)


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


def demo_comparison(
    output: str | os.PathLike | None,
    *,
    case: str | os.PathLike = DEMO_CASE,
    stage2_modes: int = DEMO_STAGE2_MODES,
    seconds: float = DEMO_SECONDS,
    progress: bool = False,
) -> Any:
    """The demo's comparison: reference integrator, optimised modal gains and data-driven.

    Parameters
    ----------
    output : str or os.PathLike or None
        Folder of the results files (one per controller; ``None``: none written).
    case : str or os.PathLike
        Case name or TOML file (default :data:`DEMO_CASE`).
    stage2_modes : int
        Stage-2 modes simulated and controlled (at most the case's).
    seconds : float
        Exposure [s] after the case's start-up.
    progress : bool
        Progress bars on the exposures.

    Returns
    -------
    CaseComparison
        As :func:`aocontrol.study.compare.compare_case` (one scheme, :data:`DEMO_SCHEME`).
    """
    from aocontrol.study.cases import apply_overrides, load_case
    from aocontrol.study.compare import compare_case

    c = load_case(case)
    if stage2_modes < c.stage2.n_modes:
        c = apply_overrides(c, {"stage2.n_modes": int(stage2_modes)})
    return compare_case(
        c,
        schemes=(DEMO_SCHEME,),
        seconds=seconds,
        gain_grid=DEMO_GAIN_GRID,
        results_dir=output,
        progress=progress,
    )
