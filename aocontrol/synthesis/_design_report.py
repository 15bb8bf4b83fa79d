"""What :func:`aocontrol.synthesis.design_from_telemetry` returns: the design and its evidence.

Control layer. Every figure it holds is a certificate or a prediction on the full telemetry
grid, never a design grid's sample: the margins are those of :func:`aocontrol.analysis.margins`
(exact for rational plants and controllers), the residuals the trapezoid of
:func:`aocontrol.analysis.residual_variance` on the telemetry PSD grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aocontrol.analysis import Margins
from aocontrol.controllers import ControllerBank
from aocontrol.synthesis._telemetry import TelemetryPSD

__all__ = ["TelemetryDesign"]

_PER_MODE = (
    "residual_variance",
    "reference_residual_variance",
    "wiener_variance",
    "constrained_variance",
)


@dataclass(frozen=True, eq=False)
class TelemetryDesign:
    """A controller bank designed from closed-loop telemetry, with its certificates.

    Returned by :func:`aocontrol.synthesis.design_from_telemetry`. Per-mode arrays have shape
    ``(n_modes,)``; variances are in the telemetry's units squared (nm^2 for modal telemetry
    in nm), PSDs one-sided [units^2/Hz].

    Attributes
    ----------
    controller_name : str
        Registry name of the design (:data:`aocontrol.synthesis.CONTROLLERS`).
    controller : ControllerBank
        The designed per-mode controllers.
    reference : ControllerBank
        The starting integrator, for reference: the optimised modal-gain integrator
        (:func:`aocontrol.synthesis.optimal_modal_gain` at the same modulus margin), which
        is also where the data-driven design starts.
    plant : control.TransferFunction
        Loop plant (command to measurement), :func:`aocontrol.plant.loop_plant`.
    fs : float
        Loop rate [Hz].
    latency_frames : float
        RTC latency beyond the one-frame WFS integration [frames] (``nan`` when the design
        was given a plant and no latency).
    estimate : TelemetryPSD
        The disturbance and noise estimate the design used (``estimate.freqs`` [Hz],
        ``estimate.psd`` (n_modes, n_freqs), ``estimate.noise_psd`` (n_modes,),
        ``estimate.method``).
    modulus_margin : float
        Required modulus margin ``min |1 + G K|`` of the design (dimensionless).
    margins : tuple of Margins
        Per mode, the margins of the designed loop (:func:`aocontrol.analysis.margins`:
        gain, phase, modulus, delay margins and closed-loop stability).
    reference_margins : tuple of Margins
        The same for :attr:`reference`.
    residual_variance : ndarray, shape (n_modes,)
        Predicted residual variance of the design, ``int |S|^2 psd + |T|^2 noise df``
        [units^2] (:func:`aocontrol.analysis.residual_variance` on ``estimate.freqs``).
    reference_residual_variance : ndarray, shape (n_modes,)
        The same for :attr:`reference`.
    wiener_variance : ndarray, shape (n_modes,)
        Lower bound of any causal linear controller, no margin required
        (:func:`aocontrol.analysis.wiener_bound`) [units^2]; ``nan`` if not computed.
    constrained_variance : ndarray, shape (n_modes,)
        Lower bound of a linear controller meeting :attr:`modulus_margin`
        (:func:`aocontrol.analysis.constrained_bound`) [units^2]; ``nan`` if not computed or
        failed for a mode.
    details : object or None
        The synthesis's own result when it has one (e.g. a
        :class:`~aocontrol.synthesis.DataDrivenResult` with per-mode reports).
    options : dict
        Design options passed to the registry's design (``order``, ...).
    timings : dict
        Wall-clock seconds of the steps (``estimate``, ``design``, ``reference``,
        ``margins``: the margins and the bounds, computed in one pass over the modes,
        ``bounds``: the predicted residuals and the bounds' assembly).
    bound_failures : dict of int to str
        Modes whose constrained bound could not be computed, with the reason (their
        :attr:`constrained_variance` is ``nan``); empty when every asked bound was computed.
    unit : str or None
        Unit of the telemetry and of every figure (``residual_rms`` in ``unit``, variances in
        ``unit^2``, PSDs in ``unit^2/Hz``): :attr:`LoopTelemetry.unit` (nm by convention);
        ``None`` when nobody stated it (printed ``"a.u."``).
    telemetry_check : LoopTelemetryCheck or None
        The command sign and scale check of the telemetry (``None`` when not run).
    uncertainty : UncertaintySet or None
        The box of loop gains and latency changes the robust margins cover (``None``: none
        asked).
    robust_margins, reference_robust_margins : tuple of RobustMargin or None
        Per mode, the certified modulus margin over :attr:`uncertainty` of the design and of
        the reference (:func:`aocontrol.analysis.robust_margin`; ``None`` when not asked or
        not computable: a multi-mode bank, a measured plant).
    """

    controller_name: str
    controller: ControllerBank
    reference: ControllerBank
    plant: Any
    fs: float
    latency_frames: float
    estimate: TelemetryPSD
    modulus_margin: float
    margins: tuple[Margins, ...]
    reference_margins: tuple[Margins, ...]
    residual_variance: np.ndarray
    reference_residual_variance: np.ndarray
    wiener_variance: np.ndarray
    constrained_variance: np.ndarray
    details: Any = None
    options: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    bound_failures: dict = field(default_factory=dict)
    unit: str | None = "nm"
    telemetry_check: Any = None
    uncertainty: Any = None
    robust_margins: tuple | None = None
    reference_robust_margins: tuple | None = None

    def __post_init__(self) -> None:
        n = self.controller.n_modes
        if self.reference.n_modes != n or self.estimate.n_modes != n:
            raise ValueError(
                f"controller, reference and estimate must have the same n_modes, got "
                f"{n}, {self.reference.n_modes} and {self.estimate.n_modes}"
            )
        for name in ("margins", "reference_margins", "robust_margins", "reference_robust_margins"):
            if getattr(self, name) is not None and len(getattr(self, name)) != n:
                raise ValueError(f"{name} must have {n} entries, got {len(getattr(self, name))}")
        for name in _PER_MODE:
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != (n,):
                raise ValueError(f"{name} must have shape ({n},), got {arr.shape}")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    # -- summaries ------------------------------------------------------------------------
    @property
    def n_modes(self) -> int:
        """Number of modes."""
        return self.controller.n_modes

    @property
    def stable(self) -> np.ndarray:
        """Closed-loop stability per mode (certified), shape ``(n_modes,)``."""
        return np.array([m.stable for m in self.margins])

    @property
    def achieved_modulus_margin(self) -> np.ndarray:
        """Modulus margin ``min |1 + G K|`` per mode, shape ``(n_modes,)``."""
        return np.array([m.modulus_margin for m in self.margins])

    @property
    def meets_margin(self) -> np.ndarray:
        """Stable and ``min |1 + G K| >= modulus_margin`` (to 1e-9) per mode."""
        return self.stable & (self.achieved_modulus_margin >= self.modulus_margin - 1e-9)

    @property
    def robust_modulus_margin(self) -> np.ndarray:
        """Certified modulus margin over :attr:`uncertainty` per mode (``nan`` where not
        computed), shape ``(n_modes,)``; a mode not certified stable over the whole set reads
        its (possibly negative) bound."""
        if self.robust_margins is None:
            return np.full(self.n_modes, np.nan)
        return np.array([r.value for r in self.robust_margins])

    @property
    def residual_rms(self) -> float:
        """Predicted residual over all modes, ``sqrt(sum residual_variance)`` [units]."""
        return float(np.sqrt(np.sum(self.residual_variance)))

    @property
    def reference_residual_rms(self) -> float:
        """The same for the reference integrator [units]."""
        return float(np.sqrt(np.sum(self.reference_residual_variance)))

    @property
    def wiener_rms(self) -> float:
        """Wiener bound over all modes [units] (``nan`` if any mode lacks it)."""
        return float(np.sqrt(np.sum(self.wiener_variance)))

    @property
    def constrained_rms(self) -> float:
        """Constrained bound over all modes [units] (``nan`` if any mode lacks it)."""
        return float(np.sqrt(np.sum(self.constrained_variance)))

    def rows(self) -> list[dict]:
        """One dict per mode for tables.

        Keys: ``mode``, ``stable`` (bool), ``gain_margin_db`` (how far the gain can rise),
        ``gain_margin_down_db`` (fall; ``-inf``: any smaller gain is stable),
        ``phase_margin_deg`` (smallest over every crossover), ``modulus_margin``,
        ``delay_margin_frames`` (latency that can be added), ``delay_margin_removed_frames``
        (removed), ``robust_margin`` (certified over :attr:`uncertainty`, ``nan`` if not
        asked), ``residual_nm`` (RMS, units),
        ``reference_nm``, ``wiener_nm``, ``constrained_nm``, ``ratio_to_constrained``
        (residual variance / constrained bound).
        """
        out = []
        robust = self.robust_modulus_margin
        for i, m in enumerate(self.margins):
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = self.residual_variance[i] / self.constrained_variance[i]
            out.append(
                {
                    "mode": i,
                    "stable": bool(m.stable),
                    "gain_margin_db": m.gain_margin_db,
                    "gain_margin_down_db": m.gain_margin_down_db,
                    "phase_margin_deg": float(m.phase_margin),
                    "modulus_margin": float(m.modulus_margin),
                    "delay_margin_frames": float(m.delay_margin),
                    "delay_margin_removed_frames": float(m.delay_margin_removed),
                    "robust_margin": float(robust[i]),
                    "residual_nm": float(np.sqrt(self.residual_variance[i])),
                    "reference_nm": float(np.sqrt(self.reference_residual_variance[i])),
                    "wiener_nm": float(np.sqrt(self.wiener_variance[i])),
                    "constrained_nm": float(np.sqrt(self.constrained_variance[i])),
                    "ratio_to_constrained": float(ratio),
                }
            )
        return out
