"""The paper's protocol: controllers compared on a science case, standalone and dCAO.

For each case and scheme, stage 1 keeps the reference integrator (the case's gain); stage 2
runs each registered controller (:data:`CONTROLLERS`):

* ``"reference"`` (alias ``"integrator"``): one gain for all modes, chosen by a gain scan for
  the best mean 4-6 lambda/D contrast (short runs, grid :data:`GAIN_GRID` below the
  stability limit of the stage-2 plant);
* ``"omgi"``: the optimised modal gain integrator (:func:`aocontrol.synthesis.
  optimal_modal_gain`, modulus margin 0.5);
* ``"datadriven"``: the 5th-order data-driven controller (:func:`aocontrol.synthesis.
  datadriven`, with the noise term, modulus margin 0.5);
* ``"lqg"`` and ``"mpc"`` (not in the paper's table, run on request): the LQG of
  :func:`aocontrol.synthesis.lqg` (AR(2) turbulence and resonances fitted to the telemetry
  PSD) and the MPC of :func:`aocontrol.synthesis.mpc` on the same model, each mode's command
  limited to the bound the stage's DM implies (:attr:`aocontrol.sim.dm.ModalDM.command_bound`
  of :meth:`aocontrol.study.scene.StageScene.modal_dm`).

The last two are designed from the simulator's own telemetry: a calibration run with the
reference integrator, whose pseudo-open loop goes through
:func:`aocontrol.synthesis.disturbance_from_telemetry` (pre-whitened against the window
leakage of the sub-hertz turbulence by default) -- never from the hidden disturbance.
Any controller joins through :func:`register_controller` with a :class:`ControllerSpec`
whose ``design`` maps :class:`DesignInputs` to a :class:`~aocontrol.controllers.ControllerBank`.

Each exposure discards the case's start-up (0.1 s) and integrates the science image over the
exposure (5 s) at 1.65 um.

Reuse: in both cascades stage 1 never sees stage 2, so the gain-scan runs, the two calibration
runs and the exposures of :func:`compare_case` each compute their stream's atmosphere, its
projection on both bases and stage 1 once, and replay them for the other stage-2 controllers
and the other scheme (:class:`aocontrol.sim.loop.UpstreamRecord`): every run's result is the
same bit for bit as a run alone (tested); the saving is measured in docs/benchmarks.md. Not
with a stage-2 sensor that reads phase maps (the diffractive one), nor with "two-pass"
optical gains.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from aocontrol._deprecation import deprecated_function
from aocontrol._version import __version__
from aocontrol.controllers import ControllerBank, Integrator, MultiModeBank
from aocontrol.sim.loop import UpstreamRecord
from aocontrol.study._calibration import calibrate_scene, calibration_seconds, design_inputs
from aocontrol.study._comparison import (
    CaseComparison,
    Cell,
    ResidualModel,
    predicted_residual,
    table_from_files,
    vibration_report,
)
from aocontrol.study._registry import (
    CONTROLLER_ALIASES,
    CONTROLLERS,
    MODULUS_MARGIN,
    ControllerSpec,
    DesignInputs,
    controller_names,
    get_controller,
    register_controller,
)
from aocontrol.study._seeds import seed_streams
from aocontrol.study._simulate import SCHEMES, UpstreamRecords, run_summary, simulate_scene
from aocontrol.study._two_pass import two_pass_scene
from aocontrol.study.cases import Case, apply_overrides, load_case
from aocontrol.study.scene import Scene, build_scene
from aocontrol.synthesis import (
    TelemetryPSD,
    disturbance_from_telemetry,
    integrator_gain_limit,
)

__all__ = [
    "CONTROLLERS",
    "CONTROLLER_ALIASES",
    "controller_names",
    "GAIN_GRID",
    "SCHEMES",
    "CaseComparison",
    "Cell",
    "ControllerSpec",
    "DesignInputs",
    "ResidualModel",
    "RunOutcome",
    "compare_case",
    "register_controller",
    "run_configuration",
    "prewhitened_disturbance",
    "table_from_files",
    "two_pass_scene",
]

logger = logging.getLogger(__name__)

#: Gains scanned for the reference integrator (those below the stage-2 stability limit).
GAIN_GRID = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)
#: Quick mode: fewer scan points.
QUICK_GAIN_GRID = (0.3, 0.5)
# Length of the gain-scan runs [s], and in quick mode (the calibration run's:
# aocontrol.study._calibration.calibration_seconds).
_SCAN_SECONDS, _QUICK_SCAN_SECONDS = 0.5, 0.2


@dataclass(frozen=True, eq=False)
class RunOutcome:
    """One configuration's run.

    Parameters
    ----------
    result : LoopResult or CascadeResult
    settings : dict
        JSON-serialisable: case name and values, controller and parameters, scheme, seconds,
        seed, package version.
    summary : dict
        ``strehl``, ``mean_contrast_4_6``, ``residual_rms_nm`` (stage-2 modal residual).
    controller : ControllerBank
        The stage-2 controller run.
    design : DesignInputs or None
        What it was designed from.
    """

    result: Any
    settings: dict
    summary: dict
    controller: ControllerBank | None = None
    design: DesignInputs | None = None


def _sensor_overrides(sensor: str | None, optical_gain: str | None) -> dict:
    """Case overrides of stage 2's sensor settings (validated by the case loader)."""
    out = {}
    if sensor is not None:
        out["stage2.sensor"] = sensor
    if optical_gain is not None:
        out["stage2.optical_gain"] = optical_gain
    return out


