"""A simulator stage (frozen configuration): controller, sensor, basis, delay, DM stroke.

A :class:`Stage` is validated once and never mutated; the runner of
:mod:`aocontrol.sim.loop` creates the per-frame state of a run from it (controller state,
delay line, DM saturation counters, the sensor's run state, telemetry buffers).

The sensor is any object implementing the sensor protocol of
:mod:`aocontrol.sim.wfs.sensors` (:class:`~aocontrol.sim.wfs.LinearModalSensor`,
:class:`~aocontrol.sim.wfs.DiffractiveSensor`); the runner calls it the same way whatever its
kind.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from aocontrol.controllers import ControllerBank
from aocontrol.plant import split_latency
from aocontrol.sim._gain_tracking import DitherGainTracker
from aocontrol.sim.dm import ModalDM
from aocontrol.sim.wfs.sensors import DiffractiveSensor, LinearModalSensor, Sensor

__all__ = ["Sensor", "DiffractiveSensor", "Stage"]


@dataclass(frozen=True)
class Stage:
    """One AO stage (frozen, validated configuration): controller, sensor, delay, DM stroke.

    Parameters
    ----------
    controller : ControllerBank
        Runs at the stage rate ``controller.fs`` [Hz].
    sensor : Sensor
        Any sensor implementing the protocol of :mod:`aocontrol.sim.wfs.sensors`
        (:class:`LinearModalSensor`, :class:`DiffractiveSensor`). Default: a noise-free
        linear sensor of optical gain 1.
    latency_frames : float
        RTC latency beyond the one-frame WFS integration [frames] (as in ``loop_plant``), in
        ``[0, aocontrol.plant.MAX_LATENCY_FRAMES]``.
    stroke : float or ndarray (n_modes,), optional
        Modal command limit [nm]: the applied command is clipped (counted as saturation).
    dm_stroke : float, optional
        Actuator stroke [nm] (e.g. 3200 for the SAXO+ stage-2 DM, +-3.2 um): the actuator
        commands ``m2c @ u`` are clipped and projected back on the modes (least squares in
        actuator space); clipped actuator-frames are counted. Needs ``m2c``. Approximation
        of the modal simulator: the part of the clipped shape outside the controlled modes is
        dropped.
    m2c : ndarray (n_act, n_modes), optional
        Modes-to-commands matrix of the DM; default ``basis.m2c`` when a basis is given.
    name : str
        Name used in messages and results.
    basis : ModalBasis-like, optional
        The stage's modal basis (``n_modes``, ``modes`` (n_modes, n_valid), ``synthesize``,
        ``pupil``, ``m2c``): the runner forms phase maps with it (science camera, diffractive
        sensor) and a cascade projects between the stages' bases. Needed by a sensor that
        reads phase maps unless passed to the runner.
    gain_tracker : DitherGainTracker, optional
        Online optical-gain tracking and compensation (:mod:`aocontrol.sim._gain_tracking`).

    Attributes
    ----------
    dm : aocontrol.sim.dm.ModalDM
        The stage's DM, the one owner of ``stroke`` and ``dm_stroke``.
    delay : tuple of (int, float)
        ``aocontrol.plant.split_latency(latency_frames)``.
    """

    controller: ControllerBank
    sensor: Any = field(default_factory=LinearModalSensor)
    latency_frames: float = 0.0
    stroke: Any = None
    dm_stroke: float | None = None
    m2c: Any = None
    name: str = "stage"
    basis: Any = field(default=None, repr=False, compare=False)
    gain_tracker: DitherGainTracker | None = None
    dm: ModalDM = field(init=False, repr=False, compare=False)
    delay: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.controller, ControllerBank):
            raise TypeError(
                f"controller must be a ControllerBank, got {type(self.controller).__name__}"
            )
        if not isinstance(self.name, str):
            raise TypeError(f"name must be a str, got {type(self.name).__name__}")
        n = self.controller.n_modes
        object.__setattr__(self, "delay", split_latency(self.latency_frames))
        if self.basis is not None:
            nb = getattr(self.basis, "n_modes", None)
            if nb is None or not hasattr(self.basis, "modes"):
                raise TypeError(
                    "basis must be a ModalBasis-like object (n_modes, modes, synthesize, "
                    f"pupil), got {type(self.basis).__name__}"
                )
            if int(nb) != n:
                raise ValueError(f"basis has {nb} modes, the controller of {self.name!r} has {n}")
            if self.m2c is None and self.dm_stroke is not None:
                object.__setattr__(self, "m2c", getattr(self.basis, "m2c", None))
        if not isinstance(self.sensor, Sensor):
            raise TypeError(
                "sensor must implement the sensor protocol (check, start; e.g. a "
                f"LinearModalSensor or a DiffractiveSensor), got {type(self.sensor).__name__}"
            )
        self.sensor.check(n, self.basis)
        if self.gain_tracker is not None and not isinstance(self.gain_tracker, DitherGainTracker):
            raise TypeError(
                "gain_tracker must be a DitherGainTracker or None, got "
                f"{type(self.gain_tracker).__name__}"
            )
        dm = ModalDM(n, stroke=self.stroke, actuator_stroke=self.dm_stroke, m2c=self.m2c)
        object.__setattr__(self, "dm", dm)
        if self.dm_stroke is not None:
            object.__setattr__(self, "m2c", dm.m2c)

    @property
    def fs(self) -> float:
        """Stage rate [Hz]."""
        return self.controller.fs

    @property
    def n_modes(self) -> int:
        """Controlled modes."""
        return self.controller.n_modes

    @property
    def senses_phase(self) -> bool:
        """Whether the sensor reads residual phase maps (e.g. a :class:`DiffractiveSensor`)."""
        return bool(getattr(self.sensor, "senses_phase", False))
