"""Online optical-gain tracking by a modal dither (instrumental-variable estimate).

Method
------
A small pseudo-random dither ``w`` (independent +-a per mode and frame, from its own random
stream) is added to the stage's DM shape, as the modal-dither optical-gain measurements of the
pyramid do (Esposito et al. 2012 at the LBT, the "dithering" method discussed by Deo et al.
2019 and Chambouleyron et al. 2020). The dither is an offset of the mirror synchronous with
the WFS frames (like the dCAO offset; a pre-computed sequence is sent ahead of the loop's
latency), so ``w[k]`` is in the DM shape of frame ``k`` with weight 1 whatever the latency.
With one frame of WFS integration, the sensor output of frame ``k`` is, to first order around
the current residual,

    m[k] = g (d[k-1] - y_c[k-1] - w[k-1]) + n[k]

with ``y_c`` the controller's part of the DM shape, ``d`` the disturbance and ``n`` the noise.
``w[k-1]`` is an instrument: ``d`` and ``n`` are independent of it, and ``y_c[k-1]`` reacts to
measurements up to frame ``k-1-k0`` (``k0`` the whole frames of the latency), hence to dithers
up to frame ``k-2-k0`` only (causality). Correlating both sides with it,

    g = - sum_k m[k] w[k-1] / sum_k w[k-1]^2,

an unbiased estimate whatever the controller does, with no model of the closed loop and no
assumption on the disturbance spectrum; its statistical error is ``~ sigma_m / (a sqrt(N))``
after ``N`` frames (``sigma_m`` the measurement's RMS, ``a`` the dither's). Modes are
dithered independently, so the estimate of a mode is not biased by the others'. For a
diffractive sensor the estimate is the local slope of the sensor averaged over the loop's own
residual, i.e. ``diag(R D_res)`` of :func:`aocontrol.sim.wfs.optical_gains`. The dither is in
the ``dm`` telemetry, not in the ``commands``: a pseudo-open loop from the telemetry sees it as
a white disturbance of variance ``a^2`` on the dithered modes.

Why the dither and not CLOSE (Deo et al. 2021): CLOSE adapts the modal gain so that the
autocorrelation of the closed-loop measurements meets a set point; its fixed point depends on
the disturbance and on the controller (designed for an integrator), so it does not estimate the
optical gain itself, and it would fight the optimised modal gains, the data-driven and the LQG
controllers, which set their loop gains themselves. The dither measures ``g`` and leaves the
controller's design alone; its cost is the dither's own residual (``a^2`` per mode, small for
``a`` a fraction of the residual) and a convergence time ``~ (sigma_m / (a g))^2`` frames for a
relative accuracy of 1.

Dithering every mode costs ``n_modes a^2`` of residual variance; ``modes`` dithers a subset
(e.g. a few dozen modes spaced logarithmically in order, where the gains vary fastest at low
orders) and the gains of the other modes are interpolated linearly in mode index (constant
beyond the ends), as the optical gains vary smoothly with the spatial frequency.

The estimate is refreshed every ``update_every`` frames from sums with exponential forgetting
(``memory`` windows) and divides the sensor's output before the controller (modal gain
compensation). A mode's estimate is used only once its relative standard error, estimated from
the same sums (``sqrt(sum (m w)^2) / |sum m w|``, the frames taken as independent), is below
``precision``: an imprecise estimate would over-compensate as often as under-compensate, and an
over-compensated loop can go unstable (faint stars: ``sigma_m`` large, see the error above);
the count of such modes is in the result's metadata (``gain_tracker_imprecise_modes``). A
precise estimate that is not finite or outside ``bounds`` (a diverging tracker) is not used
either: the previous value is kept, the modes are logged and counted in the result's
metadata (``gain_tracker_rejected``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from aocontrol._validation import check_finite_array, check_int, check_positive

__all__ = ["DitherGainTracker"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DitherGainTracker:
    """Online optical-gain estimate of a stage's sensor by a modal dither (module docstring).

    Parameters
    ----------
    amplitude : float or array_like (n_modes,)
        Dither amplitude per mode [nm] (each frame +-amplitude), > 0.
    update_every : int
        Frames of the stage's rate between two updates of the compensation (>= 10).
    memory : float
        Forgetting horizon in updates (>= 1): the sums decay by ``1 - 1/memory`` per update.
        A large value averages a stationary run; a small one follows a drift.
    bounds : tuple of float
        Accepted range ``(low, high)`` of an estimate; outside it the estimate is rejected.
    modes : array_like of int, optional
        Modes dithered (increasing indices); default every mode. The others' gains are
        interpolated.
    initial : float or array_like (n_modes,)
        Gains assumed before the first estimate (e.g. calibrated ones), in ``bounds``.
    precision : float
        Relative standard error below which a mode's estimate is used, in (0, 1).

    Raises
    ------
    ValueError
        Naming the argument with the bad value.
    """

    amplitude: Any = 1.0
    update_every: int = 500
    memory: float = 4.0
    bounds: tuple = (0.05, 3.0)
    modes: Any = None
    initial: Any = 1.0
    precision: float = 0.1

    def __post_init__(self) -> None:
        a = check_finite_array("amplitude", self.amplitude, ndim=(0, 1))
        if a.size == 0 or np.any(a <= 0):
            raise ValueError(f"amplitude must be > 0 [nm] for every mode, got {self.amplitude!r}")
        object.__setattr__(self, "amplitude", a)
        check_int("update_every", self.update_every, minimum=10)
        if not float(self.memory) >= 1.0:
            raise ValueError(f"memory must be >= 1 (updates), got {self.memory!r}")
        lo, hi = (float(b) for b in self.bounds)
        check_positive("bounds[0]", lo)
        if not hi > lo:
            raise ValueError(f"bounds must be (low, high) with 0 < low < high, got {self.bounds!r}")
        if not 0.0 < float(self.precision) < 1.0:
            raise ValueError(f"precision must be in (0, 1), got {self.precision!r}")
        g0 = check_finite_array("initial", self.initial, ndim=(0, 1))
        if g0.size == 0 or np.any(g0 < lo) or np.any(g0 > hi):
            raise ValueError(f"initial must be within bounds {self.bounds!r}, got {self.initial!r}")
        object.__setattr__(self, "initial", g0)
        if self.modes is not None:
            idx = np.asarray(self.modes)
            if (
                idx.ndim != 1
                or idx.size == 0
                or not np.issubdtype(idx.dtype, np.integer)
                or np.any(idx < 0)
                or np.any(np.diff(idx) <= 0)
            ):
                raise ValueError(f"modes must be increasing mode indices >= 0, got {self.modes!r}")
            object.__setattr__(self, "modes", idx)

    def start(self, n_modes: int, rng: np.random.Generator) -> _TrackerRun:
        """Per-run state for a stage of ``n_modes`` modes; ``rng`` draws the dither."""
        for name in ("amplitude", "initial"):
            a = getattr(self, name)
            if a.ndim == 1 and a.size != n_modes:
                raise ValueError(
                    f"{name} has {a.size} values, the stage has {n_modes} modes: give a "
                    f"scalar or {n_modes} values"
                )
        probed = np.arange(n_modes) if self.modes is None else self.modes
        if probed[-1] >= n_modes:
            raise ValueError(f"modes must be < n_modes={n_modes}, got {probed[-1]}")
        amp = np.zeros(n_modes)
        amp[probed] = np.broadcast_to(self.amplitude, (n_modes,))[probed]
        gain = np.broadcast_to(self.initial, (n_modes,)).astype(float)
        return _TrackerRun(self, amp, probed, gain, rng)


class _TrackerRun:
    """Mutable state of a :class:`DitherGainTracker` during one run."""

    def __init__(
        self,
        cfg: DitherGainTracker,
        amp: np.ndarray,
        probed: np.ndarray,
        gain: np.ndarray,
        rng: np.random.Generator,
    ) -> None:
        n = amp.size
        self.cfg = cfg
        self.amp = amp
        self.probed = probed
        self.rng = rng
        self.w_prev: np.ndarray | None = None  # the dither of the previous frame
        self.gain = gain
        self.num = np.zeros(n)
        self.den = np.zeros(n)
        self.sq = np.zeros(n)
        self.num_tot = np.zeros(n)
        self.den_tot = np.zeros(n)
        self.sq_tot = np.zeros(n)
        self.frames = 0
        self.history: list[np.ndarray] = []
        self.rejected = np.zeros(n, dtype=int)
        self.imprecise = 0  # probed modes whose last estimate was not precise enough
        self.w = np.zeros((0, n))

    def begin_chunk(self, m_chunk: int) -> None:
        signs = self.rng.integers(0, 2, size=(m_chunk, self.amp.size)) * 2.0 - 1.0
        self.w = signs * self.amp

    def observe(self, m_raw: np.ndarray) -> None:
        """Accumulate a frame's raw measurement against its instrument, the previous dither."""
        z = self.w_prev
        if z is not None:
            mz = m_raw * z
            self.num -= mz
            self.den += z * z
            self.sq += mz * mz
        self.frames += 1
        if self.frames % self.cfg.update_every == 0:
            self._update()

    def dither(self, j: int) -> np.ndarray:
        """The dither of row ``j`` of the chunk (this frame), remembered for the estimate."""
        w = self.w_prev = self.w[j]
        return w

    def _update(self) -> None:
        rho = 1.0 - 1.0 / float(self.cfg.memory)
        self.num_tot = rho * self.num_tot + self.num
        self.den_tot = rho * self.den_tot + self.den
        self.sq_tot = rho * rho * self.sq_tot + self.sq  # variance weights: rho^2
        self.num[:] = 0.0
        self.den[:] = 0.0
        self.sq[:] = 0.0
        lo, hi = self.cfg.bounds
        p = self.probed
        num, den = self.num_tot[p], self.den_tot[p]
        with np.errstate(divide="ignore", invalid="ignore"):
            est = num / den
            rel_se = np.sqrt(self.sq_tot[p]) / np.abs(num)
        precise = rel_se < self.cfg.precision  # not yet precise: keep the previous value
        ok = ~precise | (np.isfinite(est) & (den > 0) & (est >= lo) & (est <= hi))
        if not ok.all():
            bad = p[~ok]
            self.rejected[bad] += 1
            logger.warning(
                "optical-gain tracker: estimate rejected (not finite or outside %s) for modes "
                "%s: the previous compensation is kept",
                self.cfg.bounds,
                bad[:10].tolist(),
            )
        self.imprecise = int(np.count_nonzero(~precise))
        probed_gain = np.where(ok & precise, est, self.gain[p])
        if p.size == self.gain.size:
            self.gain = probed_gain
        else:  # the other modes: linear in mode index between the probed ones
            self.gain = np.interp(np.arange(self.gain.size), p, probed_gain)
        self.history.append(self.gain.copy())

    def metadata(self) -> dict:
        """JSON-serialisable summary for the result's metadata."""
        return {
            "gain_tracker": "dither",
            "gain_tracker_estimate": self.gain.tolist(),
            "gain_tracker_updates": len(self.history),
            "gain_tracker_rejected": self.rejected.tolist(),
            "gain_tracker_imprecise_modes": self.imprecise,
            "gain_tracker_history": [h.tolist() for h in self.history],
        }