def _check_names(controller: str, scheme: str) -> ControllerSpec:
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {list(SCHEMES)}, got {scheme!r}")
    return get_controller(controller)


@deprecated_function(
    "aocontrol.study.compare.prewhitened_disturbance",
    "aocontrol.synthesis.disturbance_from_telemetry(m, u, plant, fs=fs) (its .psd)",
)
def prewhitened_disturbance(
    measurements: np.ndarray, commands: np.ndarray, plant: Any, fs: float
) -> tuple[TelemetryPSD, np.ndarray]:
    """Pre-whitened disturbance PSD: deprecated, now in the control layer.

    ``disturbance_from_telemetry(measurements, commands, plant, fs=fs)`` (whose default is
    the pre-whitened estimator) returned as ``(tel, tel.psd)``; use
    :func:`aocontrol.synthesis.disturbance_from_telemetry` directly.

    Parameters
    ----------
    measurements, commands : ndarray, shape (n_frames, n_modes)
        Closed-loop telemetry [nm].
    plant : control.TransferFunction
        Loop plant.
    fs : float
        Loop rate [Hz].

    Returns
    -------
    tel : TelemetryPSD
        The pre-whitened estimate.
    psd : ndarray, shape (n_modes, n_f)
        ``tel.psd`` [nm^2/Hz].
    """
    tel = disturbance_from_telemetry(measurements, commands, plant, fs=fs, method="prewhitened")
    return tel, tel.psd


