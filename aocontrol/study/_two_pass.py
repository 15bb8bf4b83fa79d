"""Two-pass optical gains: stage 2's gains calibrated around the closed-loop residual of a
first run (the case setting ``optical_gain = "two-pass"``)."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from aocontrol.controllers import Integrator
from aocontrol.study._simulate import simulate_scene
from aocontrol.study.scene import Scene

__all__ = ["two_pass_scene"]

logger = logging.getLogger(__name__)


class _MapSample:
    """Science accumulator that keeps residual maps, evenly thinned to at most ``2 n``."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.maps: list[np.ndarray] = []
        self.stride = 1
        self.seen = 0

    def add(self, maps: np.ndarray) -> None:
        for m in np.asarray(maps, dtype=float):
            if self.seen % self.stride == 0:
                self.maps.append(m)
            self.seen += 1
            if len(self.maps) >= 2 * self.n:
                self.maps = self.maps[::2]
                self.stride *= 2

    def result(self) -> np.ndarray:
        idx = np.linspace(0, len(self.maps) - 1, min(self.n, len(self.maps))).round()
        return np.array([self.maps[int(i)] for i in np.unique(idx)])


def two_pass_scene(
    scene: Scene, scheme: str, gain: float, *, seconds: float, seed: int, n_screens: int = 4
) -> Scene:
    """Stage 2's optical gains calibrated around the closed-loop residual of a first run.

    The first pass runs the reference integrator (gain ``gain``) with the scene as built
    (gains calibrated around the fitting error alone) and keeps ``n_screens`` residual phase
    maps after both stages, evenly spread over the run; the optical gains
    (:func:`aocontrol.sim.wfs.optical_gains`, exact linearisation) around them replace the
    scene's, so the compensation includes the servo-lag and noise residual, which the
    fitting-error calibration leaves out (the red cases).

    Parameters
    ----------
    scene : Scene
    scheme : str
        One of :data:`SCHEMES`.
    gain : float
        Reference integrator gain of the first pass.
    seconds : float
        Length of the first pass [s] (after the start-up).
    seed : int
        User seed; the first pass draws from its ``"two_pass"`` stream
        (:mod:`aocontrol.study._seeds`), independent of the exposure's.
    n_screens : int
        Residual maps averaged.

    Returns
    -------
    Scene
        The scene with ``stage2.optical_gain`` (and its compensated linear sensor) replaced.

    Raises
    ------
    ValueError
        If stage 2 has no diffractive model.
    """
    from aocontrol.sim.wfs import optical_gains

    st = scene.stage2
    if st.wfs is None or st.calibration is None:
        raise ValueError(f"two-pass optical gains need a pyramid stage 2, got {st.spec.wfs!r}")
    sample = _MapSample(n_screens)
    ref = Integrator(gain, fs=st.fs, n_modes=st.n_modes)
    simulate_scene(scene, ref, scheme, seconds, seed, "two_pass", science=sample, record=())
    maps = sample.result()
    og = optical_gains(
        st.wfs, st.basis, maps, amplitude=10.0, recon=st.calibration.recon, method="derivative"
    )
    logger.info(
        "two-pass optical gains: median %.3f (fitting-error calibration %.3f), %d screens",
        float(np.median(og)),
        float(np.median(st.calibrated_gains)),
        maps.shape[0],
    )
    return dataclasses.replace(scene, stage2=st.with_optical_gains(og))
