"""The adaptive-control study: how often should a loop redesign itself under drifting turbulence?

One single-stage loop (the case's stage 2, the SAXO+ pyramid stage, seeing the full
turbulence as in dCAO) runs on a drifting atmosphere (:mod:`aocontrol.sim.drift`) with
controllers that redesign themselves (:class:`aocontrol.adaptive.AdaptiveController`). The
modal disturbance of a scenario is generated once (atmosphere with drift, projected on the
stage-2 KL basis) and replayed to every strategy with the same measurement noise: the
comparisons are paired.

Strategies (each a bank of per-mode controllers starting from the case's integrator):

* ``fixed``: data-driven design from the first window, never redesigned;
* ``adaptive``: data-driven, redesigned every ``period`` from the last ``window`` of its own
  telemetry (warm-started, certified, switched after the design latency, bumplessly);
* ``oracle``: data-driven, redesigned every ``period`` from the true disturbance of the
  period each design will serve (from its switch; at least a window long), switched after
  the same latency: an independent realisation of the same drift plus white noise of the
  true level, through the same pre-whitened estimator. It knows the disturbance's
  statistics as they will be, not the realisation the loop will face (a design fitted to
  that realisation's own Welch estimate is a prophet: ``oracle-prophet`` below);
* ``modal-gain``: the optimised integrator gain, adapted like ``adaptive``;
* ``lqg``: LQG re-identified from the same windows, adapted like ``adaptive``.

The multi-mode predictor (:data:`PREDICTORS`, not run by default): ``eof-fixed`` (trained
once on the first window, like ``fixed``) and ``eof`` (retrained every ``period``, like
``adaptive``): :class:`aocontrol.adaptive.AdaptivePredictor`, the registry's history for the
mode count, the study's margin as the multivariable one, the whole predictor certified or
not switched.

Diagnostics of the adaptive / oracle gap (:data:`DIAGNOSTICS`): ``adaptive-nolatency`` (no
design latency), ``adaptive-truth`` (the adaptive's own window, but of the true disturbance
of an independent realisation plus true noise: no pseudo-open-loop reconstruction from
closed-loop data), ``oracle-prophet`` (the run's own coming disturbance, no latency).

Figures: the residual variance summed over modes [nm^2] after the first window (the part the
strategies differ on) and its ratio to ``fixed`` and ``oracle``; switches and rejected
(uncertified) modes; design time. Scenarios (:data:`SCENARIOS`): ``wind-doubles`` (a ramp to
twice the wind speed between 20 % and 50 % of the run), ``seeing-worsens`` (a ramp to 1.5 times
the seeing over the same interval), ``stochastic`` (the Paranal model of
:meth:`aocontrol.sim.drift.Drift.stochastic`) and ``case`` (the case file's own
``[atmosphere.drift]``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from aocontrol._atomic import atomic_path
from aocontrol.adaptive import AdaptiveRun, switch_transients
from aocontrol.sim.atmosphere import Atmosphere
from aocontrol.sim.drift import Drift
from aocontrol.sim.loop import ModalTimeSeries, Stage, TurbulenceSource, run_loop
from aocontrol.study._adapt_cascade import (
    CASCADE_STRATEGIES,
    AdaptCascadeStudy,
    CascadeRow,
    run_adapt_cascade,
)
from aocontrol.study._adapt_parts import (
    _INDEPENDENT_SEED,
    PREDICTORS,
    SCENARIOS,
    _controller,
    _settings,
    scenario_drift,
)
from aocontrol.study.scene import Scene, build_scene

__all__ = [
    "CASCADE_STRATEGIES",
    "SCENARIOS",
    "STRATEGIES",
    "AdaptCascadeStudy",
    "AdaptRow",
    "AdaptStudy",
    "CascadeRow",
    "DIAGNOSTICS",
    "PREDICTORS",
    "drifting_disturbance",
    "run_adapt",
    "run_adapt_cascade",
    "scenario_drift",
    "seed_summary",
    "window_rule",
]

logger = logging.getLogger(__name__)

STRATEGIES = ("fixed", "adaptive", "oracle", "modal-gain", "lqg")
#: Strategies that decompose the adaptive / oracle gap: the adaptive loop with no design
#: latency; the adaptive loop designing from the true disturbance of its window (no
#: pseudo-open-loop estimate); the prophet oracle (this run's own coming disturbance, no
#: latency: it sees the realisation it will face).
DIAGNOSTICS = ("adaptive-nolatency", "adaptive-truth", "oracle-prophet")
# The last disturbances generated ((key, seed) -> array), at most two.
_DISTURBANCES: dict = {}


def drifting_disturbance(
    scene: Scene, drift: Drift, n_frames: int, seed: int, *, chunk: int = 3000
) -> np.ndarray:
    """Stage-2 modal disturbance [nm] of ``n_frames`` frames under ``drift``.

    Parameters
    ----------
    scene : Scene
        The case's scene (pupil, r0, layers, stage-2 basis and rate).
    drift : Drift
        Seeing and wind history.
    n_frames : int
        Frames at stage 2's rate.
    seed : int
        Seed of the phase screens.
    chunk : int, default 3000
        Frames generated at once.

    Returns
    -------
    ndarray, shape (n_frames, n_modes), float32
        The atmosphere at stage 2's rate projected on its KL basis [nm].
    """
    atm = Atmosphere(
        scene.pupil,
        scene.r0,
        list(scene.layers),
        scene.stage2.fs,
        L0=scene.case.atmosphere.L0,
        rng=seed,
        dtype=np.float32,
        drift=drift,
    )
    src = TurbulenceSource(atm, scene.stage2.basis)
    out = np.empty((n_frames, scene.stage2.n_modes), dtype=np.float32)
    for k in range(0, n_frames, chunk):
        m = min(chunk, n_frames - k)
        out[k : k + m] = src.next(m)[0]
    return out


@dataclass(frozen=True)
class AdaptRow:
    """One strategy at one (period, window) on one scenario.

    Attributes
    ----------
    strategy : str
    period, window : float
        [s].
    residual : float
        Residual variance summed over modes after the first window (or from the study's
        ``measure_from``) [nm^2].
    residual_late : float
        The same over the last 30 % of the run (after the drift settled) [nm^2].
    n_switches, n_rejected_modes, n_rejected_banks : int
        From the controller's :class:`~aocontrol.adaptive.AdaptiveRun`.
    design_seconds : float
        Median compute time of a design [s].
    clipped : int
        Actuator-frames clipped by the case's DM stroke (:attr:`LoopResult.actuator_saturation`
        summed; 0 without an actuator stroke).
    transient_median, transient_worst : float
        Residual energy in the 50 frames after a switch / the 50 before: median and largest
        over the run's switches (:func:`aocontrol.adaptive.switch_transients`; ``nan``
        without a switch).
    reference_median, reference_worst : float
        The same ratio at the midpoints between switches, where no switch happened: the noise
        of the ratio.
    transient_p : float
        One-sided Mann-Whitney p-value that the switches' ratios exceed the reference's.
    n_kept_modes : int
        Mode redesigns whose new design was worse than the running controller, which stayed
        (:attr:`aocontrol.adaptive.AdaptiveRun.n_kept_modes`; the synthesis' policy, not a
        failure).
    """

    strategy: str
    period: float
    window: float
    residual: float
    residual_late: float
    n_switches: int
    n_rejected_modes: int
    n_rejected_banks: int
    design_seconds: float
    clipped: int = 0
    transient_median: float = float("nan")
    transient_worst: float = float("nan")
    reference_median: float = float("nan")
    reference_worst: float = float("nan")
    transient_p: float = float("nan")
    n_kept_modes: int = 0


@dataclass(frozen=True)
class AdaptStudy:
    """Result of :func:`run_adapt`.

    Attributes
    ----------
    case, scenario : str
    duration : float
        Simulated time [s].
    rows : tuple of AdaptRow
    settings : dict
        The run's settings (latency, order, design and adaptive options, seed, modes).
    """

    case: str
    scenario: str
    duration: float
    rows: tuple[AdaptRow, ...]
    settings: dict = dataclasses.field(default_factory=dict)

    def row(self, strategy: str, period: float | None = None) -> AdaptRow:
        """The first row of ``strategy`` (at ``period`` if given)."""
        for r in self.rows:
            if r.strategy == strategy and (period is None or r.period == period):
                return r
        raise KeyError(f"no row for strategy {strategy!r} and period {period!r}")

    def to_dataset(self) -> object:
        """The rows as an :class:`xarray.Dataset` (dimension ``row``; units in ``attrs``)."""
        import xarray as xr

        cols = {
            f.name: [getattr(r, f.name) for r in self.rows] for f in dataclasses.fields(AdaptRow)
        }
        units = {
            "period": "s",
            "window": "s",
            "residual": "nm^2",
            "residual_late": "nm^2",
            "design_seconds": "s",
        }
        data = {
            k: xr.Variable("row", np.asarray(v), attrs={"units": units[k]} if k in units else {})
            for k, v in cols.items()
        }
        return xr.Dataset(
            data,
            attrs={
                "format": "aocontrol-adapt-study",
                "case": self.case,
                "scenario": self.scenario,
                "duration_s": self.duration,
                "settings_json": json.dumps(self.settings, default=str),
            },
        )

    def save(self, path: str | os.PathLike) -> str:
        """Write :meth:`to_dataset` as HDF5 (netCDF-4, ``xarray.open_dataset`` opens it),
        atomically; returns the path."""
        path = os.fspath(path)
        with atomic_path(path) as tmp:
            self.to_dataset().to_netcdf(tmp, engine="h5netcdf")
        return path

    def table(self) -> str:
        """Plain-text table: residual, ratios to the fixed design and to the oracle."""
        fixed = {r.window: r.residual for r in self.rows if r.strategy == "fixed"}
        oracle = {r.period: r.residual for r in self.rows if r.strategy == "oracle"}
        lines = [
            f"{self.case}, scenario {self.scenario}, {self.duration:g} s",
            f"{'strategy':<11} {'T [s]':>6} {'W [s]':>6} {'resid nm2':>10} {'/fixed':>7} "
            f"{'/oracle':>8} {'late nm2':>9} {'switch':>6} {'reject':>6} {'design s':>8}",
        ]
        for r in self.rows:
            rf = r.residual / fixed[r.window] if r.window in fixed else float("nan")
            ro = r.residual / oracle[r.period] if r.period in oracle else float("nan")
            lines.append(
                f"{r.strategy:<11} {r.period:>6g} {r.window:>6g} {r.residual:>10.4g} "
                f"{rf:>7.3f} {ro:>8.3f} {r.residual_late:>9.4g} {r.n_switches:>6d} "
                f"{r.n_rejected_modes:>6d} {r.design_seconds:>8.3g}"
            )
        return "\n".join(lines)


def check_adapt_settings(
    *,
    scenario: str | Drift,
    periods: Sequence[float],
    windows: Sequence[float],
    duration: float,
    strategies: Sequence[str],
    latency: float | None,
    measure_from: float | None = None,
) -> None:
    """The checks of :func:`run_adapt` that need no scene (the command line runs them before
    it creates its output folder); raises ValueError naming the argument. Study-layer
    internal (not in ``__all__``): the arguments are :func:`run_adapt`'s."""
    if not (isinstance(duration, (int, float)) and math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be a finite number of seconds > 0, got {duration!r}")
    bad = [s for s in strategies if s not in STRATEGIES + DIAGNOSTICS + PREDICTORS]
    if bad:
        raise ValueError(
            f"strategies must be among {list(STRATEGIES + DIAGNOSTICS + PREDICTORS)}, got {bad}"
        )
    if not isinstance(scenario, Drift) and scenario not in SCENARIOS:
        raise ValueError(f"scenario must be one of {list(SCENARIOS)} or a Drift, got {scenario!r}")
    for p in periods:
        if not p > 0:
            raise ValueError(f"periods must be > 0 s, got {p!r} s")
    for w in windows:
        if not 0 < w < duration:
            raise ValueError(f"window must be in (0, duration={duration:g}) s, got {w!r} s")
    if measure_from is not None and not 0 <= measure_from < duration:
        raise ValueError(
            f"measure_from must be in [0, duration={duration:g}) s, got {measure_from!r} s"
        )
    # Checked before any run: ``fixed`` designs once, a window in (its period is the window).
    delayed = set(strategies) - {"adaptive-nolatency", "oracle-prophet"}
    served = [("period", p) for p in periods if delayed - {"fixed", "eof-fixed"}]
    served += [("window", w) for w in windows if {"fixed", "eof-fixed"} & delayed]
    for name, t in served:
        if latency is not None and latency >= t:
            raise ValueError(
                f"latency must be shorter than every {name} (the {name} of the "
                f"{'fixed' if name == 'window' else 'redesigning'} strategies), got "
                f"latency={latency!r} s and {name}={t!r} s"
            )


def _drift_key(drift: Drift) -> list:
    """A drift's knots as plain lists (the disturbance cache's key)."""
    return [
        drift.name,
        drift.times.tolist(),
        drift.seeing.tolist(),
        drift.wind.tolist(),
        drift.direction.tolist(),
    ]


def run_adapt(
    case: str,
    *,
    scenario: str = "wind-doubles",
    periods: Sequence[float] = (1.0,),
    windows: Sequence[float] = (1.0,),
    duration: float = 60.0,
    strategies: Sequence[str] = STRATEGIES,
    latency: float | None = 0.5,
    order: int = 5,
    modulus_margin: float = 0.5,
    quick: bool = False,
    seed: int = 0,
    n_jobs: int | None = 1,
    overrides: dict | None = None,
    design_options: dict | None = None,
    adaptive_options: dict | None = None,
    measure_from: float | None = None,
) -> AdaptStudy:
    """Run the strategies on one drifting scenario for every (period, window).

    Parameters
    ----------
    case : str
        Case name or TOML path.
    scenario : str or Drift
        One of :data:`SCENARIOS`, or a :class:`~aocontrol.sim.drift.Drift` of any number of
        knots (e.g. a wind ramp and a seeing step at another time; the study's scenario
        label is its ``name``).
    periods, windows : sequence of float
        Update periods ``T`` and telemetry windows ``W`` [s]; every pair is run (the fixed
        design once per window, the oracle once per period). The recommendation (docs,
        "Recommended update period"): ``T = 2 s``, ``W = T`` (:func:`window_rule`).
    duration : float
        Simulated time [s]; each window must be shorter than the run.
    strategies : sequence of str
        Among :data:`STRATEGIES`, :data:`DIAGNOSTICS` and :data:`PREDICTORS`.
    latency : float or None, default 0.5
        Design latency [s] (``None``: the measured compute time); must be below every period.
    order : int, default 5
        Data-driven controller order.
    modulus_margin : float, default 0.5
        Certified margin of every switched-in controller (0.3 for LQG, which promises none).
    quick : bool
        The case's quick scene (24 stage-2 modes).
    seed : int
        Seed of the atmosphere, the stochastic drift and the noise.
    n_jobs : int or None
        Worker processes of each data-driven design.
    overrides : dict, optional
        Case overrides.
    design_options : dict, optional
        Other keyword arguments of :func:`aocontrol.synthesis.datadriven` (e.g. ``n_grid``,
        ``max_iter`` for quick runs).
    adaptive_options : dict, optional
        Other keyword arguments of :class:`~aocontrol.adaptive.AdaptiveController` (e.g.
        ``select``).
    measure_from : float, optional
        Time [s] from which ``residual`` is averaged, the same for every row (``None``: each
        row's own window, after which its first design can be running). Runs at different
        windows are compared on a common span with it.

    Returns
    -------
    AdaptStudy

    Raises
    ------
    ValueError
        A duration that is not positive, an unknown scenario or strategy, a window not
        shorter than the run, a period (or, with ``fixed``, a window) not longer than the
        latency, ``measure_from`` outside ``[0, duration)``: all before any run.
    """
    check_adapt_settings(
        scenario=scenario,
        periods=periods,
        windows=windows,
        duration=duration,
        strategies=strategies,
        latency=latency,
        measure_from=measure_from,
    )
    scene = build_scene(case, quick=quick, overrides=overrides)
    c = scene.case
    if isinstance(scenario, Drift):
        drift, label = scenario, scenario.name
    else:
        drift = scenario_drift(
            scenario, duration, c.atmosphere.seeing, seed=seed, case_drift=c.atmosphere.drift
        )
        label = scenario
    st = scene.stage2
    n = int(round(duration * st.fs))
    key = json.dumps([str(case), quick, overrides, _drift_key(drift), duration, seed], default=str)

    def disturbance(s: int) -> np.ndarray:
        # Kept for the next call on the same run (a study calls once per period).
        if (key, s) not in _DISTURBANCES:
            if len(_DISTURBANCES) >= 2:
                _DISTURBANCES.clear()
            _DISTURBANCES[key, s] = drifting_disturbance(scene, drift, n, s)
        return _DISTURBANCES[key, s]

    d = disturbance(seed)
    # An independent realisation of the same drift: what the oracle knows is the disturbance's
    # statistics, not the realisation the loop will face.
    needs = {"oracle", "adaptive-truth"} & set(strategies)
    independent = disturbance(seed + _INDEPENDENT_SEED) if needs else d
    rows = []
    late = int(0.7 * n)
    for strategy in strategies:
        pairs = [
            (p, w)
            for w in windows
            for p in (periods if strategy not in ("fixed", "eof-fixed") else (w,))
            if strategy != "oracle" or w == windows[0]
        ]
        for period, window in pairs:
            ctrl = _controller(
                strategy,
                scene,
                (d, independent),
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
            # The case's DM (its actuator stroke clips the commands, as in the comparisons).
            stage = Stage(ctrl, st.sensor, st.spec.latency_frames, dm=st.modal_dm(), name="stage 2")
            res = run_loop(
                stage,
                ModalTimeSeries(d, st.fs),
                n,
                rng=np.random.default_rng([seed, 11]),
                record=("residuals",),
            )
            run: AdaptiveRun = ctrl.last_run
            e = res.telemetry["residuals"]
            first = round((window if measure_from is None else measure_from) * st.fs)
            secs = [r.design_seconds for r in run.redesigns]
            sat = res.actuator_saturation
            tr = switch_transients(e, run.switch_frames)
            rows.append(
                AdaptRow(
                    strategy=strategy,
                    period=float(period),
                    window=float(window),
                    residual=float(np.mean(np.sum(e[first:].astype(float) ** 2, axis=1))),
                    residual_late=float(np.mean(np.sum(e[late:].astype(float) ** 2, axis=1))),
                    n_switches=run.n_switches,
                    n_rejected_modes=run.n_rejected_modes,
                    n_rejected_banks=run.n_rejected_banks,
                    design_seconds=float(np.median(secs)) if secs else 0.0,
                    clipped=int(np.sum(sat)) if sat is not None else 0,
                    transient_median=tr.median,
                    transient_worst=tr.worst,
                    reference_median=tr.reference_median,
                    reference_worst=tr.reference_worst,
                    transient_p=tr.p_value,
                    n_kept_modes=run.n_kept_modes,
                )
            )
            logger.info("%s", rows[-1])
    settings = _settings(
        st, latency, order, modulus_margin, quick, seed, design_options, adaptive_options
    )
    settings["measure_from"] = measure_from
    settings["drift"] = _drift_key(drift)[1:]  # times, seeing, wind, direction
    return AdaptStudy(c.name, label, float(duration), tuple(rows), settings)


_RULE = re.compile(r"^max\(\s*T\s*,\s*([0-9.eE+-]+)\s*\)$")


def window_rule(spec: str, period: float) -> float:
    """The window [s] a rule gives at ``period`` ``T`` [s].

    Parameters
    ----------
    spec : str
        A number of seconds (``"1"``), ``"T"`` (the window is the period) or ``"max(T, x)"``
        (the period, at least ``x`` seconds).
    period : float
        Update period [s].

    Raises
    ------
    ValueError
        A rule of none of these forms, or a window that is not positive.
    """
    text = spec.strip()
    m = _RULE.match(text)
    try:
        w = period if text == "T" else max(period, float(m.group(1))) if m else float(text)
    except ValueError:
        w = float("nan")
    if not w > 0:
        raise ValueError(
            f"window rule must be a positive number of seconds, 'T' or 'max(T, x)', got {spec!r}"
        )
    return float(w)


def seed_summary(
    studies: Sequence[AdaptStudy], strategy: str = "adaptive", fixed_window: float | None = None
) -> list[dict]:
    """Ratios of ``strategy`` to the fixed design and to the oracle over several seeds.

    Parameters
    ----------
    studies : sequence of AdaptStudy
        One study per seed (``settings["seed"]``), same scenario; each with the ``fixed``
        rows of its windows and the ``oracle`` rows of its periods (a ratio without its
        reference is NaN).
    strategy : str, default "adaptive"
        The strategy compared.
    fixed_window : float, optional
        The window [s] of the fixed design every ratio is taken to (``None``: each row's
        own window). One fixed design is a single draw of a window's estimate: a common one
        keeps the rows of different windows comparable.

    Returns
    -------
    list of dict
        One per (period, window) of ``strategy``, sorted: ``period``, ``window`` [s];
        ``seeds``; ``fixed`` and ``oracle``: the per-seed ratios (residual of ``strategy`` /
        that of the fixed design at the same window or ``fixed_window``, / that of the oracle
        at the same period); ``fixed_mean``, ``fixed_std``, ``oracle_mean``, ``oracle_std``:
        their mean and sample standard deviation over seeds (NaN std for one seed).
    """
    by: dict = {}
    for study in studies:
        fixed = {r.window: r.residual for r in study.rows if r.strategy == "fixed"}
        oracle = {r.period: r.residual for r in study.rows if r.strategy == "oracle"}
        for r in study.rows:
            if r.strategy != strategy:
                continue
            entry = by.setdefault((r.period, r.window), {"seeds": [], "fixed": [], "oracle": []})
            entry["seeds"].append(study.settings.get("seed"))
            ref = r.window if fixed_window is None else fixed_window
            entry["fixed"].append(r.residual / fixed.get(ref, float("nan")))
            entry["oracle"].append(r.residual / oracle.get(r.period, float("nan")))
    out = []
    for (period, window), entry in sorted(by.items()):
        row = {"period": period, "window": window, **entry}
        for ref in ("fixed", "oracle"):
            x = np.asarray(entry[ref], dtype=float)
            row[f"{ref}_mean"] = float(np.mean(x))
            row[f"{ref}_std"] = float(np.std(x, ddof=1)) if x.size > 1 else float("nan")
        out.append(row)
    return out
