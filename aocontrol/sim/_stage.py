"""A simulator stage (frozen configuration): controller, sensor, basis, delay, DM.

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

from aocontrol._deprecation import DeprecatedAttribute, declare, warn_renamed
from aocontrol.controllers import ControllerBank
from aocontrol.plant import split_latency
from aocontrol.sim._gain_tracking import DitherGainTracker
from aocontrol.sim.dm import ModalDM
from aocontrol.sim.model_errors import OpticalGainError
from aocontrol.sim.wfs.sensors import DiffractiveSensor, LinearModalSensor, Sensor

__all__ = ["Sensor", "DiffractiveSensor", "Stage"]


_DM_NOTE = "the stage's DM: dm=ModalDM.from_basis(basis, actuator_stroke=...) or ModalDM(...)"


for _old in ("stroke", "dm_stroke", "m2c"):  # Stage(...) keywords, warned in __init__
    declare("aocontrol.sim._stage.Stage", _old, "dm", kind="keyword")


@dataclass(frozen=True, init=False)
class Stage:
    """One AO stage (frozen, validated configuration): controller, sensor, delay, DM.

    The stage's DM (:class:`~aocontrol.sim.dm.ModalDM`) owns the stroke: the actuator stroke
    (``actuator_stroke`` [nm], the physical limit) and a limit per mode (``modal_stroke``
    [nm RMS]); the stage keeps no copy. A controller's own ``command_limit`` is a separate,
    controller-side setting (see :mod:`aocontrol.sim.dm` for the stroke's names).

    Parameters
    ----------
    controller : ControllerBank
        Runs at the stage rate ``controller.fs`` [Hz].
    sensor : Sensor
        Any sensor implementing the protocol of :mod:`aocontrol.sim.wfs.sensors`
        (:class:`LinearModalSensor`, :class:`DiffractiveSensor`). Default (or ``None``): a
        noise-free linear sensor of optical gain 1.
    latency_frames : float
        RTC latency beyond the one-frame WFS integration [frames] (as in ``loop_plant``), in
        ``[0, aocontrol.plant.MAX_LATENCY_FRAMES]``.
    dm : ModalDM, optional
        The stage's DM, ``dm.n_modes == controller.n_modes``, e.g.
        ``ModalDM.from_basis(basis, actuator_stroke=3200.0)`` (the SAXO+ stage-2 DM,
        +-3.2 um: the actuator commands ``m2c @ u`` are clipped and projected back on the
        modes; clipped actuator-frames are counted). Default: an unlimited DM.
    name : str
        Name used in messages and results.
    basis : ModalBasis-like, optional
        The stage's modal basis (``n_modes``, ``modes`` (n_modes, n_valid), ``synthesize``,
        ``pupil``, ``m2c``): the runner forms phase maps with it (science camera, diffractive
        sensor) and a cascade projects between the stages' bases. Needed by a sensor that
        reads phase maps unless passed to the runner.
    gain_tracker : DitherGainTracker, optional
        Online optical-gain tracking and compensation (:mod:`aocontrol.sim._gain_tracking`).
    optical_gain_error : OpticalGainError, optional
        The sensor's true optical gains relative to those the loop compensates, possibly
        drifting (:class:`aocontrol.sim.model_errors.OpticalGainError`), a model error.
        ``None`` (or a neutral one): the compensated gains are the true ones.
    stroke, dm_stroke, m2c : optional
        Deprecated (``DeprecationWarning``): the DM's ``modal_stroke`` [nm RMS],
        ``actuator_stroke`` [nm] and ``m2c`` (default ``basis.m2c`` with ``dm_stroke``), from
        which the stage builds ``dm``; pass ``dm`` instead. Reading ``stage.stroke``,
        ``stage.dm_stroke`` or ``stage.m2c`` returns the DM's, with the same warning.

    Attributes
    ----------
    dm : aocontrol.sim.dm.ModalDM
        The stage's DM, the one owner of the stroke.
    delay : tuple of (int, float)
        ``aocontrol.plant.split_latency(latency_frames)``.

    Raises
    ------
    TypeError
        A controller, sensor, basis, DM or tracker of the wrong kind, or ``dm`` together
        with a deprecated stroke keyword.
    ValueError
        A DM or basis whose number of modes is not the controller's, a bad latency or stroke.
    """

    controller: ControllerBank
    sensor: Any = field(default_factory=LinearModalSensor)
    latency_frames: float = 0.0
    dm: ModalDM | None = field(default=None, repr=False, compare=False)
    name: str = "stage"
    basis: Any = field(default=None, repr=False, compare=False)
    gain_tracker: DitherGainTracker | None = None
    optical_gain_error: OpticalGainError | None = None
    delay: tuple = field(init=False, repr=False, compare=False)

    #: Deprecated: the DM's ``modal_stroke`` [nm RMS] (``stage.dm.modal_stroke``).
    stroke = DeprecatedAttribute("dm.modal_stroke", _DM_NOTE)
    #: Deprecated: the DM's ``actuator_stroke`` [nm] (``stage.dm.actuator_stroke``).
    dm_stroke = DeprecatedAttribute("dm.actuator_stroke", _DM_NOTE)
    #: Deprecated: the DM's ``m2c`` (``stage.dm.m2c``).
    m2c = DeprecatedAttribute("dm.m2c", _DM_NOTE)

    def __init__(
        self,
        controller: ControllerBank,
        sensor: Any = None,
        latency_frames: float = 0.0,
        *,
        dm: ModalDM | None = None,
        name: str = "stage",
        basis: Any = None,
        gain_tracker: DitherGainTracker | None = None,
        optical_gain_error: OpticalGainError | None = None,
        stroke: Any = None,
        dm_stroke: float | None = None,
        m2c: Any = None,
    ) -> None:
        fields = dict(
            controller=controller,
            sensor=LinearModalSensor() if sensor is None else sensor,
            latency_frames=latency_frames,
            dm=dm,
            name=name,
            basis=basis,
            gain_tracker=gain_tracker,
            optical_gain_error=optical_gain_error,
        )
        for key, value in fields.items():
            object.__setattr__(self, key, value)
        self._check()
        legacy = {"stroke": stroke, "dm_stroke": dm_stroke, "m2c": m2c}
        legacy = {k: v for k, v in legacy.items() if v is not None}
        if legacy and dm is not None:
            raise TypeError(
                f"Stage: give dm only ({sorted(legacy)} are the deprecated way to build it), "
                "got both"
            )
        for key in legacy:
            warn_renamed("Stage", key, "dm", _DM_NOTE)
        n = self.controller.n_modes
        if dm is None:
            if dm_stroke is not None and m2c is None and basis is not None:
                m2c = getattr(basis, "m2c", None)
            dm = ModalDM(n, modal_stroke=stroke, actuator_stroke=dm_stroke, m2c=m2c)
        elif not isinstance(dm, ModalDM):
            raise TypeError(f"dm must be an aocontrol.sim.dm.ModalDM, got {type(dm).__name__}")
        elif dm.n_modes != n:
            raise ValueError(f"dm has {dm.n_modes} modes, the controller of {self.name!r} has {n}")
        object.__setattr__(self, "dm", dm)

    def _check(self) -> None:
        """Validate the fields set by ``__init__`` (the DM apart) and set ``delay``."""
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
        if not isinstance(self.sensor, Sensor):
            raise TypeError(
                "sensor must implement the sensor protocol (check, start; e.g. a "
                f"LinearModalSensor or a DiffractiveSensor), got {type(self.sensor).__name__}"
            )
        self.sensor.check(n, self.basis)
        err = self.optical_gain_error
        if err is not None:
            if not isinstance(err, OpticalGainError):
                raise TypeError(
                    f"optical_gain_error must be an OpticalGainError, got {type(err).__name__}"
                )
            for name in ("factor", "phase"):
                arr = getattr(err, name)
                if arr.ndim == 1 and arr.shape != (n,):
                    raise ValueError(
                        f"optical_gain_error.{name} has {arr.shape[0]} values, the controller "
                        f"of {self.name!r} has {n} modes"
                    )
            if err.is_identity:
                object.__setattr__(self, "optical_gain_error", None)
        if self.gain_tracker is not None and not isinstance(self.gain_tracker, DitherGainTracker):
            raise TypeError(
                "gain_tracker must be a DitherGainTracker or None, got "
                f"{type(self.gain_tracker).__name__}"
            )

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
