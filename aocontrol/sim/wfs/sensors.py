"""The sensors of the simulator's stages and the one sensor protocol the loop driver calls.

Sensor protocol (:class:`Sensor`)
---------------------------------
A sensor is a frozen configuration; ``start(n_modes, rng, pupil)`` returns its per-run state
(:class:`SensorRun`), which the driver of :mod:`aocontrol.sim.loop` calls once per frame of
the stage's rate, the same way for every kind of sensor:

* ``begin_chunk(m)`` before a chunk of ``m`` frames (a linear sensor draws its noise there);
* ``read(j, residual, opd) -> (n_modes,)`` [nm]: the measurement of frame ``j`` of the chunk,
  from the residual of the previous frame (WFS integration of one frame), given as its modal
  coefficients ``residual`` (n_modes,) [nm] and as a zero-argument callable ``opd()`` that forms
  the residual OPD map ``(n_pix, n_pix)`` [nm] on demand (fitting error included): a linear
  sensor uses the coefficients, a diffractive one calls ``opd()``. The driver forms no map for a
  sensor that does not ask for one.

A run state also gives ``optical_gain`` and ``noise_std`` (n_modes,): the loop gain factor and
modal noise level the runner's pole check and divergence guards assume, and ``needs_phase``
(whether ``read`` will call ``opd``: the driver then requires phase maps from its source).

Two sensors implement it: :class:`LinearModalSensor` (the fast default,
``m = g e + n``) and :class:`DiffractiveSensor` (a pyramid or Shack-Hartmann model in the loop,
photon and read noise on the detector pixels, then a reconstructor).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from aocontrol._validation import check_finite_array, check_int, check_nonnegative, check_positive
from aocontrol.sim.wfs._common import blas_threads
from aocontrol.sim.wfs.calibration import WFSCalibration, calibrate, optical_gains

__all__ = ["Sensor", "SensorRun", "LinearModalSensor", "DiffractiveSensor"]

logger = logging.getLogger(__name__)

# Flat-wavefront measurements used to estimate a diffractive sensor's noise level (for the
# divergence guard only).
_NOISE_PROBES = 8


@runtime_checkable
class SensorRun(Protocol):
    """Per-run state of a sensor (see the module docstring).

    Parameters
    ----------
    *args, **kwargs
        Not used: a protocol is not instantiated.
    """

    optical_gain: np.ndarray
    noise_std: np.ndarray
    needs_phase: bool

    def begin_chunk(self, m_chunk: int) -> None:
        """Prepare ``m_chunk`` frames."""

    def read(self, j: int, residual: np.ndarray, opd: Callable[[], np.ndarray]) -> np.ndarray:
        """Measurement ``(n_modes,)`` [nm] of frame ``j`` of the chunk."""


@runtime_checkable
class Sensor(Protocol):
    """A stage's wavefront sensor (see the module docstring).

    Parameters
    ----------
    *args, **kwargs
        Not used: a protocol is not instantiated; any object with the members below
        satisfies it (``isinstance`` checks them at run time).
    """

    @property
    def n_modes(self) -> int | None:
        """Modes measured (``None``: any count)."""

    def check(self, n_modes: int, basis: Any = None) -> None:
        """Raise ``ValueError`` (naming the argument) if the sensor does not fit the stage."""

    def start(self, n_modes: int, rng: np.random.Generator, pupil: Any = None) -> SensorRun:
        """Per-run state for a stage of ``n_modes`` modes."""


def _as_modal(name: str, value: Any) -> np.ndarray:
    """A finite scalar or 1-D array, read-only."""
    out = check_finite_array(name, value, ndim=(0, 1)).copy()
    if out.size == 0:
        raise ValueError(f"{name} must not be empty")
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class LinearModalSensor:
    """The linear modal WFS of the fast loop: ``measurement = optical_gain * residual + noise``.

    The one linear modal sensor class of the project (``LinearModalWFS`` is a deprecated
    alias). :meth:`from_diffractive` / :meth:`from_calibration` derive it from a diffractive WFS
    model. It implements the sensor protocol of this module (its run state reads the modal
    residual, never a phase map).

    Parameters
    ----------
    optical_gain : float or array_like, shape (n_modes,)
        Per-mode optical gain (dimensionless, finite and > 0; 1 = diffraction-limited
        calibration). A scalar applies to every mode.
    noise_std : float or array_like, shape (n_modes,)
        Per-mode measurement noise standard deviation [nm RMS] (finite, >= 0), white,
        independent between modes and frames. A scalar applies to every mode.
    calibration : WFSCalibration, optional
        The calibration it was derived from (kept for reference, not compared).

    Raises
    ------
    ValueError
        If a value is not finite, an optical gain is <= 0, a noise level < 0, or both
        arguments are arrays of different lengths.

    Notes
    -----
    The modal noise of a real WFS is slightly correlated between modes; this model keeps its
    per-mode variance only.

    Examples
    --------
    >>> wfs = LinearModalSensor(optical_gain=[1.0, 0.5], noise_std=[0.0, 0.0])
    >>> wfs.measure(np.array([2.0, 2.0]), np.random.default_rng(0))
    array([2., 1.])
    """

    optical_gain: Any = 1.0
    noise_std: Any = 0.0
    calibration: WFSCalibration | None = field(default=None, repr=False, compare=False)

    #: Former protocol flag (the run state's ``needs_phase`` replaces it).
    senses_phase: ClassVar[bool] = False

    def __post_init__(self) -> None:
        g = _as_modal("optical_gain", self.optical_gain)
        s = _as_modal("noise_std", self.noise_std)
        if g.ndim == 1 and s.ndim == 1 and g.shape != s.shape:
            raise ValueError(
                f"optical_gain and noise_std must have the same shape (n_modes,), "
                f"got {g.shape} and {s.shape}"
            )
        if np.any(g <= 0):
            raise ValueError(
                f"optical_gain must be finite and > 0 for every mode, found min {g.min()!r}"
            )
        if np.any(s < 0):
            raise ValueError(f"noise_std must be >= 0 [nm], found min {s.min()!r}")
        object.__setattr__(self, "optical_gain", g)
        object.__setattr__(self, "noise_std", s)

    @property
    def n_modes(self) -> int | None:
        """Number of modes, or ``None`` when both parameters are scalars (any count)."""
        sizes = {a.size for a in (self.optical_gain, self.noise_std) if a.ndim == 1}
        return sizes.pop() if sizes else None

    def check(self, n_modes: int, basis: Any = None) -> None:
        """Check that the sensor fits a stage of ``n_modes`` modes (``basis`` unused).

        Raises
        ------
        ValueError
            Naming ``optical_gain`` or ``noise_std`` when its length is not ``n_modes``.
        """
        n_modes = check_int("n_modes", n_modes, minimum=1)
        for name in ("optical_gain", "noise_std"):
            a = getattr(self, name)
            if a.ndim == 1 and a.size != n_modes:
                raise ValueError(
                    f"the sensor has {a.size} modes ({name} of length {a.size}), the "
                    f"controller has {n_modes}: {name} must be a scalar or of length {n_modes}"
                )

    def arrays(self, n_modes: int) -> tuple[np.ndarray, np.ndarray]:
        """Optical gains and noise levels broadcast to ``n_modes``.

        Parameters
        ----------
        n_modes : int
            Modes of the stage using the sensor.

        Returns
        -------
        optical_gain, noise_std : ndarray, shape (n_modes,)
            Dimensionless gains and noise standard deviations [nm].

        Raises
        ------
        ValueError
            If the sensor has a different number of modes (naming the argument).
        """
        self.check(n_modes)
        og = np.broadcast_to(self.optical_gain, (n_modes,))
        ns = np.broadcast_to(self.noise_std, (n_modes,))
        return og, ns

    def start(self, n_modes: int, rng: np.random.Generator, pupil: Any = None) -> _LinearRun:
        """Per-run state (sensor protocol); ``pupil`` is not used.

        Parameters
        ----------
        n_modes : int
        rng : numpy.random.Generator
            Source of the measurement noise (drawn per chunk).
        pupil : Pupil, optional
            Not used.
        """
        og, ns = self.arrays(n_modes)
        return _LinearRun(og, ns, rng)

    def measure(self, residual: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Modal measurements [nm] of residual coefficients.

        Parameters
        ----------
        residual : array_like, shape (n_modes,) or (n_frames, n_modes)
            Residual modal coefficients [nm RMS].
        rng : numpy.random.Generator
            Source of the measurement noise.

        Returns
        -------
        ndarray, same shape as ``residual``
            ``optical_gain * residual + noise_std * N(0, 1)`` [nm].
        """
        x = np.asarray(residual, dtype=float)
        n = self.n_modes
        if x.ndim not in (1, 2) or (n is not None and x.shape[-1] != n):
            raise ValueError(
                f"residual must have shape (n_modes,) or (n_frames, n_modes) with "
                f"n_modes={n}, got {x.shape}"
            )
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        return self.optical_gain * x + self.noise_std * rng.standard_normal(x.shape)

    @classmethod
    def from_calibration(
        cls,
        calibration: WFSCalibration,
        photons_per_frame: float,
        read_noise: float,
        optical_gain: np.ndarray | None = None,
        *,
        compensate: bool = False,
    ) -> LinearModalSensor:
        """Linear model from a :class:`WFSCalibration` at a given flux and read noise.

        Parameters
        ----------
        calibration : WFSCalibration
        photons_per_frame : float
            Photo-electrons per frame [e-] (:meth:`WFSCalibration.noise_variance`).
        read_noise : float
            [e- RMS per pixel].
        optical_gain : ndarray (n_modes,), optional
            Optical gains (default 1 for every mode).
        compensate : bool
            Modal gain compensation in the reconstructor (as a calibrated instrument does):
            the sensor then has unit gain and noise ``sigma / g`` per mode.
        """
        var = calibration.noise_variance(photons_per_frame, read_noise)
        g = np.ones(calibration.n_modes) if optical_gain is None else np.asarray(optical_gain)
        std = np.sqrt(var)
        if compensate:
            return cls(optical_gain=np.ones_like(g), noise_std=std / g, calibration=calibration)
        return cls(optical_gain=g, noise_std=std, calibration=calibration)

    @classmethod
    def from_diffractive(
        cls,
        wfs: Any,
        basis_or_modes: Any,
        photons_per_frame: float,
        read_noise: float,
        *,
        amplitude: float = 10.0,
        residual_opd: np.ndarray | None = None,
        n_modes: int | None = None,
        max_condition: float | None = None,
        method: str = "push-pull",
        compensate: bool = False,
        calibration: WFSCalibration | None = None,
    ) -> LinearModalSensor:
        """Calibrate a diffractive WFS and return the equivalent linear modal model.

        Parameters
        ----------
        wfs : PyramidWFS or diffractive ShackHartmannWFS
        basis_or_modes : ModalBasis-like or array (n_modes, n_valid)
        photons_per_frame : float
            Photo-electrons per frame (e.g. :func:`aocontrol.sim.noise.photons_per_frame`).
        read_noise : float
            [e- RMS per pixel].
        amplitude : float
            Push-pull amplitude [nm RMS].
        residual_opd : array (n_screens, n_pix, n_pix), optional
            Residual screens for the optical gains (default: gains of 1), e.g.
            :func:`aocontrol.sim.wfs.fitting_residual_screens` or closed-loop residual maps.
        n_modes, max_condition
            Passed to :func:`reconstructor`.
        method : {"push-pull", "derivative"}
            How the interaction matrices are measured (``"derivative"``: the exact
            linearisation, half the cost).
        compensate : bool
            See :meth:`from_calibration`.
        calibration : WFSCalibration, optional
            A calibration of ``wfs`` on the basis already made (not recomputed).
        """
        cal = calibration
        if cal is None:
            cal = calibrate(
                wfs,
                basis_or_modes,
                amplitude,
                n_modes=n_modes,
                max_condition=max_condition,
                method=method,
            )
        gains = None
        if residual_opd is not None:
            gains = optical_gains(
                wfs,
                basis_or_modes,
                residual_opd,
                amplitude=amplitude,
                recon=cal.recon,
                method=method,
            )
            if not np.all(gains > 0):
                raise ValueError(
                    f"residual_opd gives optical gains <= 0 (min {gains.min()!r}): the "
                    "residual is too large for a linear model of this sensor"
                )
        return cls.from_calibration(
            cal, photons_per_frame, read_noise, optical_gain=gains, compensate=compensate
        )


