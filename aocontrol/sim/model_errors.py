"""Model errors: what the instrument does that the controller's model does not.

A controller is designed on a model of the loop (:func:`aocontrol.loop_plant`: a WFS frame, a
latency, a DM of unit gain and instant response, optical gains compensated). The simulator
can run a loop that differs from it, each difference a setting of the run, never a code
fork; with every setting at its neutral value the run is the nominal one bit for bit:

* a true latency other than the design's: the :class:`~aocontrol.sim.Stage`'s
  ``latency_frames`` is the truth, the design keeps its own plant;
* the DM's temporal response (:class:`DMResponse`: a first-order lag and optionally a lightly
  damped mechanical resonance), applied to the DM shape of every mode;
* misregistration of the DM against the WFS after calibration (:func:`misregistration_matrix`:
  the DM's modes shifted and rotated over the pupil, as seen in the stage's basis);
* optical gains other than the calibrated ones, and drifting (:class:`OpticalGainError`).

The pseudo-open loop rebuilt with the wrong plant follows: telemetry of the true loop,
reconstructed by the design with the nominal one.

Conventions: times in seconds, frequencies in Hz, shifts in fractions of a WFS
subaperture, rotations in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import control
import numpy as np

from aocontrol._validation import check_finite_array, check_nonnegative, check_positive
from aocontrol.plant import tf_from_z_inverse

__all__ = ["DMResponse", "OpticalGainError", "misregistration_matrix"]


@dataclass(frozen=True)
class DMResponse:
    """Temporal response of a DM, the same for every mode: unit gain at 0 Hz.

    In discrete time at the loop rate ``fs``, the DM shape the WFS sees in a frame is the
    commanded shape (the delay line of :func:`aocontrol.loop_plant`) through

        H(z) = (1 - a) / (1 - a z^-1) * (1 + c1 + c2) / (1 + c1 z^-1 + c2 z^-2),

    ``a = exp(-1 / (fs tau))`` the first-order lag of time constant ``tau``, and ``c1, c2``
    the lightly damped resonance (poles ``exp((-zeta w +- j w sqrt(1 - zeta^2)) / fs)``,
    ``w = 2 pi f_r``; matched poles, no zero). The loop's true plant is ``G H``. A sampled
    model: the lag over the frame's integration is not averaged (for ``tau`` below a frame
    the difference is a fraction of the lag itself).

    Parameters
    ----------
    time_constant : float, default 0
        First-order time constant ``tau`` [s], >= 0 (0: no lag).
    resonance_hz : float, optional
        Mechanical resonance [Hz], > 0 and below ``fs/2`` at the loop rate (``None``: none).
    damping : float, default 0.1
        Damping ratio ``zeta`` of the resonance, in (0, 1).

    Examples
    --------
    >>> h = DMResponse(time_constant=1e-4)      # 0.1 ms lag at 3 kHz
    >>> b, a = h.coefficients(3000.0)
    >>> round(float(b.sum() / a.sum()), 12)      # unit gain at 0 Hz
    1.0
    """

    time_constant: float = 0.0
    resonance_hz: float | None = None
    damping: float = 0.1

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "time_constant", check_nonnegative("time_constant", self.time_constant)
        )
        if self.resonance_hz is not None:
            object.__setattr__(
                self, "resonance_hz", check_positive("resonance_hz", self.resonance_hz)
            )
        zeta = float(self.damping)
        if not (0.0 < zeta < 1.0):
            raise ValueError(f"damping must be in (0, 1), got {self.damping!r}")
        object.__setattr__(self, "damping", zeta)

    @property
    def is_identity(self) -> bool:
        """No lag and no resonance: the DM follows its command exactly."""
        return self.time_constant == 0.0 and self.resonance_hz is None

    def coefficients(self, fs: float) -> tuple[np.ndarray, np.ndarray]:
        """``(b, a)`` of ``H(z)`` in powers of ``z^-1`` at the loop rate ``fs`` [Hz]."""
        fs = check_positive("fs", fs)
        b, a = np.array([1.0]), np.array([1.0])
        if self.time_constant > 0:
            p = math.exp(-1.0 / (fs * self.time_constant))
            b, a = np.array([1.0 - p]), np.array([1.0, -p])
        if self.resonance_hz is not None:
            if self.resonance_hz >= fs / 2:
                raise ValueError(
                    f"resonance_hz must be below fs/2 = {fs / 2:g} Hz, got {self.resonance_hz!r}"
                )
            w = 2 * math.pi * self.resonance_hz / fs
            z = self.damping
            pole = np.exp(complex(-z * w, w * math.sqrt(1 - z * z)))
            c = np.array([1.0, -2.0 * pole.real, abs(pole) ** 2])
            b, a = np.convolve(b, [c.sum()]), np.convolve(a, c)
        return b, a

    def transfer_function(self, fs: float) -> control.TransferFunction:
        """``H(z)`` as a transfer function (``dt = 1/fs``)."""
        b, a = self.coefficients(fs)
        return tf_from_z_inverse(b, a, 1.0 / fs)


@dataclass(frozen=True)
class OpticalGainError:
    """Optical gains of the sensor other than those the loop compensates, possibly drifting.

    The loop compensates the calibrated optical gains; the sensor's true ones are ``factor``
    times those, modulated in time: ``g(t) = factor (1 + drift (sin(2 pi t / period +
    phase)))`` per mode (a pyramid's gains follow its residual: a seeing that changes over
    minutes moves them). For the linear modal sensor the factor multiplies the signal (the
    residual it reads) and not its noise, as a true optical-gain change does; for the
    diffractive sensor, whose optical gains are its physics, it multiplies the measurement
    (a compensation error: the noise is scaled too).

    Parameters
    ----------
    factor : float or array_like (n_modes,), default 1
        True / compensated optical gain, > 0 (0.7: 30 % lower than calibrated).
    drift : float, default 0
        Relative amplitude of the modulation, in [0, 1).
    period : float, default 60
        Period of the modulation [s], > 0.
    phase : float or array_like (n_modes,), default 0
        Phase of each mode's modulation [rad].
    """

    factor: float | np.ndarray = 1.0
    drift: float = 0.0
    period: float = 60.0
    phase: float | np.ndarray = 0.0

    def __post_init__(self) -> None:
        f = check_finite_array("factor", self.factor, ndim=(0, 1))
        if np.any(f <= 0):
            raise ValueError(f"factor must be > 0 for every mode, got min {float(f.min())!r}")
        object.__setattr__(self, "factor", f)
        d = float(self.drift)
        if not (0.0 <= d < 1.0):
            raise ValueError(f"drift must be in [0, 1), got {self.drift!r}")
        object.__setattr__(self, "drift", d)
        object.__setattr__(self, "period", check_positive("period", self.period))
        object.__setattr__(self, "phase", check_finite_array("phase", self.phase, ndim=(0, 1)))

    @property
    def is_identity(self) -> bool:
        """Unit factor and no drift: the compensated gains are the true ones."""
        return bool(np.all(self.factor == 1.0)) and self.drift == 0.0

    def gains(self, t: float, n_modes: int) -> np.ndarray:
        """True / compensated optical gain of every mode at time ``t`` [s], shape (n_modes,)."""
        g = np.broadcast_to(self.factor, (n_modes,)).astype(float)
        if self.drift:
            g = g * (1.0 + self.drift * np.sin(2 * np.pi * t / self.period + self.phase))
        return g


def misregistration_matrix(
    dm: object,
    basis: object,
    *,
    shift_x: float = 0.0,
    shift_y: float = 0.0,
    rotation: float = 0.0,
    subaperture: float,
) -> np.ndarray:
    """The DM's modes as they land on the pupil after a misregistration, in the stage's basis.

    The DM's actuators move against the pupil (and the WFS, conjugated to it) after the
    calibration: their centres are rotated by ``rotation`` degrees about the pupil's centre
    and shifted by ``(shift_x, shift_y)`` subapertures; the influence functions move with
    them (exact for the mirror's model, :class:`~aocontrol.sim.dm.DeformableMirror`). Each
    mode's commands (``basis.m2c``) then make a moved shape, projected on the basis over the
    pupil (orthonormal there: a unit coefficient is 1 nm RMS). Column ``i`` is what command
    ``i`` of the stage makes; the part of the moved shape outside the basis is dropped (the
    modal simulator's approximation: ``1 - ||M[:, i]||^2`` of a unit mode's variance). With
    no shift and no rotation it is the identity.

    Parameters
    ----------
    dm : DeformableMirror
        The stage's mirror (actuator positions, pitch, coupling).
    basis : ModalBasis
        The stage's modes (``modes`` (n_modes, n_valid), ``m2c`` (n_act, n_modes)).
    shift_x, shift_y : float
        Shift [subapertures].
    rotation : float
        Rotation [deg].
    subaperture : float
        Size of a WFS subaperture [m] (the pupil's diameter / subapertures across).

    Returns
    -------
    ndarray, shape (n_modes, n_modes)
    """
    subaperture = check_positive("subaperture", subaperture)
    modes = np.asarray(basis.modes, dtype=float)
    n = modes.shape[0]
    if shift_x == 0.0 and shift_y == 0.0 and rotation == 0.0:
        return np.eye(n)
    pupil = dm.pupil
    xp = pupil.to_vector(pupil.x)
    yp = pupil.to_vector(pupil.y)
    c, s_ = math.cos(math.radians(rotation)), math.sin(math.radians(rotation))
    pos = np.asarray(dm.positions, dtype=float)
    x = c * pos[:, 0] - s_ * pos[:, 1] + shift_x * subaperture
    y = s_ * pos[:, 0] + c * pos[:, 1] + shift_y * subaperture
    d2 = (x[:, None] - xp[None, :]) ** 2 + (y[:, None] - yp[None, :]) ** 2
    influence = np.exp(math.log(dm.coupling) / dm.pitch**2 * d2)
    moved = np.asarray(basis.m2c, dtype=float).T @ influence  # (n_modes, n_valid)
    # Orthonormal over the pupil: the coefficient of mode j is mean(mode_j * shape).
    return (modes @ moved.T) / modes.shape[1]
