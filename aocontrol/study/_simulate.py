"""The study layer's simulation driver: one run of a scene, single stage or cascade.

A :class:`~aocontrol.study.scene.Scene` (calibrated stages, atmosphere, science camera) and a
stage-2 controller make one run: :func:`simulate_scene` builds the stages from the scene's
settings and drives :func:`aocontrol.sim.loop.run_loop` or
:func:`~aocontrol.sim.loop.run_cascade`, with the atmosphere and the noise drawn from one
named stream of the user's seed (:mod:`aocontrol.study._seeds`). The comparison protocol
(:mod:`aocontrol.study.compare`), its calibration runs (:mod:`aocontrol.study._calibration`)
and the two-pass optical gains (:mod:`aocontrol.study._two_pass`) all run through it.
Internal to the study layer (private module; its names are used by those three).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from aocontrol.controllers import ControllerBank, Integrator
from aocontrol.sim.loop import (
    LinearModalSensor,
    PhaseSource,
    Stage,
    TurbulenceSource,
    UpstreamRecord,
    run_cascade,
    run_loop,
)
from aocontrol.study._comparison import stage2_result
from aocontrol.study._seeds import seed_sequence
from aocontrol.study.scene import Scene, StageScene

__all__ = [
    "SCHEMES",
    "UpstreamRecords",
    "replayable",
    "run_summary",
    "scene_frames",
    "scene_source",
    "scene_stage",
    "simulate_scene",
]

#: Schemes: stage 2 alone on the full atmosphere, or the two cascades.
SCHEMES = ("single", "standalone", "dcao")


def scene_frames(scene: Scene, seconds: float) -> int:
    """Stage-2 frames in ``seconds``, a whole number of the slow stage's frames (at least one)."""
    ratio = scene.case.rate_ratio
    n = int(round(seconds * scene.stage2.fs))
    return max(ratio, -(-n // ratio) * ratio)


def scene_stage(st: StageScene, controller: ControllerBank, name: str) -> Stage:
    """A stage of the scene running ``controller``: its sensor, latency, DM and basis, with
    the case's model errors (the true latency, the DM's response and misregistration, the
    sensor's true optical gains; the designs keep the nominal plant)."""
    # The sensor in the loop and its optical-gain handling, and the DM (its stroke): the
    # case's stage settings.
    sensor, tracker = st.loop_sensor()
    return Stage(
        controller,
        sensor,
        st.spec.true_latency_frames,  # the design's plus the case's model error
        dm=st.modal_dm(),
        name=name,
        basis=st.basis,
        gain_tracker=tracker,
        optical_gain_error=st.optical_gain_error(),
    )


def scene_source(scene: Scene, rng: np.random.Generator, scheme: str) -> Any:
    """The disturbance of a run: the atmosphere (and vibration); modal for ``"single"``."""
    atm = scene.atmosphere(rng)
    vib = scene.vibration_source(rng) if scene.case.vibration is not None else None
    if scheme == "single":
        return TurbulenceSource(PhaseSource(atm, vib) if vib else atm, scene.stage2.basis)
    return PhaseSource(atm, vib) if vib else atm


def simulate_scene(
    scene: Scene,
    controller: ControllerBank,
    scheme: str,
    seconds: float,
    seed: int,
    purpose: str,
    *,
    science: Any = True,
    record: tuple[str, ...] = ("measurements", "commands", "residuals"),
    progress: bool = False,
    metadata: dict | None = None,
    upstream: UpstreamRecord | None = None,
) -> Any:
    """One run of a scene: stage 2 with ``controller`` (and stage 1's integrator in a cascade).

    Internal to the study layer: the comparison's runs, its calibration runs and the two-pass
    calibration share it. The atmosphere and the noise draw from the ``purpose`` stream
    of ``seed`` (:func:`aocontrol.study._seeds.seed_sequence`).

    Parameters
    ----------
    scene : Scene
    controller : ControllerBank
        Stage 2's controller.
    scheme : str
        One of :data:`SCHEMES`.
    seconds : float
        Length after the start-up [s].
    seed : int
        User seed.
    purpose : str
        Its stream (``"exposure"``, ``"calibration"``, ``"gain_scan"``, ``"two_pass"``).
    science : bool or accumulator, default True
        The science camera (True), none (False), or an object with ``add(maps)`` and
        ``result()``.
    record : tuple of str
        Telemetry recorded.
    progress : bool
        Progress bar.
    metadata : dict, optional
        Stored in the result.
    upstream : UpstreamRecord, optional
        A cascade's upstream (:class:`aocontrol.sim.loop.UpstreamRecord`): filled by the
        first run given it, replayed by the next (same result bit for bit). Only for runs of
        one scene, seed, ``purpose`` and length (stage 1 and the disturbance the same); see
        :class:`UpstreamRecords`. Ignored for ``"single"``.

    Returns
    -------
    LoopResult or CascadeResult
    """
    sci = scene.case.science
    settle = scene_frames(scene, sci.startup)
    n = settle + scene_frames(scene, seconds)
    seeds = seed_sequence(seed, purpose)
    atm_rng, noise_rng = (np.random.default_rng(s) for s in seeds.spawn(2))
    # science: True for the camera, False for none, or an accumulator (add(maps), result()).
    camera = scene.camera().long_exposure() if science is True else (science or None)
    s2 = scene_stage(scene.stage2, controller, "stage 2")
    if scheme == "single":
        return run_loop(
            s2,
            scene_source(scene, atm_rng, scheme),
            n,
            rng=noise_rng,
            science=camera,
            basis=scene.stage2.basis,
            science_every=sci.science_every,
            record=record,
            settle_frames=settle,
            progress=progress,
            metadata=metadata,
        )
    st1 = scene.stage1
    s1 = scene_stage(st1, Integrator(st1.spec.gain, fs=st1.fs, n_modes=st1.n_modes), "stage 1")
    return run_cascade(
        s1,
        s2,
        scene_source(scene, atm_rng, scheme),
        n,
        scheme=scheme,
        basis1=st1.basis,
        basis2=scene.stage2.basis,
        rng=noise_rng,
        science=camera,
        science_every=sci.science_every,
        record=record,
        settle_frames=settle,
        progress=progress,
        metadata=metadata,
        upstream=upstream,
    )


def replayable(scene: Scene) -> bool:
    """Whether a cascade of ``scene`` can replay its upstream: stage 2's sensor reads modal
    residuals (a sensor reading phase maps needs the phase of every frame, not kept)."""
    sensor, _ = scene.stage2.loop_sensor()
    return isinstance(sensor, LinearModalSensor)


class UpstreamRecords:
    """The upstream records of one case and seed, one per purpose and length (compare_case).

    Stage 1 (its integrator at the case's gain, its sensor and noise stream) and the
    disturbance of a purpose's stream are the same for every stage-2 controller and both
    cascade schemes, so the runs of a comparison that share a purpose and a length replay
    the first one's upstream (:class:`aocontrol.sim.loop.UpstreamRecord`).
    """

    def __init__(self, scene: Scene, enabled: bool = True) -> None:
        self.enabled = enabled and replayable(scene)
        self.records: dict[tuple, UpstreamRecord] = {}

    def get(self, scheme: str, purpose: str, seconds: float) -> UpstreamRecord | None:
        if not self.enabled or scheme == "single":
            return None
        return self.records.setdefault((purpose, float(seconds)), UpstreamRecord())


def run_summary(result: Any) -> dict:
    """Strehl, mean contrast 4-6 and 1-2 lambda/D and stage 2's modal residual RMS [nm]."""
    sci = result.science
    return {
        "strehl": float(sci.strehl) if sci is not None else math.nan,
        "mean_contrast_4_6": float(sci.mean_contrast_4_6) if sci is not None else math.nan,
        "mean_contrast_1_2": float(sci.mean_contrast_1_2) if sci is not None else math.nan,
        "residual_rms_nm": float(stage2_result(result).residual_rms),
    }