def run_configuration(
    case: str | os.PathLike | Case,
    *,
    controller: str,
    scheme: str,
    seconds: float = 5.0,
    seed: int = 0,
    overrides: dict | None = None,
    quick: bool = False,
    progress: bool = False,
    design: DesignInputs | None = None,
    sensor: str | None = None,
    optical_gain: str | None = None,
    upstream: UpstreamRecord | None = None,
) -> RunOutcome:
    """Run one configuration: a case, a stage-2 controller and a scheme.

    Parameters
    ----------
    case : str, path or Case
        Case name (:func:`aocontrol.study.cases.list_cases`), TOML path or :class:`Case`.
    controller : str
        A registered name (:data:`CONTROLLERS`). The reference uses the case's stage-2 gain
        (override ``"stage2.gain"`` to change it).
    scheme : {"single", "standalone", "dcao"}
        ``single``: stage 2 alone on the full atmosphere.
    seconds : float
        Exposure after the case's start-up [s].
    seed : int
        User seed. The exposure draws the atmosphere and noise from its ``"exposure"``
        stream, the calibration run from its ``"calibration"`` stream
        (``SeedSequence([seed, purpose])``, :mod:`aocontrol.study._seeds`); the settings
        record both as ``seed_streams``.
    overrides : dict, optional
        Case values replaced, e.g. ``{"seeing": 0.6, "stage2.fs": 1500}``.
    quick : bool
        Quick scene (fewer modes) and short calibration run.
    progress : bool
        Progress bar on the exposure.
    design : DesignInputs, optional
        Reuse these design inputs instead of a new calibration run.
    sensor : {"linear", "diffractive"}, optional
        Stage 2's sensor in the loop (default the case's ``[stage2] sensor``, "linear").
    optical_gain : {"none", "calibrated", "tracked", "two-pass"}, optional
        Stage 2's optical-gain handling (default the case's, "calibrated"); "two-pass" first
        runs :func:`two_pass_scene` (its ``"two_pass"`` stream of ``seed``).
    upstream : UpstreamRecord, optional
        Upstream of the exposure (:class:`aocontrol.sim.loop.UpstreamRecord`), filled by the
        first configuration of a case, seed and length given it and replayed by the others
        (the same result bit for bit; :func:`compare_case` does this). A cascade only, with
        stage 2 reading modal residuals.

    Returns
    -------
    RunOutcome

    Raises
    ------
    ValueError
        Unknown case, controller or scheme (the message lists the valid ones), bad overrides.
    LoopDivergedError
        A stage diverged (named with the frame and the modes).
    """
    spec = _check_names(controller, scheme)
    if not (isinstance(seconds, (int, float)) and seconds > 0):
        raise ValueError(f"seconds must be > 0, got {seconds!r}")
    base = load_case(case)
    overrides = dict(overrides or {}, **_sensor_overrides(sensor, optical_gain))
    c = apply_overrides(base, overrides)
    scene = build_scene(c, quick=quick, progress=progress)
    gain = c.stage2.gain
    if c.stage2.optical_gain == "two-pass":
        cal = calibration_seconds(scene, quick)
        scene = two_pass_scene(scene, scheme, gain, seconds=cal, seed=seed)
    if design is None and spec.needs_telemetry:
        cal = calibration_seconds(scene, quick)
        design = design_inputs(scene, scheme, gain, seconds=cal, seed=seed, progress=progress)
    if design is None:
        st = scene.stage2
        design = DesignInputs(
            st.plant,
            np.zeros(0),
            np.zeros((st.n_modes, 0)),
            np.zeros(st.n_modes),
            st.fs,
            st.n_modes,
            float(gain),
        )
    if progress and "progress" in spec.options and "progress" not in design.options:
        # A bar over the modes of a long design (the data-driven bank: a minute at 540 modes).
        design = dataclasses.replace(design, options={**design.options, "progress": True})
    t0 = time.perf_counter()
    ctrl = spec.design(design)
    t_design = time.perf_counter() - t0
    settings = {
        "case": c.name,
        "case_values": c.to_dict(),
        "overrides": dict(overrides or {}),
        "controller": {"name": spec.name, "parameters": spec.parameters, "repr": repr(ctrl)},
        "reference_gain": float(gain),
        "scheme": scheme,
        "seconds": float(seconds),
        "seed": int(seed),
        "seed_streams": seed_streams(
            seed,
            ("exposure",)
            + (("calibration",) if spec.needs_telemetry else ())
            + (("two_pass",) if c.stage2.optical_gain == "two-pass" else ()),
        ),
        "quick": bool(quick),
        "scene": scene.settings(),
        "version": __version__,
    }
    t0 = time.perf_counter()
    res = simulate_scene(
        scene,
        ctrl,
        scheme,
        seconds,
        seed,
        "exposure",
        progress=progress,
        metadata=settings,
        upstream=upstream,
    )
    summary = run_summary(res)
    summary.update(design_seconds=t_design, run_seconds=time.perf_counter() - t0)
    return RunOutcome(res, settings, summary, ctrl, design)


# ----------------------------------------------------------------------------- protocol
def _scan_grid(scene: Scene, quick: bool, grid: Sequence[float] | None) -> list[float]:
    grid = list(grid if grid is not None else (QUICK_GAIN_GRID if quick else GAIN_GRID))
    limit = integrator_gain_limit(scene.stage2.plant, modulus_margin=MODULUS_MARGIN)
    keep = [g for g in grid if 0 < g < limit]
    if not keep:
        raise ValueError(f"no scan gain below the stability limit {limit:.3f}: grid {grid}")
    return keep


