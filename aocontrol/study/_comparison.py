"""What :func:`aocontrol.study.compare.compare_case` returns: the cells of a case, its
comparison and the table beside the paper (also rebuilt from results files)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from aocontrol.analysis import (
    mean_square_sampling_variance,
    residual_psd,
    residual_variance,
)
from aocontrol.controllers import ControllerBank
from aocontrol.sim.loop import LoopResult
from aocontrol.synthesis import (
    SensorErrorPSD,
    TelemetryPSD,
    disturbance_from_telemetry,
    sensor_error_psd,
    split_sensor_error,
)

if TYPE_CHECKING:
    from aocontrol.study.scene import Scene


@dataclass(frozen=True, eq=False)
class Cell:
    """One configuration of a case's table.

    Parameters
    ----------
    controller, scheme : str
    strehl : float
        Long-exposure Strehl ratio at the science wavelength, in (0, 1].
    mean_contrast_4_6 : float
        Mean raw contrast over 4-6 lambda/D after the perfect coronagraph.
    mean_contrast_1_2 : float
        The same over 1-2 lambda/D (NaN in a cell read from a file written before it).
    residual_rms_nm : float
        Stage-2 modal residual RMS [nm] (measured).
    predicted_rms_nm : float
        Residual RMS predicted from the design PSDs (``residual_variance`` of the controller
        on the calibration telemetry) [nm], for a diffractive stage 2 from the scheme's
        :class:`ResidualModel` (the sensor's error apart); NaN when not available.
    radii_ld, contrast_profile : ndarray
        Radial contrast curve (radius [lambda/D], contrast).
    settings : dict
        As :attr:`RunOutcome.settings`.
    path : str or None
        Results file, if written.
    bank : ControllerBank or None
        The stage-2 controller that ran.
    predicted_rms_se_nm, residual_rms_se_nm : float
        Standard errors [nm] of the prediction (the calibration record it was estimated
        from is one draw of the atmosphere) and of the measured RMS (the exposure is one
        draw), both from the predicted residual PSD and the records' lengths
        (:func:`aocontrol.analysis.mean_square_sampling_variance`: a Gaussian stationary
        residual); NaN when not available. :meth:`ratio_interval` combines them.
    """

    controller: str
    scheme: str
    strehl: float
    mean_contrast_4_6: float
    residual_rms_nm: float
    predicted_rms_nm: float
    radii_ld: np.ndarray = field(repr=False)
    contrast_profile: np.ndarray = field(repr=False)
    settings: dict = field(repr=False, default_factory=dict)
    path: str | None = None
    bank: ControllerBank | None = field(default=None, repr=False)
    predicted_rms_se_nm: float = math.nan
    residual_rms_se_nm: float = math.nan
    mean_contrast_1_2: float = math.nan

    def ratio_interval(self, z: float = 2.0) -> tuple[float, float, float]:
        """Predicted / measured RMS and its interval ``ratio (1 -+ z s)``, ``s`` the two
        relative standard errors in quadrature: ``(ratio, low, high)`` (NaN bounds when a
        standard error is not available). An example of its width is in docs/benchmarks.md.
        """
        if not (isinstance(z, (int, float)) and z > 0):
            raise ValueError(f"z must be a number > 0, got {z!r}")
        r = self.predicted_rms_nm / self.residual_rms_nm
        s = math.hypot(
            self.predicted_rms_se_nm / self.predicted_rms_nm,
            self.residual_rms_se_nm / self.residual_rms_nm,
        )
        return r, r * (1 - z * s), r * (1 + z * s)


def predicted_residual(
    plant: Any,
    controller: ControllerBank,
    freqs: np.ndarray,
    psd: np.ndarray,
    noise_psd: np.ndarray,
    *,
    loop_gain: np.ndarray | None = None,
    seconds: Sequence[float] = (),
) -> tuple[float, list[float]]:
    """Predicted residual RMS [nm] of ``controller`` and the relative standard error of a
    ``T``-second record's RMS for each ``T`` in ``seconds`` (Gaussian stationary residual,
    :func:`aocontrol.analysis.mean_square_sampling_variance`; ``delta rms / rms = delta ms /
    (2 ms)``)."""
    var = residual_variance(plant, controller, freqs, psd, noise_psd, loop_gain=loop_gain)
    ms = float(np.sum(var))
    p = residual_psd(plant, controller, freqs, psd, noise_psd, loop_gain=loop_gain)
    v4 = float(np.sum(mean_square_sampling_variance(freqs, p, 1.0)))
    rel = [math.sqrt(v4 / t) / (2.0 * ms) if ms > 0 else math.nan for t in seconds]
    return math.sqrt(ms), rel


@dataclass(frozen=True, eq=False)
class CaseComparison:
    """Results of :func:`compare_case`.

    Parameters
    ----------
    case : str
    cells : tuple of Cell
        One per (scheme, controller).
    reference_gains : dict
        Scanned gain per scheme.
    scan : dict
        ``{scheme: [(gain, mean contrast), ...]}`` of the gain scan.
    vibration : dict or None
        For a case with a vibration: ``tilt_rms_nm`` per controller, ``relative_gain``, the
        tilt residual PSDs ``(freqs, psd)`` per controller, and for the sensitivity plot the
        frequencies, ``|S|^2`` per controller and the tilt disturbance PSD (pseudo-open loop
        of the calibration telemetry) at the stage-2 input.
    seconds : dict
        Wall time per part [s]: ``scan``, ``calibration``, ``runs`` (the configurations'
        designs and exposures) and ``design`` (the designs' share of ``runs``).
    designs : dict
        ``{scheme: DesignInputs}``: the stage-2 plant and the calibration telemetry's PSDs
        each scheme's controllers were designed from (margins and rejection of the report).
    residual_models : dict
        ``{scheme: ResidualModel}`` for a diffractive stage 2: what the cells'
        ``predicted_rms_nm`` used instead of the design PSDs (the sensor's error apart).
    """

    case: str
    cells: tuple
    reference_gains: dict
    scan: dict
    vibration: dict | None = None
    seconds: dict = field(default_factory=dict)
    designs: dict = field(default_factory=dict, repr=False)
    residual_models: dict = field(default_factory=dict, repr=False)

    def cell(self, controller: str, scheme: str) -> Cell:
        """The cell of ``controller`` in ``scheme``."""
        for c in self.cells:
            if c.controller == controller and c.scheme == scheme:
                return c
        raise KeyError(f"no cell ({controller!r}, {scheme!r})")

    def table(self) -> str:
        """The paper's table: mean contrast 4-6 lambda/D and Strehl [%] per configuration."""
        return format_table(self.case, self.cells)

    @property
    def contrast_curves(self) -> dict:
        """``{(scheme, controller): (radii_ld, contrast)}`` for the radial contrast plot."""
        return {(c.scheme, c.controller): (c.radii_ld, c.contrast_profile) for c in self.cells}


@dataclass(frozen=True, eq=False)
class ResidualModel:
    """What the stage-2 residual is predicted from when the sensor is diffractive.

    The calibration telemetry's pseudo-open loop ``m / og + G u = z^-1 d + v / og`` with the
    sensor's error ``v`` (aliasing, non-linearity, noise: coloured) moved from the disturbance
    to the noise, through ``T`` (:mod:`aocontrol.synthesis._sensor_error`), and the loop's
    own gain ``og G K`` where the reconstructor leaves the optical gains uncompensated.

    Parameters
    ----------
    freqs : ndarray, shape (n_f,)
        Frequencies [Hz].
    psd, noise_psd : ndarray, shape (n_modes, n_f)
        Disturbance and sensor-error PSDs, one-sided [nm^2/Hz].
    loop_gain : ndarray, shape (n_modes,) or None
        Optical gains the loop does not compensate (``"none"``: the calibrated ones), or
        ``None`` (compensated).
    error : SensorErrorPSD
        The sensor's error, from the calibration run (the sensor's output and the modal
        residual it looked at).
    """

    freqs: np.ndarray
    psd: np.ndarray
    noise_psd: np.ndarray
    loop_gain: np.ndarray | None
    error: SensorErrorPSD

    @classmethod
    def from_calibration(
        cls,
        measurements: np.ndarray,
        commands: np.ndarray,
        residuals: np.ndarray,
        plant: Any,
        fs: float,
        *,
        optical_gain: np.ndarray | None = None,
        estimator: str = "prewhitened",
    ) -> ResidualModel:
        """From a calibration run's stage-2 records ``(n_frames, n_modes)`` [nm].

        ``optical_gain``: gains ``m`` carries uncompensated (``None``: compensated).
        """
        tel: TelemetryPSD = disturbance_from_telemetry(
            measurements, commands, plant, fs=fs, method=estimator, optical_gain=optical_gain
        )
        err = sensor_error_psd(measurements, residuals, plant, fs=fs, optical_gain=optical_gain)
        psd, noise = split_sensor_error(tel, err)
        og = None if optical_gain is None else np.asarray(optical_gain, dtype=float)
        return cls(tel.freqs, psd, noise, og, err)

    def predicted_rms(self, plant: Any, controller: ControllerBank) -> float:
        """Stage-2 modal residual RMS [nm] of ``controller`` in this loop."""
        return self.predicted(plant, controller)[0]

    def predicted(
        self, plant: Any, controller: ControllerBank, seconds: Sequence[float] = ()
    ) -> tuple[float, list[float]]:
        """Stage-2 modal residual RMS [nm] of ``controller`` in this loop and the relative
        standard errors of records of ``seconds`` (:func:`predicted_residual`)."""
        return predicted_residual(
            plant, controller, self.freqs, self.psd, self.noise_psd,
            loop_gain=self.loop_gain, seconds=seconds,
        )  # fmt: skip


def format_table(case: str, cells: Sequence[Any]) -> str:
    """Text table of the cells (``scheme controller`` columns, contrast and Strehl rows).

    Parameters
    ----------
    case : str
        Title.
    cells : sequence of Cell or dict
        Objects or dicts with ``scheme``, ``controller``, ``mean_contrast_4_6``, ``strehl``
        (and ``mean_contrast_1_2``, NaN where missing).

    Returns
    -------
    str
    """
    get = (lambda c, k: c[k]) if cells and isinstance(cells[0], dict) else getattr
    heads = [f"{get(c, 'scheme')} {get(c, 'controller')}" for c in cells]
    w = max(14, *(len(h) for h in heads))
    lines = [case, " " * 22 + "".join(f"{h:>{w + 2}}" for h in heads)]
    lines.append(
        f"{'avg contrast 4-6 l/D':22}"
        + "".join(f"{get(c, 'mean_contrast_4_6'):>{w + 2}.3e}" for c in cells)
    )

    def near(c: Any) -> float:  # results written before the 1-2 lambda/D figure: nan
        v = c.get("mean_contrast_1_2", math.nan) if isinstance(c, dict) else c.mean_contrast_1_2
        return float(v)

    lines.append(f"{'avg contrast 1-2 l/D':22}" + "".join(f"{near(c):>{w + 2}.3e}" for c in cells))
    lines.append(
        f"{'Strehl [%]':22}" + "".join(f"{100 * get(c, 'strehl'):>{w + 2}.2f}" for c in cells)
    )
    return "\n".join(lines)


def table_from_files(paths: Sequence[str | os.PathLike]) -> str:
    """Rebuild a case table from results files, without rerunning.

    Parameters
    ----------
    paths : sequence of path
        Files written by :func:`compare_case` (``results_dir``).

    Returns
    -------
    str
        One table per case (as :meth:`CaseComparison.table`).
    """
    from aocontrol.study.results import load_result, read_settings

    rows: dict[str, list[dict]] = {}
    for p in paths:
        st = read_settings(p)
        res = load_result(p)
        sci = res.science
        strehl = sci["strehl"] if isinstance(sci, dict) else sci.strehl
        con = sci["mean_contrast_4_6"] if isinstance(sci, dict) else sci.mean_contrast_4_6
        near = (
            sci.get("mean_contrast_1_2", math.nan)
            if isinstance(sci, dict)
            else sci.mean_contrast_1_2
        )
        rows.setdefault(st["case"], []).append(
            {
                "scheme": st["scheme"],
                "controller": st["controller"]["name"],
                "strehl": float(strehl),
                "mean_contrast_4_6": float(con),
                "mean_contrast_1_2": float(near),
            }
        )
    return "\n\n".join(format_table(k, v) for k, v in rows.items())


# Shown, documented and pickled under the module that exports them.
Cell.__module__ = CaseComparison.__module__ = ResidualModel.__module__ = "aocontrol.study.compare"


def stage2_result(result: Any) -> LoopResult:
    """Stage 2's result of a run (the run itself for stage 2 alone)."""
    return result if isinstance(result, LoopResult) else result.stages[1]


def vibration_report(
    scene: Scene,
    scheme: str,
    controllers: Sequence[str],
    designs: dict,
    ctrls: dict,
    results: dict,
) -> dict:
    """Tilt residual RMS, residual PSDs and sensitivity functions (paper's vibration plots)."""
    from aocontrol.plant import frequency_response

    mode = scene.case.vibration.modes[0]
    design = designs[scheme]
    out: dict[str, Any] = {"mode": mode, "scheme": scheme, "tilt_rms_nm": {}, "psd": {}}
    f = design.freqs
    g = frequency_response(design.plant, f, fs=design.fs)
    out["freqs"] = f
    out["disturbance_psd"] = design.psd[mode]
    out["sensitivity2"] = {}
    for name in controllers:
        r2 = stage2_result(results[(scheme, name)])
        out["tilt_rms_nm"][name] = float(math.sqrt(r2.residual_variance[mode]))
        fr, p = r2.psd("residuals")
        out["psd"][name] = (fr, p[mode])
        try:
            tf = ctrls[(scheme, name)].transfer_function(mode)
        except (NotImplementedError, ValueError, TypeError):  # e.g. a constrained MPC
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            k = frequency_response(tf, f, fs=design.fs)
            s2 = np.abs(1.0 / (1.0 + g * k)) ** 2
        out["sensitivity2"][name] = np.where(np.isfinite(k), s2, 0.0)  # pole of K on |z|=1
    if "reference" in out["tilt_rms_nm"] and "datadriven" in out["tilt_rms_nm"]:
        a, b = out["tilt_rms_nm"]["reference"], out["tilt_rms_nm"]["datadriven"]
        out["relative_gain"] = (a - b) / a
    return out
