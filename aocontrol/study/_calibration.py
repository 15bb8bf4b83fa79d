"""Calibration runs: the design inputs of a case's controllers from the simulator's telemetry.

A run of the reference integrator (:func:`aocontrol.study._simulate.simulate_scene`, its
``"calibration"`` stream) records stage 2's measurements and commands; their pseudo-open loop
goes through :func:`aocontrol.synthesis.disturbance_from_telemetry` (pre-whitened by default)
to the PSDs every design is made from (:class:`~aocontrol.synthesis.DesignInputs`) -- never
from the hidden disturbance. For a diffractive stage 2, the sensor's error is modelled apart
for the predicted residual (:class:`~aocontrol.study._comparison.ResidualModel`).
"""

from __future__ import annotations

import numpy as np

from aocontrol.controllers import Integrator
from aocontrol.sim.loop import UpstreamRecord
from aocontrol.study._comparison import ResidualModel, stage2_result
from aocontrol.study._registry import DesignInputs
from aocontrol.study._simulate import simulate_scene
from aocontrol.study.scene import Scene
from aocontrol.synthesis import disturbance_from_telemetry

__all__ = ["calibration_seconds", "calibrate_scene", "design_inputs"]

# Lengths of the calibration run [s]: at least _CAL_FRAMES (_QUICK_CAL_FRAMES) stage-2 frames
# (27 s at 300 Hz, cheap since the cost goes with frames) so that its Welch PSDs average at
# least 8 segments (synthesis.default_nperseg): a PSD of one segment is a chi-square(2)
# scatter that the designs would fit.
_CAL_SECONDS, _CAL_FRAMES = 2.0, 8192
_QUICK_CAL_SECONDS, _QUICK_CAL_FRAMES = 0.5, 4096


def calibration_seconds(scene: Scene, quick: bool = False) -> float:
    """Length of the calibration run [s]: at least ``_CAL_FRAMES`` (quick:
    ``_QUICK_CAL_FRAMES``) stage-2 frames and ``_CAL_SECONDS`` (``_QUICK_CAL_SECONDS``)."""
    s, n = (_QUICK_CAL_SECONDS, _QUICK_CAL_FRAMES) if quick else (_CAL_SECONDS, _CAL_FRAMES)
    return max(s, n / scene.stage2.fs)


def design_inputs(
    scene: Scene,
    scheme: str,
    gain: float,
    *,
    seconds: float,
    seed: int,
    estimator: str = "prewhitened",
    upstream: UpstreamRecord | None = None,
    progress: bool = False,
) -> DesignInputs:
    """Calibration run with the reference integrator and the PSDs of its telemetry.

    Optical gains: the recorded measurements are those the controller received, after the
    loop's compensation (the calibrated gains for ``"calibrated"`` and ``"two-pass"``, the
    tracker's running estimate for ``"tracked"``), so the pseudo-open loop ``m + G u`` is
    already rebuilt with the gains the loop applied (``optical_gain=`` of
    :func:`aocontrol.synthesis.disturbance_from_telemetry` stays 1), as an instrument would
    do. ``"none"`` (raw reconstructor): the designs see the unit-gain plant, not the loop's
    ``og G`` (not wired: one plant for all modes). What the pseudo-open loop cannot
    separate from the disturbance is the sensor's error beyond ``og e`` (aliasing of the
    fitting error, non-linearity; coloured, re-injected through ``T``): the designs are
    made on it as disturbance. The predicted residual of a diffractive stage 2 is not
    (:class:`ResidualModel`, from :func:`calibrate_scene`): the error's PSD from the calibration
    run's sensor output and modal residual, the loop's ``og`` for ``"none"``.

    Parameters
    ----------
    scene : Scene
    scheme : str
        One of :data:`SCHEMES`.
    gain : float
        Reference integrator gain of the calibration run.
    seconds : float
        Length of the calibration run [s] (after the start-up).
    seed : int
        User seed; the run draws from its ``"calibration"`` stream
        (:mod:`aocontrol.study._seeds`), independent of every exposure's.
    estimator : {"prewhitened", "welch"}
        Disturbance estimator (``method`` of
        :func:`aocontrol.synthesis.disturbance_from_telemetry`).
    upstream : UpstreamRecord, optional
        Upstream of the calibration run, shared with the other scheme's (see
        :func:`simulate_scene`).
    progress : bool
        Progress bar on the calibration run.

    Returns
    -------
    DesignInputs
    """
    return calibrate_scene(
        scene,
        scheme,
        gain,
        seconds=seconds,
        seed=seed,
        estimator=estimator,
        upstream=upstream,
        progress=progress,
    )[0]


def calibrate_scene(
    scene: Scene,
    scheme: str,
    gain: float,
    *,
    seconds: float,
    seed: int,
    estimator: str = "prewhitened",
    upstream: UpstreamRecord | None = None,
    progress: bool = False,
) -> tuple[DesignInputs, ResidualModel | None]:
    """:func:`design_inputs` and, for a diffractive stage 2, the :class:`ResidualModel` of
    the predicted residual (``None`` for a linear one: its error is the white noise the
    estimator's floor already holds).

    Between runs the calibration record and the exposure are each one draw of the
    atmosphere: each cell of a comparison carries both standard errors
    (:meth:`~aocontrol.study.compare.Cell.ratio_interval`). The measured agreement of the
    prediction is in ``docs/benchmarks.md`` (``bench_telemetry_design.py``).
    """
    st = scene.stage2
    ref = Integrator(gain, fs=st.fs, n_modes=st.n_modes)
    res = simulate_scene(
        scene,
        ref,
        scheme,
        seconds,
        seed,
        "calibration",
        science=False,
        upstream=upstream,
        progress=progress,
    )
    r2 = stage2_result(res)
    k = r2.settle_frames
    m = np.asarray(r2.telemetry["measurements"][k:], dtype=float)
    u = np.asarray(r2.telemetry["commands"][k:], dtype=float)
    tel = disturbance_from_telemetry(m, u, st.plant, fs=st.fs, method=estimator)
    model = None
    if st.spec.sensor == "diffractive":
        e = np.asarray(r2.telemetry["residuals"][k:], dtype=float)
        raw = st.spec.optical_gain == "none"
        model = ResidualModel.from_calibration(
            m, u, e, st.plant, st.fs, optical_gain=st.calibrated_gains if raw else None,
            estimator=estimator,
        )  # fmt: skip
    design = DesignInputs(
        plant=st.plant,
        freqs=tel.freqs,
        psd=tel.psd,
        noise_psd=tel.noise_psd,
        fs=st.fs,
        n_modes=st.n_modes,
        reference_gain=float(gain),
        telemetry=tel,
        command_limit=st.modal_dm().command_bound,
    )
    return design, model
