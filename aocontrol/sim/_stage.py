"""A simulator stage (frozen configuration) and the sensor protocol.

A :class:`Stage` is validated once and never mutated; the runner of
:mod:`aocontrol.sim.loop` creates the per-frame state of a run from it (controller state,
delay line, DM saturation counters, telemetry buffers).

Sensor protocol (:class:`Sensor`): ``n_modes`` (``None`` for any count),
``senses_phase`` (``False``: ``measure`` takes the modal residual ``(n_modes,)``; ``True``:
it takes the residual OPD map ``(n_pix, n_pix)``), ``measure(residual, rng) -> (n_modes,)``
[nm]. :class:`~aocontrol.sim.wfs.LinearModalSensor` and :class:`DiffractiveSensor` implement it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from aocontrol._validation import check_nonnegative, check_positive
from aocontrol.controllers import ControllerBank
from aocontrol.plant import split_latency
from aocontrol.sim.dm import ModalDM
from aocontrol.sim.wfs.calibration import LinearModalSensor

__all__ = ["Sensor", "DiffractiveSensor", "Stage"]


@runtime_checkable
class Sensor(Protocol):
    """A wavefront sensor of a stage: the residual (modal or a phase map) -> modal measurement.

    Parameters
    ----------
    *args, **kwargs
        Not used: a protocol is not instantiated; any object with the members below
        satisfies it (``isinstance`` checks them at run time).
    """

    senses_phase: bool

    @property
    def n_modes(self) -> int | None:
        """Modes measured (``None``: any count)."""

    def measure(self, residual: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Modal measurement ``(n_modes,)`` [nm] of one residual."""


@dataclass(frozen=True)
class DiffractiveSensor:
    """A diffractive WFS in the loop: ``m = R s(residual phase map)`` with detector noise.

    Each frame the residual OPD map (turbulence minus DM shape, fitting error included) goes
    through the WFS model (pyramid or Shack-Hartmann), with Poisson and read-out noise on the
    detector pixels when ``photons`` is given, then through the reconstructor.

    Parameters
    ----------
    wfs : object with ``signals(opd)`` and ``measure(opd, photons, read_noise, rng)``
        E.g. :class:`aocontrol.sim.wfs.PyramidWFS`; signals are reference-subtracted.
    reconstructor : ndarray, shape (n_modes, n_signals)
        Signals to modal measurements [nm] (e.g. :func:`aocontrol.sim.wfs.reconstructor`).
    photons : float, optional
        Photo-electrons per frame in the WFS; ``None`` for a noise-free sensor.
    read_noise : float
        Read-out noise [e- RMS per pixel].
    """

    wfs: Any
    reconstructor: Any
    photons: float | None = None
    read_noise: float = 0.0

    #: Sensor protocol: this sensor measures residual phase maps.
    senses_phase: ClassVar[bool] = True

    def __post_init__(self) -> None:
        r = np.asarray(self.reconstructor, dtype=float)
        if r.ndim != 2 or not np.all(np.isfinite(r)):
            raise ValueError(
                f"reconstructor must be a finite (n_modes, n_signals) matrix, got shape {r.shape}"
            )
        n_signals = getattr(self.wfs, "n_signals", r.shape[1])
        if r.shape[1] != n_signals:
            raise ValueError(
                f"reconstructor has {r.shape[1]} columns, the WFS gives {n_signals} signals"
            )
        object.__setattr__(self, "reconstructor", r)
        if self.photons is not None:
            check_positive("photons", self.photons)
        check_nonnegative("read_noise", self.read_noise)

    @property
    def n_modes(self) -> int:
        """Modes reconstructed."""
        return int(self.reconstructor.shape[0])

    @property
    def noisy(self) -> bool:
        """Whether detector noise is simulated (``photons`` given)."""
        return self.photons is not None

    def measure(self, residual: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Modal measurement ``(n_modes,)`` [nm] of one residual OPD map.

        Parameters
        ----------
        residual : ndarray (n_pix, n_pix)
            Residual OPD map [nm].
        rng : numpy.random.Generator
            Source of the detector noise.

        Returns
        -------
        ndarray (n_modes,)
        """
        if self.photons is None:
            sig = self.wfs.signals(residual)
        else:
            sig = self.wfs.measure(residual, self.photons, self.read_noise, rng)
        return self.reconstructor @ sig

    def measure_map(self, opd: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Same as :meth:`measure` (former name).

        Parameters
        ----------
        opd : ndarray (n_pix, n_pix)
            Residual OPD map [nm].
        rng : numpy.random.Generator
            Source of the detector noise.

        Returns
        -------
        ndarray (n_modes,)
        """
        return self.measure(opd, rng)


@dataclass(frozen=True)
class Stage:
    """One AO stage (frozen, validated configuration): controller, sensor, delay, DM stroke.

    Parameters
    ----------
    controller : ControllerBank
        Runs at the stage rate ``controller.fs`` [Hz].
    sensor : LinearModalSensor or DiffractiveSensor
        Default: a noise-free linear sensor of optical gain 1.
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
        Modes-to-commands matrix of the DM (``ModalBasis.m2c``).
    name : str
        Name used in messages and results.

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
        if isinstance(self.sensor, LinearModalSensor):
            self.sensor.arrays(n)
        elif isinstance(self.sensor, DiffractiveSensor):
            if self.sensor.n_modes != n:
                raise ValueError(
                    f"the sensor reconstructs {self.sensor.n_modes} modes, the controller has {n}"
                )
        else:
            raise TypeError(
                "sensor must be a LinearModalSensor (alias LinearModalWFS) or a "
                f"DiffractiveSensor, got {type(self.sensor).__name__}"
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
        """Whether the sensor needs residual phase maps (a :class:`DiffractiveSensor`)."""
        return bool(self.sensor.senses_phase)
