"""Drifting turbulence: seeing and wind that change in time (scripted or stochastic).

A :class:`Drift` is a piecewise-linear time history of three factors relative to an
atmosphere's base conditions, given at knots ``times`` [s]:

* ``seeing`` [dimensionless]: seeing / base seeing (``r0(t) = r0 / seeing(t)``, r0 scales as
  the inverse of the seeing at a fixed wavelength);
* ``wind`` [dimensionless], per knot or per knot and layer: wind speed / base speed;
* ``direction`` [deg], per knot or per knot and layer: added to each layer's base direction.

Between knots the seeing factor is interpolated linearly; the wind is interpolated linearly
**as a velocity vector** per layer (so that the displacement of a frozen-flow screen, the time
integral of the velocity, has a closed form). Two knots at the same time make a step (the
value after the step applies from that time on). Before the first knot and after the last the
end values hold.

Physics (see :class:`aocontrol.sim.atmosphere.Atmosphere`, argument ``drift``):

* **Phase statistics at every instant.** The phase of a von Kármán screen scales as
  ``r0^(-5/6)``: the atmosphere draws its screens at the base ``r0`` and multiplies frame ``k``
  by ``seeing(k dt)^(5/6)``, so its structure function at each instant is exactly
  ``D(r; r0(t))`` (``r0^(-5/3)`` scaling), with no transient and whatever the step. (The
  outer scale and the profile's shape stay fixed; only the integrated strength drifts.)
* **Frozen flow without jumps.** Each layer's screen is displaced by ``X(t) = int_0^t v(s) ds``
  (exact for the piecewise-linear velocity), not by ``v(t) t``: a change of wind changes the
  screen's velocity, never its position, so consecutive frames stay continuous across a step.
* **Frames independent of the split into calls**: ``X(t)`` and ``seeing(t)`` are functions of
  the frame index alone.

Stochastic model (:meth:`Drift.stochastic`): the logarithm of the seeing factor is an
Ornstein-Uhlenbeck process (a stationary Gauss-Markov process, exact discretisation on knots
``knot_interval`` apart) started at 0 (the base seeing is the median), with

* correlation time ``seeing_timescale = 17 min``: Racine (1996, "Temporal fluctuations of
  atmospheric seeing", PASP 108, 372): the mean ratio of two seeing values separated by ``dt``
  grows with an e-folding time of 17 minutes (Mauna Kea free-atmosphere Cn2 profiles; the only
  published e-folding time we found; it is used for Paranal for want of a local figure);
* amplitude set by the RMS change of the seeing over one hour at Paranal,
  ``seeing_rms_change_1h = 0.16 arcsec``: Masciadri, Turchi & Fini (2023, "Optical turbulence
  forecasts at short time-scales using an autoregressive method at the Very Large Telescope",
  MNRAS 523, 3487) report a 1-2 h seeing forecast RMSE of 0.08 arcsec at the VLT, "roughly a
  factor of two" better than persistence; the RMSE of persistence at 1 h, about 0.16 arcsec, is
  the RMS change of the seeing over one hour. With the lognormal model of median ``m`` (the base
  seeing) and log-standard deviation ``sigma``, the RMS change over a lag ``h`` is
  ``m sqrt(2 e^(s2) (e^(s2) - e^(s2 rho)))``, ``s2 = sigma^2``, ``rho = exp(-h / timescale)``;
  ``sigma`` is solved from it (0.14 for a 0.8 arcsec median).

The coherence time ``tau0 = 0.314 r0 / v`` then drifts with ``r0``. A drift of the wind speed
is optional (``wind_log_sigma``, ``wind_timescale``): we found no published figure for the
timescale of the wind at Paranal, so it defaults to no wind drift rather than to a guess.
These timescales (tens of minutes) make a 60-s run almost stationary; the scripted scenarios
(:meth:`Drift.step`, :meth:`Drift.ramp`: a wind that doubles, a seeing 1.5 times worse within
a minute) are deliberately faster than the sky, to test how quickly a loop adapts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from aocontrol._validation import check_nonnegative, check_positive

__all__ = [
    "Drift",
    "SEEING_TIMESCALE",
    "SEEING_RMS_CHANGE_1H",
    "lognormal_sigma_from_rms_change",
]

#: Correlation (e-folding) time of the seeing [s]: Racine (1996), PASP 108, 372 (17 min).
SEEING_TIMESCALE = 17.0 * 60.0
#: RMS change of the seeing over one hour at Paranal [arcsec]: twice the 0.08 arcsec RMSE of the
#: autoregressive 1-h forecast, which is "roughly a factor of two" better than persistence
#: (Masciadri, Turchi & Fini 2023, MNRAS 523, 3487).
SEEING_RMS_CHANGE_1H = 0.16


def _knot_array(name: str, value: object, n_knots: int, *, minimum: float | None) -> np.ndarray:
    """``value`` as float array of shape (n_knots,) or (n_knots, n_layers), checked."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n_knots, float(arr))
    if arr.ndim not in (1, 2) or arr.shape[0] != n_knots:
        raise ValueError(
            f"{name} must have shape ({n_knots},) or ({n_knots}, n_layers) (one row per "
            f"knot), got {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()!r}")
    if minimum is not None and np.any(arr < minimum):
        raise ValueError(f"{name} must be >= {minimum:g}, got min {float(arr.min())!r}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Drift:
    """Piecewise-linear history of the seeing and wind relative to the base atmosphere.

    Parameters
    ----------
    times : array_like, shape (n_knots,)
        Knot times [s], non-decreasing, >= 0; two equal times make a step.
    seeing : array_like, shape (n_knots,)
        Seeing factor (seeing / base seeing) at each knot, > 0: ``r0(t) = r0 / seeing(t)``.
    wind : float or array_like, shape (n_knots,) or (n_knots, n_layers), default 1
        Wind-speed factor (speed / base speed) at each knot, >= 0, shared or per layer.
    direction : float or array_like, shape (n_knots,) or (n_knots, n_layers), default 0
        Offset added to each layer's wind direction [deg] at each knot.
    name : str, optional
        Label of the scenario (reports, files).

    Examples
    --------
    >>> d = Drift.ramp(10.0, 40.0, wind=2.0)        # the wind doubles between 10 s and 40 s
    >>> float(d.seeing_at(25.0)[()]), d.wind_at(25.0, 1).tolist()
    (1.0, [1.5])
    """

    times: np.ndarray
    seeing: np.ndarray
    wind: np.ndarray = 1.0  # type: ignore[assignment]
    direction: np.ndarray = 0.0  # type: ignore[assignment]
    name: str = "drift"

    def __post_init__(self) -> None:
        t = np.asarray(self.times, dtype=float)
        if t.ndim != 1 or t.size < 1:
            raise ValueError(f"times must be a 1-D array of at least one knot [s], got {t.shape}")
        if not np.all(np.isfinite(t)) or np.any(t < 0):
            raise ValueError(f"times must be finite and >= 0 [s], got {t.tolist()!r}")
        if np.any(np.diff(t) < 0):
            raise ValueError(f"times must be non-decreasing [s], got {t.tolist()!r}")
        t.setflags(write=False)
        n = t.size
        object.__setattr__(self, "times", t)
        seeing = _knot_array("seeing", self.seeing, n, minimum=None)
        if seeing.ndim != 1 or np.any(seeing <= 0):
            raise ValueError(
                f"seeing must be > 0 with shape ({n},) (one factor per knot), got "
                f"{seeing.tolist()!r}"
            )
        object.__setattr__(self, "seeing", seeing)
        object.__setattr__(self, "wind", _knot_array("wind", self.wind, n, minimum=0.0))
        object.__setattr__(
            self, "direction", _knot_array("direction", self.direction, n, minimum=None)
        )
        if not isinstance(self.name, str):
            raise TypeError(f"name must be a str, got {type(self.name).__name__}")

    # ------------------------------------------------------------------ constructors
    @classmethod
    def constant(cls) -> Drift:
        """No drift (the base atmosphere forever)."""
        return cls([0.0], [1.0], name="constant")

    @classmethod
    def step(
        cls, at: float, *, seeing: float = 1.0, wind: float = 1.0, direction: float = 0.0
    ) -> Drift:
        """Base conditions until ``at`` [s], then ``seeing``, ``wind`` factors and ``direction``
        offset [deg] (a step: the screens change speed, never position)."""
        at = check_nonnegative("at", at)
        return cls(
            [at, at],
            [1.0, seeing],
            [1.0, wind],
            [0.0, direction],
            name=f"step at {at:g} s",
        )

    @classmethod
    def ramp(
        cls,
        start: float,
        stop: float,
        *,
        seeing: float = 1.0,
        wind: float = 1.0,
        direction: float = 0.0,
    ) -> Drift:
        """Base conditions until ``start`` [s], a linear ramp to the ``seeing`` and ``wind``
        factors and ``direction`` offset [deg] at ``stop`` [s], then held."""
        start = check_nonnegative("start", start)
        stop = check_nonnegative("stop", stop)
        if stop < start:
            raise ValueError(f"stop must be >= start={start!r} [s], got {stop!r}")
        return cls(
            [start, stop],
            [1.0, seeing],
            [1.0, wind],
            [0.0, direction],
            name=f"ramp {start:g}-{stop:g} s",
        )

    @classmethod
    def stochastic(
        cls,
        duration: float,
        rng: np.random.Generator | int,
        *,
        base_seeing: float,
        knot_interval: float = 1.0,
        seeing_timescale: float = SEEING_TIMESCALE,
        seeing_rms_change_1h: float = SEEING_RMS_CHANGE_1H,
        wind_timescale: float = SEEING_TIMESCALE,
        wind_log_sigma: float = 0.0,
    ) -> Drift:
        """Stochastic drift with the site statistics of the module notes (Paranal defaults).

        Parameters
        ----------
        duration : float
            Length covered by knots [s], > 0 (the last values hold after it).
        rng : numpy.random.Generator or int
            Randomness.
        base_seeing : float
            Seeing of the base atmosphere [arcsec] (the median of the lognormal model), > 0.
        knot_interval : float, default 1.0
            Time between knots [s] (the process is exact on the knots, linear between).
        seeing_timescale : float, default 1020 s (17 min, Racine 1996)
            Correlation time of the log seeing [s].
        seeing_rms_change_1h : float, default 0.16 arcsec (Masciadri et al. 2023)
            RMS change of the seeing over one hour [arcsec], >= 0.
        wind_timescale : float, default 1020 s
            Correlation time of the log wind factor [s] (all layers share it).
        wind_log_sigma : float, default 0
            Standard deviation of the log wind factor (0: no wind drift; no published figure).
        """
        duration = check_positive("duration", duration)
        knot_interval = check_positive("knot_interval", knot_interval)
        base_seeing = check_positive("base_seeing", base_seeing)
        tau_s = check_positive("seeing_timescale", seeing_timescale)
        tau_w = check_positive("wind_timescale", wind_timescale)
        sigma_w = check_nonnegative("wind_log_sigma", wind_log_sigma)
        sigma_s = lognormal_sigma_from_rms_change(
            check_nonnegative("seeing_rms_change_1h", seeing_rms_change_1h),
            base_seeing,
            3600.0,
            tau_s,
        )
        gen = np.random.default_rng(rng)
        n = int(math.ceil(duration / knot_interval)) + 1
        times = np.arange(n) * knot_interval
        white = gen.standard_normal((2, n - 1))

        def ou(sigma: float, tau: float, w: np.ndarray) -> np.ndarray:
            rho = math.exp(-knot_interval / tau)
            x = np.zeros(n)
            for k in range(n - 1):
                x[k + 1] = rho * x[k] + sigma * math.sqrt(1.0 - rho * rho) * w[k]
            return x

        seeing = np.exp(ou(sigma_s, tau_s, white[0]))
        wind = np.exp(ou(sigma_w, tau_w, white[1]))
        return cls(times, seeing, wind, 0.0, name="stochastic (Paranal statistics)")

    # ------------------------------------------------------------------ evaluation
    def _segments(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Segment index ``i`` (knots i, i+1) and fraction in [0, 1] of each time."""
        kt = self.times
        i = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, max(kt.size - 2, 0))
        if kt.size == 1:
            return i, np.zeros_like(t)
        span = kt[i + 1] - kt[i]
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(span > 0, (t - kt[i]) / np.where(span > 0, span, 1.0), 1.0)
        # Before the first knot the first value holds (also when the first segment is a step).
        f = np.where(t < kt[0], 0.0, f)
        return i, np.clip(f, 0.0, 1.0)

    def _interp(self, values: np.ndarray, t: np.ndarray) -> np.ndarray:
        if self.times.size == 1:
            return np.broadcast_to(values[0], t.shape + values.shape[1:]).copy()
        i, f = self._segments(t)
        f = f.reshape(f.shape + (1,) * (values.ndim - 1))
        return (1.0 - f) * values[i] + f * values[i + 1]

    def seeing_at(self, t: object) -> np.ndarray:
        """Seeing factor at times ``t`` [s], shape of ``t``."""
        return self._interp(self.seeing, np.asarray(t, dtype=float))

    def phase_scale(self, t: object) -> np.ndarray:
        """Factor on the phase at times ``t`` [s]: ``seeing(t)^(5/6)`` (phase ~ r0^(-5/6))."""
        return self.seeing_at(t) ** (5.0 / 6.0)

    def _per_layer(self, arr: np.ndarray, n_layers: int, name: str) -> np.ndarray:
        if arr.ndim == 1:
            return np.repeat(arr[:, None], n_layers, axis=1)
        if arr.shape[1] != n_layers:
            raise ValueError(
                f"drift {name} has {arr.shape[1]} layer columns but the atmosphere has "
                f"{n_layers} layers"
            )
        return arr

    def wind_at(self, t: object, n_layers: int) -> np.ndarray:
        """Wind-speed factor per layer at times ``t`` [s], shape ``t.shape + (n_layers,)``
        (the norm of the interpolated velocity relative to the base speed at the knots'
        directions; equal to the knots' factors between knots of the same direction)."""
        t = np.asarray(t, dtype=float)
        w = self._per_layer(self.wind, n_layers, "wind")
        d = np.radians(self._per_layer(self.direction, n_layers, "direction"))
        vec = np.stack([w * np.cos(d), w * np.sin(d)], axis=-1)  # unit base speed, offset only
        return np.linalg.norm(self._interp(vec, t), axis=-1)

    def knot_velocities(self, speeds: np.ndarray, directions_deg: np.ndarray) -> np.ndarray:
        """Velocity (vx, vy) [m/s] of each layer at each knot, shape (n_knots, n_layers, 2)."""
        speeds = np.asarray(speeds, dtype=float)
        n_layers = speeds.size
        w = self._per_layer(self.wind, n_layers, "wind") * speeds
        d = np.radians(self._per_layer(self.direction, n_layers, "direction") + directions_deg)
        return np.stack([w * np.cos(d), w * np.sin(d)], axis=-1)

    def max_speed(self, speeds: np.ndarray, directions_deg: np.ndarray) -> float:
        """Largest layer speed over the scenario [m/s] (at a knot: the speed is piecewise
        the norm of a linear function, convex between knots)."""
        v = self.knot_velocities(speeds, directions_deg)
        return float(np.linalg.norm(v, axis=-1).max())

    def displacement(self, t: object, speeds: np.ndarray, directions_deg: np.ndarray) -> np.ndarray:
        """Screen displacement ``X(t) = int_0^t v(s) ds`` [m] per layer, shape
        ``t.shape + (n_layers, 2)`` (x, y), exact for the piecewise-linear velocity."""
        t = np.asarray(t, dtype=float)
        v = self.knot_velocities(speeds, directions_deg)  # (K, L, 2)
        kt = self.times
        # Velocity is v[0] before the first knot: X(t) = v[0] t for t <= kt[0].
        if kt.size == 1:
            return t[..., None, None] * v[0]
        # Position at each knot: X(kt[0]) = v[0] kt[0], then trapezoids.
        seg = 0.5 * (v[1:] + v[:-1]) * np.diff(kt)[:, None, None]
        at_knots = np.concatenate([(v[0] * kt[0])[None], v[0] * kt[0] + np.cumsum(seg, axis=0)])
        i, f = self._segments(t)
        span = (kt[i + 1] - kt[i])[..., None, None]
        ff = f[..., None, None]
        before = t < kt[0]
        after = t >= kt[-1]
        # Inside segment i: X = X_i + span (f v_i + f^2 (v_{i+1} - v_i) / 2).
        inside = at_knots[i] + span * (ff * v[i] + 0.5 * ff * ff * (v[i + 1] - v[i]))
        out = np.where(before[..., None, None], t[..., None, None] * v[0], inside)
        tail = at_knots[-1] + (t - kt[-1])[..., None, None] * v[-1]
        return np.where(after[..., None, None], tail, out)

    def describe(self) -> str:
        """One line: the name and the factors at the last knot."""
        return (
            f"{self.name}: seeing x{float(self.seeing[-1]):.3g}, wind "
            f"x{float(np.max(self.wind[-1])):.3g} at {float(self.times[-1]):g} s"
        )


def lognormal_sigma_from_rms_change(
    rms_change: float, median: float, lag: float, timescale: float
) -> float:
    """Log-standard deviation of a stationary lognormal OU process from its RMS change.

    ``E[(s(t + lag) - s(t))^2] = 2 m^2 e^(s2) (e^(s2) - e^(s2 rho))`` with ``m`` the median,
    ``s2 = sigma^2`` and ``rho = exp(-lag / timescale)``: solved for ``sigma`` (Brent).

    Parameters
    ----------
    rms_change : float
        RMS change over ``lag`` (unit of ``median``), >= 0.
    median : float
        Median of the process, > 0.
    lag, timescale : float
        Lag and correlation time [s], > 0.

    Examples
    --------
    >>> round(lognormal_sigma_from_rms_change(0.16, 0.8, 3600.0, 1020.0), 3)
    0.141
    """
    rms_change = check_nonnegative("rms_change", rms_change)
    median = check_positive("median", median)
    rho = math.exp(-check_positive("lag", lag) / check_positive("timescale", timescale))
    target = (rms_change / median) ** 2
    if target == 0.0:
        return 0.0

    def excess(sigma: float) -> float:
        s2 = sigma * sigma
        return 2.0 * math.exp(s2) * (math.exp(s2) - math.exp(s2 * rho)) - target

    hi = 1.0
    while excess(hi) < 0.0:
        hi *= 2.0
        if hi > 64:
            raise ValueError(f"rms_change={rms_change!r} is too large for a lognormal model")
    return float(scipy.optimize.brentq(excess, 0.0, hi, xtol=1e-12))