class _LinearRun:
    """Run state of a :class:`LinearModalSensor`: ``og * e_prev + noise``, noise per chunk."""

    needs_phase = False

    def __init__(self, og: np.ndarray, ns: np.ndarray, rng: np.random.Generator) -> None:
        self.optical_gain = og
        self.noise_std = ns
        self.rng = rng
        self.noisy = bool(np.any(ns > 0))
        # Unit optical gains: ``1.0 * residual`` is ``residual`` exactly (one product less
        # per frame on the real-time path).
        self.unit_gain = bool(np.all(og == 1.0))
        self.noise = np.zeros((0, og.size))

    def begin_chunk(self, m_chunk: int) -> None:
        n = self.optical_gain.size
        if self.noisy:
            self.noise = self.rng.standard_normal((m_chunk, n)) * self.noise_std
        else:
            self.noise = np.zeros((m_chunk, n))

    def read(self, j: int, residual: np.ndarray, opd: Callable[[], np.ndarray]) -> np.ndarray:
        if self.unit_gain:
            return residual + self.noise[j]
        return self.optical_gain * residual + self.noise[j]


@dataclass(frozen=True)
class DiffractiveSensor:
    """A diffractive WFS in the loop: ``m = R s(residual phase map) / c`` with detector noise.

    Each frame the residual OPD map (turbulence minus the DM shapes, fitting error included)
    goes through the WFS model (pyramid or Shack-Hartmann: modulation, binning), with Poisson
    and read-out noise on the detector pixels when ``photons`` is given, then through the
    reconstructor (calibrated around a flat wavefront, as COMPASS does) and the optional
    modal gain compensation ``c``.

    Parameters
    ----------
    wfs : WavefrontSensor
        E.g. :class:`aocontrol.sim.wfs.PyramidWFS`, or any object with ``pupil``,
        ``signals(opd)`` and ``measure(opd, photons, read_noise, rng)``; signals are
        reference-subtracted.
    reconstructor : ndarray, shape (n_modes, n_signals)
        Signals to modal measurements [nm] (e.g. :func:`aocontrol.sim.wfs.reconstructor`).
    photons : float, optional
        Photo-electrons per frame in the WFS; ``None`` for a noise-free sensor.
    read_noise : float
        Read-out noise [e- RMS per pixel].
    gain_compensation : array_like (n_modes,), optional
        Modal gain compensation: the measurements are divided by it (e.g. the optical gains
        calibrated around the expected residual, :func:`aocontrol.sim.wfs.optical_gains`).
        ``None``: the raw reconstructor (the loop sees the true optical gains).

    Raises
    ------
    ValueError
        A reconstructor that is missing, not a finite matrix or does not match the WFS's
        signals; a bad compensation, flux or read noise (each named).
    """

    wfs: Any
    reconstructor: Any
    photons: float | None = None
    read_noise: float = 0.0
    gain_compensation: Any = None

    #: Former protocol flag (the run state's ``needs_phase`` replaces it).
    senses_phase: ClassVar[bool] = True

    def __post_init__(self) -> None:
        if self.reconstructor is None:
            raise ValueError(
                "reconstructor is required: a DiffractiveSensor needs a (n_modes, n_signals) "
                "reconstructor (e.g. aocontrol.sim.wfs.calibrate(wfs, basis).recon)"
            )
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
        # The product of every frame in float32: half the memory traffic of the float64
        # matrix (400 x 2496: 8 MB read per frame); relative rounding ~1e-6 of the
        # measurement, below the pyramid's own complex64 propagation.
        object.__setattr__(self, "_recon32", r.astype(np.float32))
        if self.photons is not None:
            check_positive("photons", self.photons)
        check_nonnegative("read_noise", self.read_noise)
        if self.gain_compensation is not None:
            c = check_finite_array("gain_compensation", self.gain_compensation, ndim=1)
            if c.shape != (r.shape[0],) or np.any(c <= 0):
                raise ValueError(
                    f"gain_compensation must be {r.shape[0]} values > 0 (one per reconstructed "
                    f"mode), got shape {c.shape}, min {c.min() if c.size else None!r}"
                )
            object.__setattr__(self, "gain_compensation", c)

    @property
    def n_modes(self) -> int:
        """Modes reconstructed."""
        return int(self.reconstructor.shape[0])

    @property
    def noisy(self) -> bool:
        """Whether detector noise is simulated (``photons`` given)."""
        return self.photons is not None

    def check(self, n_modes: int, basis: Any = None) -> None:
        """Check that the sensor fits a stage of ``n_modes`` modes on ``basis``.

        Raises
        ------
        ValueError
            A reconstructor for another mode count, or a WFS on another pupil than the
            basis's.
        """
        if self.n_modes != n_modes:
            raise ValueError(
                f"the sensor reconstructs {self.n_modes} modes, the controller has {n_modes}"
            )
        wfs_pupil = getattr(self.wfs, "pupil", None)
        b_pupil = getattr(basis, "pupil", None)
        if basis is not None and wfs_pupil is not None and b_pupil != wfs_pupil:
            raise ValueError(
                f"sensor.wfs.pupil must equal the stage basis's pupil, got {wfs_pupil} and "
                f"{b_pupil}"
            )

    def start(self, n_modes: int, rng: np.random.Generator, pupil: Any = None) -> _DiffractiveRun:
        """Per-run state (sensor protocol).

        With detector noise, the modal noise level (for the divergence guard only) comes from
        a few measurements of a flat wavefront drawn from a child of ``rng``: the loop's own
        noise stream is unchanged.

        Parameters
        ----------
        n_modes : int
        rng : numpy.random.Generator
            Source of the detector noise.
        pupil : Pupil, optional
            Default ``wfs.pupil``.
        """
        self.check(n_modes)
        pupil = getattr(self.wfs, "pupil", None) if pupil is None else pupil
        noise_std = np.zeros(n_modes)
        if self.noisy:
            probe_rng = rng.spawn(1)[0]
            flat = pupil.to_map(np.zeros(pupil.n_valid))
            probe = np.array([self.measure(flat, probe_rng) for _ in range(_NOISE_PROBES)])
            noise_std = probe.std(axis=0)
        return _DiffractiveRun(self, rng, noise_std)

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
        # one BLAS thread (or the WFS's workers) for the WFS and the reconstructor product:
        # on a shared machine a multi-threaded BLAS stalls on products of this size
        with blas_threads(getattr(self.wfs, "workers", 1)):
            if self.photons is None:
                sig = self.wfs.signals(residual)
            else:
                sig = self.wfs.measure(residual, self.photons, self.read_noise, rng)
            m = (self._recon32 @ sig.astype(np.float32)).astype(float)
        if self.gain_compensation is not None:
            m = m / self.gain_compensation
        return m


class _DiffractiveRun:
    """Run state of a :class:`DiffractiveSensor`: the residual map of the previous frame."""

    needs_phase = True

    def __init__(
        self, sensor: DiffractiveSensor, rng: np.random.Generator, noise_std: np.ndarray
    ) -> None:
        self.sensor = sensor
        self.rng = rng
        self.optical_gain = np.ones(sensor.n_modes)
        self.noise_std = noise_std

    def begin_chunk(self, m_chunk: int) -> None:
        pass

    def read(self, j: int, residual: np.ndarray, opd: Callable[[], np.ndarray]) -> np.ndarray:
        return self.sensor.measure(opd(), self.rng)