def _predicted(
    ctrl: ControllerBank,
    design: DesignInputs,
    model: ResidualModel | None,
    calibration: float,
    exposure: float,
) -> tuple[float, float, float]:
    """Predicted RMS [nm] and the relative standard errors of the prediction (a
    ``calibration``-second record) and of an ``exposure``-second measurement (NaN without
    telemetry, and for a multi-mode controller: it uses the modes' cross-spectra, which the
    per-mode PSDs of the prediction do not hold)."""
    if isinstance(ctrl, MultiModeBank):
        return math.nan, math.nan, math.nan
    if model is not None:
        rms, rel = model.predicted(design.plant, ctrl, (calibration, exposure))
    elif design.freqs.size == 0:
        return math.nan, math.nan, math.nan
    else:
        rms, rel = predicted_residual(
            design.plant, ctrl, design.freqs, design.psd, design.noise_psd,
            seconds=(calibration, exposure),
        )  # fmt: skip
    return rms, rel[0], rel[1]


def _save(outcome: RunOutcome, directory: str | None, name: str) -> str | None:
    if directory is None:
        return None
    from aocontrol.study.results import save_result  # h5py only when files are written

    os.makedirs(directory, exist_ok=True)
    path = os.path.join(directory, f"{name}.h5")
    return save_result(outcome.result, path, settings=outcome.settings)


