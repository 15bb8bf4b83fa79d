"""Pieces shared by the adaptive study's single-stage and cascade runs (private).

The design sources that know the truth (the oracle and the diagnostics) and the controller of
each strategy; see :mod:`aocontrol.study.adapt` for the strategies.
"""

from __future__ import annotations

import numpy as np

from aocontrol.adaptive import (
    AdaptiveController,
    AdaptivePredictor,
    datadriven_designer,
    lqg_designer,
    modal_gain_designer,
)
from aocontrol.controllers import Integrator
from aocontrol.sim.drift import Drift
from aocontrol.study.scene import Scene
from aocontrol.synthesis import TelemetryPSD, disturbance_from_telemetry, eof_default_history

#: The multi-mode predictor's strategies: trained once on the first window ("eof-fixed", the
#: fixed strategy's counterpart) or retrained every period ("eof", the adaptive one), by
#: :class:`aocontrol.adaptive.AdaptivePredictor` with the registry's history for the mode
#: count and the study's margin. Not in the default strategies (a 540-mode training is
#: seconds; the study's modal designs are the subject).
PREDICTORS = ("eof-fixed", "eof")

# Offset of the seed of the oracle's independent realisation of the drift.
_INDEPENDENT_SEED = 7919


def _prewhitened(pol: np.ndarray, plant: object) -> TelemetryPSD:
    """The study's PSD estimate of a pseudo-open loop (pre-whitened Welch)."""
    fs = 1.0 / float(plant.dt)
    return disturbance_from_telemetry(pol, np.zeros_like(pol), plant, fs=fs, method="prewhitened")


def _truth(
    d: np.ndarray,
    scene: Scene,
    frames: int,
    seed: int,
    *,
    offset: int,
    centre: float,
):
    """A design source that knows the true disturbance: ``frames`` frames of a realisation
    ``d`` (an independent one for the fair oracle) plus white noise of the true level, through
    the loops' estimator. The segment starts at ``frame + offset - centre * frames``
    (clipped to the run): ``offset`` = the switch latency and ``centre`` = 0 is the period a
    design will serve; ``offset`` = 0 and ``centre`` = 1 the window behind the request."""
    st = scene.stage2
    rng = np.random.default_rng([seed, 23])

    def oracle(frame: int) -> TelemetryPSD:
        start = int(max(0, min(frame + offset - round(centre * frames), d.shape[0] - frames)))
        seg = np.asarray(d[start : start + frames], dtype=float)
        seg = seg + rng.standard_normal(seg.shape) * st.noise_std
        return _prewhitened(seg, st.plant)

    return oracle


def _controller(
    strategy: str,
    scene: Scene,
    truth: tuple[np.ndarray, np.ndarray],
    period: float,
    window: float,
    latency: float | None,
    order: int,
    modulus_margin: float,
    n_jobs: int | None,
    seed: int,
    design_options: dict,
    adaptive_options: dict,
) -> AdaptiveController | AdaptivePredictor:
    """The controller of one strategy (``truth``: the run's disturbance and an independent
    realisation of the same drift). ``adaptive_options`` go to
    :class:`~aocontrol.adaptive.AdaptiveController` only (not to the predictors)."""
    st = scene.stage2
    initial = Integrator(st.spec.gain, fs=st.fs, n_modes=st.n_modes)
    if strategy in PREDICTORS:
        return AdaptivePredictor(
            initial,
            st.plant,
            period=window if strategy == "eof-fixed" else period,
            window=window,
            latency=latency,
            history=eof_default_history(st.n_modes),
            modulus_margin=modulus_margin,
            max_designs=1 if strategy == "eof-fixed" else None,
        )
    window_frames = round(window * st.fs)
    period_frames = round(period * st.fs)
    dd = datadriven_designer(
        order=order, modulus_margin=modulus_margin, n_jobs=n_jobs, **design_options
    )
    designer = {
        "modal-gain": modal_gain_designer(modulus_margin=modulus_margin),
        "lqg": lqg_designer(),
    }.get(strategy, dd)
    lat = 0.0 if strategy in ("adaptive-nolatency", "oracle-prophet") else latency
    kwargs = dict(
        period=window if strategy == "fixed" else period,
        window=window,
        latency=lat,
        modulus_margin=modulus_margin if strategy != "lqg" else min(modulus_margin, 0.3),
        estimator=_prewhitened,
        **adaptive_options,
    )
    if strategy == "fixed":
        kwargs["max_designs"] = 1
    lat_frames = 0 if lat is None else round(lat * st.fs)
    d, independent = truth
    if strategy == "oracle":
        # The period the design will serve (from its switch), at least a window long.
        kwargs["oracle"] = _truth(
            independent,
            scene,
            max(period_frames, window_frames),
            seed,
            offset=lat_frames + period_frames // 2,
            centre=0.5,
        )
    elif strategy == "oracle-prophet":
        # The old oracle: this run's own coming disturbance, no latency.
        kwargs["oracle"] = _truth(
            d, scene, max(period_frames, window_frames), seed, offset=0, centre=0.0
        )
    elif strategy == "adaptive-truth":
        # The adaptive's window, on the true disturbance (no pseudo-open-loop estimate).
        kwargs["oracle"] = _truth(independent, scene, window_frames, seed, offset=0, centre=1.0)
    return AdaptiveController(initial, st.plant, designer, **kwargs)


def _settings(
    stage: object,
    latency: float | None,
    order: int,
    modulus_margin: float,
    quick: bool,
    seed: int,
    design_options: dict | None,
    adaptive_options: dict | None,
) -> dict:
    """The settings a study records with its rows (``stage``: the scene's stage 2)."""
    return dict(
        latency=latency,
        order=order,
        modulus_margin=modulus_margin,
        quick=quick,
        seed=seed,
        n_modes=stage.n_modes,
        fs=stage.fs,
        design_options=dict(design_options or {}),
        adaptive_options=dict(adaptive_options or {}),
    )


#: Named drift scenarios of the adaptive study (:func:`scenario_drift`).
SCENARIOS = ("wind-doubles", "seeing-worsens", "stochastic", "case")
# Fractions of the run between which the scripted scenarios ramp.
_RAMP = (0.2, 0.5)


def scenario_drift(
    name: str, duration: float, base_seeing: float, *, seed: int = 0, case_drift: object = None
) -> Drift:
    """The :class:`~aocontrol.sim.drift.Drift` of a named scenario.

    Parameters
    ----------
    name : str
        One of :data:`SCENARIOS`.
    duration : float
        Run length [s] (the ramps span 20 % to 50 % of it).
    base_seeing : float
        The case's seeing [arcsec] (median of the stochastic model).
    seed : int
        Seed of the stochastic model.
    case_drift : DriftSpec, optional
        The case's ``[atmosphere.drift]`` (scenario ``case``).

    Raises
    ------
    ValueError
        Unknown scenario, or ``case`` for a case without a drift.
    """
    start, stop = _RAMP[0] * duration, _RAMP[1] * duration
    if name == "wind-doubles":
        return Drift.ramp(start, stop, wind=2.0)
    if name == "seeing-worsens":
        return Drift.ramp(start, stop, seeing=1.5)
    if name == "stochastic":
        return Drift.stochastic(duration, seed, base_seeing=base_seeing)
    if name == "case":
        if case_drift is None:
            raise ValueError("scenario 'case' needs a case with an [atmosphere.drift] table")
        return case_drift.build(base_seeing)
    raise ValueError(f"scenario must be one of {list(SCENARIOS)}, got {name!r}")
