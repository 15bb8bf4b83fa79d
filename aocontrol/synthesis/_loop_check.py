"""Is this telemetry the loop it claims to be? The command sign and scale, from the data alone.

A file whose commands enter with the other sign, or in another unit than its measurements, is
read without complaint and gives a wrong pseudo-open loop ``pol = m + G u``, hence a wrong
predicted residual and wrong designs. This module tells it from the telemetry itself, before
a design is made.

Sign. With the loop conventions of :mod:`aocontrol.synthesis._telemetry` (``u = K m``, the
residual ``d - G u``), the measurement is ``m = S pol`` with ``S = 1 / (1 + L)``, ``L = G K``,
and ``pol = z^-1 d + n``. Read with the other sign, the pseudo-open loop is

    pol' = m - G u = (1 - L) / (1 + L) pol.

The one-step prediction error (innovation) variance of a process filtered by a monic filter
``H`` is multiplied by ``exp(int log |H|^2) = prod |z_i|^2`` over the zeros ``z_i`` of ``H``
outside the unit circle (Jensen's formula; Kolmogorov-Szego). ``(1 - L) / (1 + L)`` is monic
(``L`` has a delay), its poles are the stable closed loop's, and its zeros are the poles of the
loop closed with positive feedback, unstable for any controller with integral action (``L``
is large and positive at low frequency). So the wrong sign's pseudo-open loop is strictly
less predictable, by the factor ``prod |z_i|^2`` whatever the disturbance and the noise:
``1 / 1.274^2 = 0.616`` for an integrator of gain 0.3 with 0.4 frame of latency, 0.52 at
gain 0.5, 0.91 at gain 0.05 and 1.5 frames.
The statistic is the ratio of the innovation variances of ``m + G u`` and ``m - G u``
(least-squares AR fits, one per mode, the median over the modes checked): below 1 the sign is
the loop's, above 1 it is the other one; near 1 (a loop without integral action, open-loop
telemetry) the data cannot tell.

Scale. ``G u`` and ``m`` are the same physical quantity in a closed loop (the correction and
the residual), within a few decades of each other. Commands in metres against measurements in
nanometres (a unit the files do not state, or a matrix that does not convert) put the ratio of
their RMS near ``1e-9`` or ``1e9``; the check refuses a ratio beyond ``1e6`` either way (it
does not see a factor of 1e3, e.g. micrometres for nanometres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import control
import numpy as np

from aocontrol._blas import blas_threads
from aocontrol._validation import check_finite_array
from aocontrol.synthesis._telemetry import pseudo_open_loop

__all__ = [
    "MIN_CHECK_FRAMES",
    "SIGN_TOLERANCE",
    "SCALE_LIMIT",
    "LoopTelemetryCheck",
    "TelemetryCheckError",
    "check_loop_telemetry",
]

#: The sign statistic is decided beyond this relative distance from 1 (either way). Measured
#: scatter of the per-mode ratio: +-0.01 on 256 frames, +-0.002 on 2048 (integrators and
#: data-driven designs in simulated loops); the smallest effect measured, 9 % (gain 0.05, 1.5
#: frames), is 4.5 times it.
SIGN_TOLERANCE = 0.02
#: ``rms(G u) / rms(m)`` (median over the modes) beyond ``SCALE_LIMIT`` or below its inverse:
#: measurements and commands are not in the same unit.
SCALE_LIMIT = 1e6
# AR order of the innovation fits, most modes checked (evenly spaced, the first included), and
# the frames dropped at the start (the pseudo-open loop's transient from unknown earlier
# commands).
_AR_ORDER = 16
_MAX_MODES = 64
_SKIP = 8
#: Fewest frames :func:`check_loop_telemetry` accepts (four per AR coefficient, plus the
#: transient dropped).
MIN_CHECK_FRAMES = 4 * _AR_ORDER + _SKIP


class TelemetryCheckError(ValueError):
    """Telemetry that is not the loop it claims to be (:func:`check_loop_telemetry`).

    Raised by :func:`aocontrol.synthesis.design_from_telemetry` before any design; the
    message names the statistic, its value and the option that fixes it.

    Parameters
    ----------
    message : str
        What is implausible and the option that fixes it.
    check : LoopTelemetryCheck
        The statistics (kept as ``.check``).
    """

    def __init__(self, message: str, check: LoopTelemetryCheck) -> None:
        super().__init__(message)
        self.check = check

    def __reduce__(self):  # picklable despite the custom signature
        return (type(self), (self.args[0], self.check))


@dataclass(frozen=True, eq=False)
class LoopTelemetryCheck:
    """The command sign and scale of closed-loop telemetry (:func:`check_loop_telemetry`).

    Attributes
    ----------
    modes : ndarray of int, shape (n_checked,)
        Modes checked.
    sign_ratios : ndarray, shape (n_checked,)
        Per mode, innovation variance of ``m + G u`` over that of ``m - G u``: ``< 1`` for
        the loop's own sign (module docstring), ``nan`` for a mode without commands.
    sign_statistic : float
        Median of :attr:`sign_ratios` (``nan`` if no mode has commands).
    scale : float
        Median over the modes with commands of ``rms(G u) / rms(m)`` (``nan`` if none).
    """

    modes: np.ndarray
    sign_ratios: np.ndarray
    sign_statistic: float
    scale: float

    @property
    def sign(self) -> str:
        """``"plausible"`` (statistic below ``1 - SIGN_TOLERANCE``), ``"implausible"`` (above
        ``1 + SIGN_TOLERANCE``: the commands enter with the other sign) or ``"undecided"``."""
        s = self.sign_statistic
        if not math.isfinite(s):
            return "undecided"
        if s > 1 + SIGN_TOLERANCE:
            return "implausible"
        return "plausible" if s < 1 - SIGN_TOLERANCE else "undecided"

    @property
    def scale_plausible(self) -> bool:
        """``rms(G u) / rms(m)`` within ``[1 / SCALE_LIMIT, SCALE_LIMIT]`` (or no commands)."""
        return not math.isfinite(self.scale) or 1 / SCALE_LIMIT <= self.scale <= SCALE_LIMIT

    @property
    def ok(self) -> bool:
        """Neither the sign nor the scale is implausible."""
        return self.sign != "implausible" and self.scale_plausible

    def problems(self, sign_option: str = "command_sign=-1") -> list[str]:
        """What is implausible, each with the option that fixes it (``sign_option``)."""
        out = []
        if self.sign == "implausible":
            out.append(
                f"the commands enter with the other sign: the pseudo-open loop m + G u is "
                f"{self.sign_statistic:.3g}x less predictable than m - G u (innovation "
                f"variance, median over {self.modes.size} modes; the loop's own sign gives "
                f"< {1 - SIGN_TOLERANCE:g}); read the telemetry with {sign_option}"
            )
        if not self.scale_plausible:
            out.append(
                f"measurements and commands are not in the same unit: rms(G u) / rms(m) = "
                f"{self.scale:.3g} (median over the modes; a closed loop gives 1e-6..1e6); "
                "check the units of the file (AOT commands are in metres on the actuators) "
                "and the matrices mapping them to modes"
            )
        return out


def _innovation_variance(x: np.ndarray, order: int) -> np.ndarray:
    """One-step prediction error variance of each column by a least-squares AR(order) fit.

    On one BLAS thread: each fit is a few columns tall and thin, where OpenBLAS's threads
    only add synchronisation (0.39 s instead of 3.0 s for the 2 x 64 fits of a
    15,300-frame file on a loaded 2-core machine, the same statistic).
    """
    x = x - x.mean(axis=0)
    n, m = x.shape
    out = np.empty(m)
    with blas_threads(1):
        for i in range(m):
            col = x[:, i]
            lags = np.lib.stride_tricks.sliding_window_view(col[:-1], order)[:, ::-1]
            y = col[order:]
            coef, *_ = np.linalg.lstsq(lags, y, rcond=None)
            out[i] = np.mean((y - lags @ coef) ** 2)
    return out


def check_loop_telemetry(
    measurements: object,
    commands: object,
    plant: control.TransferFunction,
    *,
    fs: float | None = None,
) -> LoopTelemetryCheck:
    """Check the command sign and scale of closed-loop telemetry from the data alone.

    Module docstring for the statistics: the sign from the innovation variances of ``m + G u``
    and ``m - G u`` (exact factor: the unstable poles of the loop closed with the other sign),
    the scale from ``rms(G u) / rms(m)``.

    Parameters
    ----------
    measurements, commands : array_like, shape (n_frames, n_modes)
        Closed-loop modal telemetry ``m`` and ``u = K m`` [units].
    plant : control.TransferFunction
        Loop plant (command to measurement), e.g. :func:`aocontrol.loop_plant`.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.

    Returns
    -------
    LoopTelemetryCheck
        ``.sign`` (``"plausible"``, ``"implausible"``, ``"undecided"``),
        ``.scale_plausible``, ``.problems()``.

    Raises
    ------
    ValueError
        Telemetry of different shapes or too short (fewer than ``MIN_CHECK_FRAMES`` = 72).

    Examples
    --------
    >>> from aocontrol import loop_plant
    >>> from aocontrol.controllers import Integrator
    >>> rng = np.random.default_rng(0)
    >>> d = np.cumsum(rng.standard_normal((4000, 1)), axis=0)  # a random walk to correct
    >>> K, m, u, e = Integrator(0.3, fs=1000.0), [], [], np.zeros(1)
    >>> prev = np.zeros(1)
    >>> for k in range(4000):  # G = z^-1 (WFS) and no latency: e[k] = d[k] - u[k-1]
    ...     m.append(e + 0.1 * rng.standard_normal(1))
    ...     u.append(K.step(m[-1]))
    ...     e = d[k] - u[-1]
    >>> G = loop_plant(1000.0, 0.0)
    >>> check_loop_telemetry(np.array(m), np.array(u), G).sign
    'plausible'
    >>> check_loop_telemetry(np.array(m), -np.array(u), G).sign
    'implausible'
    """
    m = check_finite_array("measurements", measurements, ndim=(1, 2))
    u = check_finite_array("commands", commands, ndim=(1, 2))
    m, u = (x[:, None] if x.ndim == 1 else x for x in (m, u))
    if m.shape != u.shape:
        raise ValueError(
            f"measurements and commands must have the same shape (n_frames, n_modes), got "
            f"{m.shape} and {u.shape}"
        )
    need = MIN_CHECK_FRAMES
    if m.shape[0] < need:
        raise ValueError(
            f"telemetry must have at least {need} frames to check the command sign, got "
            f"{m.shape[0]}"
        )
    n_modes = m.shape[1]
    modes = np.unique(np.linspace(0, n_modes - 1, min(n_modes, _MAX_MODES)).round().astype(int))
    gu = pseudo_open_loop(np.zeros_like(u[:, modes]), u[:, modes], plant, fs=fs)[_SKIP:]
    mm = m[_SKIP:, modes]
    active = np.std(gu, axis=0) > 0
    ratios = np.full(modes.size, np.nan)
    if active.any():
        plus = _innovation_variance(mm[:, active] + gu[:, active], _AR_ORDER)
        minus = _innovation_variance(mm[:, active] - gu[:, active], _AR_ORDER)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratios[active] = plus / minus
    with np.errstate(divide="ignore", invalid="ignore"):
        scales = np.std(gu, axis=0) / np.std(mm, axis=0)
    finite = np.isfinite(ratios)
    statistic = float(np.median(ratios[finite])) if finite.any() else math.nan
    scale = float(np.median(scales[active])) if active.any() else math.nan
    return LoopTelemetryCheck(modes, ratios, statistic, scale)
