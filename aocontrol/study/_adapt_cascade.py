"""The adaptive study on a cascade: stage 2 redesigns itself with stage 1 in the loop.

Stage 1 runs the case's integrator; stage 2 (the case's pyramid stage: its linear modal
sensor, its DM and stroke) runs each strategy of :func:`aocontrol.study.adapt.run_adapt`.
Every run is a full cascade (:func:`aocontrol.sim.run_cascade`) on the same drifting
atmosphere and noise, with the science camera after both stages: the contrast is the mean
raw contrast between 4 and 6 lambda/D (``science.mean_contrast_4_6``, as the comparisons of
:mod:`aocontrol.study.compare` compute it), over the same span as the residual (after the
first window). The disturbance stage 2 sees (stage 1's residual in stage-2 modes) does not
depend on stage 2's controller (stage 1 never sees stage 2, in both schemes): the oracle
designs from that disturbance in a cascade run on an independent realisation of the same
drift. Vibrations of the case are left out, as in the single-stage study.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from aocontrol.controllers import Integrator
from aocontrol.sim.atmosphere import Atmosphere
from aocontrol.sim.loop import Stage, run_cascade
from aocontrol.study._adapt_parts import (
    _INDEPENDENT_SEED,
    PREDICTORS,
    SCENARIOS,
    _controller,
    _settings,
    scenario_drift,
)
from aocontrol.study.scene import Scene, build_scene

logger = logging.getLogger(__name__)

#: Strategies the cascade study runs (those of the single-stage study that design stage 2).
CASCADE_STRATEGIES = ("fixed", "adaptive", "oracle", "modal-gain", "lqg")


@dataclass(frozen=True)
class CascadeRow:
    """One strategy at one period on a cascade.

    Attributes
    ----------
    strategy : str
    period, window : float
        [s].
    residual : float
        Stage-2 residual variance summed over its modes after the first window [nm^2].
    contrast : float
        Mean raw contrast over 4 to 6 lambda/D after both stages, same span.
    contrast_inner : float
        Mean raw contrast over ``inner_band`` of :func:`run_adapt_cascade` (inside stage
        2's control radius: the quick scene's 24 stage-2 modes reach about
        ``sqrt(24 / pi) = 2.8`` lambda/D, so 4-6 lambda/D is stage 1's).
    strehl : float
        Long-exposure Strehl ratio, same span.
    n_switches, n_rejected_modes : int
        From the controller's :class:`~aocontrol.adaptive.AdaptiveRun`.
    clipped : int
        Stage-2 actuator-frames clipped by the DM stroke.
    """

    strategy: str
    period: float
    window: float
    residual: float
    contrast: float
    contrast_inner: float
    strehl: float
    n_switches: int
    n_rejected_modes: int
    clipped: int


@dataclass(frozen=True)
class AdaptCascadeStudy:
    """Result of :func:`run_adapt_cascade`.

    Attributes
    ----------
    case, scenario, scheme : str
    duration : float
        Simulated time [s].
    rows : tuple of CascadeRow
    settings : dict
    """

    case: str
    scenario: str
    scheme: str
    duration: float
    rows: tuple[CascadeRow, ...]
    settings: dict = dataclasses.field(default_factory=dict)

    def table(self) -> str:
        """Plain-text table: residual and contrast, with their ratios to the fixed design."""
        fixed = next((r for r in self.rows if r.strategy == "fixed"), None)
        lines = [
            f"{self.case} cascade ({self.scheme}), scenario {self.scenario}, {self.duration:g} s",
            f"{'strategy':<11} {'T [s]':>6} {'resid nm2':>10} {'/fixed':>7} "
            f"{'C 4-6':>10} {'/fixed':>7} {'C inner':>10} {'/fixed':>7} {'Strehl':>7} "
            f"{'switch':>6} {'clipped':>8}",
        ]
        for r in self.rows:
            rf = r.residual / fixed.residual if fixed else float("nan")
            cf = r.contrast / fixed.contrast if fixed else float("nan")
            ci = r.contrast_inner / fixed.contrast_inner if fixed else float("nan")
            lines.append(
                f"{r.strategy:<11} {r.period:>6g} {r.residual:>10.4g} {rf:>7.3f} "
                f"{r.contrast:>10.3e} {cf:>7.3f} {r.contrast_inner:>10.3e} {ci:>7.3f} "
                f"{r.strehl:>7.4f} {r.n_switches:>6d} "
                f"{r.clipped:>8d}"
            )
        return "\n".join(lines)


def _frames(scene: Scene, seconds: float) -> int:
    """Fast frames in ``seconds``, a multiple of the stages' rate ratio."""
    r = scene.case.rate_ratio
    return max(r, -(-int(round(seconds * scene.stage2.fs)) // r) * r)


def _cascade(
    scene: Scene,
    drift: object,
    controller: object,
    n: int,
    seed: int,
    *,
    scheme: str,
    settle: int,
    science: object,
    record: tuple[str, ...],
) -> object:
    """One cascade run: stage 1's integrator, ``controller`` at stage 2 (``science``: a
    long-exposure accumulator or ``None``)."""
    st1, st2 = scene.stage1, scene.stage2
    atm = Atmosphere(
        scene.pupil,
        scene.r0,
        list(scene.layers),
        st2.fs,
        L0=scene.case.atmosphere.L0,
        rng=seed,
        dtype=np.float32,
        drift=drift,
    )
    s1 = Stage(
        Integrator(st1.spec.gain, fs=st1.fs, n_modes=st1.n_modes),
        st1.sensor,
        st1.spec.latency_frames,
        dm=st1.modal_dm(),
        name="stage 1",
        basis=st1.basis,
    )
    s2 = Stage(
        controller,
        st2.sensor,
        st2.spec.latency_frames,
        dm=st2.modal_dm(),
        name="stage 2",
        basis=st2.basis,
    )
    return run_cascade(
        s1,
        s2,
        atm,
        n,
        scheme=scheme,
        rng=np.random.default_rng([seed, 11]),
        science=science,
        science_every=scene.case.science.science_every,
        record=record,
        settle_frames=settle,
    )


def run_adapt_cascade(
    case: str,
    *,
    scenario: str = "wind-doubles",
    periods: Sequence[float] = (1.0,),
    window: float = 1.0,
    duration: float = 20.0,
    strategies: Sequence[str] = ("fixed", "adaptive", "oracle"),
    scheme: str = "standalone",
    latency: float = 0.5,
    order: int = 2,
    modulus_margin: float = 0.5,
    quick: bool = True,
    seed: int = 0,
    n_jobs: int | None = 1,
    design_options: dict | None = None,
    adaptive_options: dict | None = None,
    inner_band: tuple[float, float] = (1.0, 2.0),
) -> AdaptCascadeStudy:
    """The adaptive study on a cascade: residual and contrast against the update period.

    Parameters
    ----------
    case : str
        Case name or TOML path (a cascade case, e.g. ``"bright1-best"``).
    scenario : str
        One of :data:`aocontrol.study.adapt.SCENARIOS`.
    periods : sequence of float
        Update periods ``T`` [s] (the fixed design runs once).
    window : float
        Telemetry window ``W`` [s].
    duration : float
        Simulated time [s] (the ramps span 20 % to 50 % of it).
    strategies : sequence of str
        Among :data:`CASCADE_STRATEGIES` and :data:`~aocontrol.study.adapt.PREDICTORS`.
    scheme : {"standalone", "dcao"}
        Cascade scheme.
    latency : float
        Design latency [s], shorter than every period and than the window.
    order, modulus_margin, n_jobs, design_options, adaptive_options
        As in :func:`aocontrol.study.adapt.run_adapt`.
    quick : bool, default True
        The case's quick scene.
    seed : int
        Seed of the atmosphere and the noise (the oracle's realisation: an offset seed).
    inner_band : (float, float), default (1.0, 2.0)
        Annulus [lambda/D] of the second contrast figure (inside stage 2's control radius).

    Returns
    -------
    AdaptCascadeStudy

    Raises
    ------
    ValueError
        Unknown scenario, strategy or scheme, a window not shorter than the run, a latency
        not shorter than a period or the window: before any run.
    """

    bad = [s for s in strategies if s not in CASCADE_STRATEGIES + PREDICTORS]
    if bad:
        raise ValueError(
            f"strategies must be among {list(CASCADE_STRATEGIES + PREDICTORS)}, got {bad}"
        )
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario must be one of {list(SCENARIOS)}, got {scenario!r}")
    if scheme not in ("standalone", "dcao"):
        raise ValueError(f"scheme must be 'standalone' or 'dcao', got {scheme!r}")
    if not 0 < window < duration:
        raise ValueError(f"window must be in (0, duration={duration:g}) s, got {window!r} s")
    for name, t in [("window", window)] + [("period", p) for p in periods]:
        if latency >= t:
            raise ValueError(
                f"latency must be shorter than every period and the window, got "
                f"latency={latency!r} s and {name}={t!r} s"
            )
    scene = build_scene(case, quick=quick)
    c = scene.case
    if scene.stage1 is None:
        raise ValueError(f"case {c.name!r} has no stage 1: not a cascade")
    drift = scenario_drift(
        scenario, duration, c.atmosphere.seeing, seed=seed, case_drift=c.atmosphere.drift
    )
    st = scene.stage2
    n = _frames(scene, duration)
    first = _frames(scene, window)
    independent = None
    if "oracle" in strategies:
        # What stage 2 sees on an independent realisation of the drift (stage 2's controller
        # does not change it): the oracle's truth.
        truth_run = _cascade(
            scene,
            drift,
            Integrator(st.spec.gain, fs=st.fs, n_modes=st.n_modes),
            n,
            seed + _INDEPENDENT_SEED,
            scheme=scheme,
            settle=first,
            science=None,
            record=("disturbance",),
        )
        independent = np.asarray(truth_run.stages[1].telemetry["disturbance"])
    rows = []
    for strategy in strategies:
        for period in (window,) if strategy in ("fixed", "eof-fixed") else periods:
            ctrl = _controller(
                strategy,
                scene,
                (independent, independent),
                period,
                window,
                latency,
                order,
                modulus_margin,
                n_jobs,
                seed,
                dict(design_options or {}),
                dict(adaptive_options or {}),
            )
            exposure = scene.camera().long_exposure()
            res = _cascade(
                scene,
                drift,
                ctrl,
                n,
                seed,
                scheme=scheme,
                settle=first,
                science=exposure,
                record=("residuals",),
            )
            e = res.stages[1].telemetry["residuals"][first:].astype(float)
            sat = res.stages[1].actuator_saturation
            run = ctrl.last_run
            rows.append(
                CascadeRow(
                    strategy=strategy,
                    period=float(period),
                    window=float(window),
                    residual=float(np.mean(np.sum(e**2, axis=1))),
                    contrast=float(res.science.mean_contrast_4_6),
                    contrast_inner=float(
                        exposure.camera.mean_contrast(exposure.coronagraphic, *inner_band)
                    ),
                    strehl=float(res.science.strehl),
                    n_switches=run.n_switches,
                    n_rejected_modes=run.n_rejected_modes,
                    clipped=int(np.sum(sat)) if sat is not None else 0,
                )
            )
            logger.info("%s", rows[-1])
    settings = _settings(
        st, latency, order, modulus_margin, quick, seed, design_options, adaptive_options
    )
    return AdaptCascadeStudy(c.name, scenario, scheme, float(duration), tuple(rows), settings)