def compare_case(
    case: str | os.PathLike | Case,
    *,
    controllers: Sequence[str] = ("reference", "omgi", "datadriven"),
    schemes: Sequence[str] = ("standalone", "dcao"),
    seconds: float | None = None,
    seed: int = 0,
    quick: bool = False,
    gain_grid: Sequence[float] | None = None,
    results_dir: str | os.PathLike | None = None,
    progress: bool = False,
    sensor: str | None = None,
    optical_gain: str | None = None,
    estimator: str = "prewhitened",
    overrides: dict | None = None,
) -> CaseComparison:
    """The paper's protocol on one case (module docstring).

    Parameters
    ----------
    case : str, path or Case
    controllers : sequence of str
        Registered names, run on stage 2 in this order.
    schemes : sequence of str
        Among :data:`SCHEMES`.
    seconds : float, optional
        Exposure [s]; default the case's (5 s), 0.5 s in quick mode.
    seed : int
        User seed: exposures, the calibration run and the gain scan draw from its
        ``"exposure"``, ``"calibration"`` and ``"gain_scan"`` streams
        (``SeedSequence([seed, purpose])``, :mod:`aocontrol.study._seeds`).
    quick : bool
        Quick scene, scan grid :data:`QUICK_GAIN_GRID`, short runs.
    gain_grid : sequence of float, optional
        Reference gains scanned (default :data:`GAIN_GRID`).
    results_dir : path, optional
        Write one results file per configuration there (:mod:`aocontrol.study.results`).
    progress : bool
        Log progress at INFO level and show bars on the exposures.
    sensor, optical_gain : str, optional
        Stage 2's sensor and optical-gain handling (:func:`run_configuration`); the gain scan,
        calibration run and exposures all use them.
    estimator : {"prewhitened", "welch"}
        Disturbance estimator of the calibration telemetry
        (:func:`aocontrol.synthesis.disturbance_from_telemetry`).
    overrides : dict, optional
        Case values replaced for every run (:func:`aocontrol.study.cases.apply_overrides`),
        e.g. a model error ``{"stage2.latency_error": 0.3}``: the calibration runs and the
        exposures run the instrument so changed, the designs keep the nominal plant.

    Returns
    -------
    CaseComparison
    """
    for name in controllers:
        _check_names(name, "single")
    for s in schemes:
        _check_names("reference", s)
    c = apply_overrides(
        load_case(case), dict(overrides or {}, **_sensor_overrides(sensor, optical_gain))
    )
    scene = build_scene(c, quick=quick, progress=progress)
    exposure = seconds if seconds is not None else (0.5 if quick else c.science.exposure)
    scan_s = _QUICK_SCAN_SECONDS if quick else _SCAN_SECONDS
    cal_s = calibration_seconds(scene, quick)
    grid = _scan_grid(scene, quick, gain_grid)
    # Stage 1 and the disturbance of each stream are the same for every stage-2 controller
    # and both schemes: each stream's upstream is computed once and replayed (bit for bit).
    upstream = UpstreamRecords(scene, enabled=c.stage2.optical_gain != "two-pass")
    cells, gains, scans = [], {}, {}
    # Wall time per part [s]; "design" is the part of "runs" spent designing controllers.
    timing = {"scan": 0.0, "calibration": 0.0, "runs": 0.0, "design": 0.0}
    designs: dict[str, DesignInputs] = {}
    models: dict[str, ResidualModel] = {}
    ctrls: dict[tuple[str, str], ControllerBank] = {}
    results: dict[tuple[str, str], Any] = {}
    rd = None if results_dir is None else os.fspath(results_dir)
    for scheme in schemes:
        t0 = time.perf_counter()
        scan = []
        for g in grid:
            ref = Integrator(g, fs=scene.stage2.fs, n_modes=scene.stage2.n_modes)
            r = simulate_scene(
                scene,
                ref,
                scheme,
                scan_s,
                seed,
                "gain_scan",
                record=(),
                upstream=upstream.get(scheme, "gain_scan", scan_s),
            )
            scan.append((g, float(r.science.mean_contrast_4_6)))
        best = min(scan, key=lambda x: x[1])[0]
        gains[scheme], scans[scheme] = best, scan
        timing["scan"] += time.perf_counter() - t0
        logger.info("%s %s: reference gain %.2f (scan %s)", c.name, scheme, best, scan)
        t0 = time.perf_counter()
        design, model = calibrate_scene(
            scene,
            scheme,
            best,
            seconds=cal_s,
            seed=seed,
            estimator=estimator,
            upstream=upstream.get(scheme, "calibration", cal_s),
        )
        designs[scheme] = design
        if model is not None:
            models[scheme] = model
        timing["calibration"] += time.perf_counter() - t0
        for name in controllers:
            t0 = time.perf_counter()
            out = run_configuration(
                c,
                controller=name,
                scheme=scheme,
                seconds=exposure,
                seed=seed,
                overrides={"stage2.gain": best},
                quick=quick,
                progress=progress,
                design=design,
                upstream=upstream.get(scheme, "exposure", exposure),
            )
            timing["runs"] += time.perf_counter() - t0
            timing["design"] += out.summary["design_seconds"]
            # The reference gain came from the scan: its stream belongs to this run's record.
            out.settings["seed_streams"].update(seed_streams(seed, ("gain_scan",)))
            sci = out.result.science
            path = _save(out, rd, f"{c.name}_{scheme}_{name}")
            pred, se_pred, se_meas = _predicted(out.controller, design, model, cal_s, exposure)
            meas = out.summary["residual_rms_nm"]
            cells.append(
                Cell(
                    controller=name,
                    scheme=scheme,
                    strehl=out.summary["strehl"],
                    mean_contrast_4_6=out.summary["mean_contrast_4_6"],
                    mean_contrast_1_2=out.summary["mean_contrast_1_2"],
                    residual_rms_nm=meas,
                    predicted_rms_nm=pred,
                    radii_ld=np.asarray(sci.radii_ld),
                    contrast_profile=np.asarray(sci.contrast_profile),
                    settings=out.settings,
                    path=path,
                    bank=out.controller,
                    predicted_rms_se_nm=se_pred * pred,
                    residual_rms_se_nm=se_meas * meas,
                )
            )
            ctrls[(scheme, name)] = out.controller
            results[(scheme, name)] = out.result
            logger.info("%s %s %s: %s", c.name, scheme, name, out.summary)
    vib = None
    if c.vibration is not None:
        vib = vibration_report(scene, schemes[0], controllers, designs, ctrls, results)
    return CaseComparison(c.name, tuple(cells), gains, scans, vib, timing, designs, models)
