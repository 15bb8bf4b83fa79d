"""Modal time-domain AO loop with the control layer's timing.

Timing (the plant of :func:`aocontrol.loop_plant`, so that the simulator's rejection equals
``|S|^2`` of :mod:`aocontrol.analysis`): at frame ``k``

1. the WFS delivers ``m[k] = og * e[k-1] + n[k]`` (integration of the previous frame);
2. the controller computes ``u[k] = K(m)[k]`` (its own stroke clipping included);
3. the DM applies ``y[k] = (1 - f) u[k - k0] + f u[k - k0 - 1]`` with
   ``k0 = floor(latency_frames)``, ``f`` its fractional part (linear interpolation of the
   commands, as COMPASS), clipped to the DM stroke;
4. the residual is ``e[k] = d[k] - y[k]``.

Everything is modal (nm RMS per mode, shape ``(n_modes,)``) and vectorised over modes; the
only Python loop is over frames. Phase maps (nm OPD) are formed only for the frames that feed
the science camera: ``residual_map = phase[k] - DM shape``, which keeps the fitting error.
"""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from aocontrol._validation import check_int, check_nonnegative, check_positive
from aocontrol.analysis import welch_psd
from aocontrol.controllers import ControllerBank

__all__ = [
    "DisturbanceSource",
    "ModalTimeSeries",
    "TurbulenceSource",
    "LinearModalSensor",
    "DiffractiveSensor",
    "Stage",
    "LoopResult",
    "LoopDivergedError",
    "run_loop",
]

logger = logging.getLogger(__name__)

#: Telemetry that can be recorded, each ``(n_frames, n_modes)`` float32 [nm].
TELEMETRY = ("disturbance", "measurements", "commands", "dm", "residuals")
# A residual larger than this factor times the largest disturbance of any mode (or 10 sigma
# of the measurement noise, plus 1 nm) seen so far is taken as a diverging loop.
_DIVERGENCE_FACTOR = 1e3
# Flat-wavefront measurements used to estimate a diffractive sensor's noise level.
_NOISE_PROBES = 8


class LoopDivergedError(RuntimeError):
    """The closed loop diverged: raised with the frame and the modes concerned."""

    def __init__(self, frame: int, modes: np.ndarray) -> None:
        self.frame = int(frame)
        self.modes = np.asarray(modes, dtype=int)
        shown = self.modes[:10].tolist()
        more = "" if self.modes.size <= 10 else f" (+{self.modes.size - 10} more)"
        super().__init__(
            f"closed loop diverged at frame {self.frame}: residual of modes {shown}{more} "
            "exceeds 1e3 x the disturbance; the controller is probably unstable for these "
            "modes (check aocontrol.analysis.is_stable)"
        )


@runtime_checkable
class DisturbanceSource(Protocol):
    """Anything that yields the next frames of the disturbance."""

    n_modes: int

    def next(self, n_frames: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Return modal disturbance ``(n_frames, n_modes)`` [nm] and the phase on the valid
        pupil pixels ``(n_frames, n_valid)`` [nm] (or ``None`` for a purely modal source)."""


class ModalTimeSeries:
    """A precomputed modal disturbance, shape ``(n_frames, n_modes)`` [nm]."""

    def __init__(self, series: np.ndarray) -> None:
        series = np.asarray(series, dtype=float)
        if series.ndim != 2 or series.shape[0] < 1:
            raise ValueError(f"series must have shape (n_frames, n_modes), got {series.shape}")
        if not np.all(np.isfinite(series)):
            raise ValueError("series must contain only finite values")
        self._series = series
        self._pos = 0
        self.n_modes = series.shape[1]

    def next(self, n_frames: int) -> tuple[np.ndarray, None]:
        end = self._pos + n_frames
        if end > self._series.shape[0]:
            raise ValueError(
                f"the modal time series has {self._series.shape[0]} frames, {end} were requested"
            )
        out = self._series[self._pos : end]
        self._pos = end
        return out, None


class TurbulenceSource:
    """Phase screens from an atmosphere, projected on a modal basis.

    Parameters
    ----------
    atmosphere : object with ``phase_vectors(n_frames) -> (n_frames, n_valid)`` [nm]
    basis : object with ``project(vectors) -> (..., n_modes)``, ``synthesize`` and ``n_modes``
    additive : DisturbanceSource, optional
        A modal disturbance added on top (e.g. a vibration), same modes.
    """

    def __init__(
        self,
        atmosphere: Any,
        basis: Any,
        *,
        additive: DisturbanceSource | None = None,
    ) -> None:
        self.atmosphere = atmosphere
        self.basis = basis
        self.n_modes = int(basis.n_modes)
        if additive is not None and additive.n_modes != self.n_modes:
            raise ValueError(f"additive has {additive.n_modes} modes, basis {self.n_modes}")
        self.additive = additive

    def next(self, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
        phase = self.atmosphere.phase_vectors(n_frames)
        modal = self.basis.project(phase)
        if self.additive is not None:
            extra, _ = self.additive.next(n_frames)
            modal = modal + extra
            phase = phase + self.basis.synthesize(extra)
        return modal, phase


@dataclass(frozen=True)
class LinearModalSensor:
    """The fast linear modal WFS: ``m = optical_gain * e + noise``.

    Parameters
    ----------
    optical_gain : float or ndarray (n_modes,)
        Modal sensitivity (1 for a perfectly calibrated linear sensor).
    noise_std : float or ndarray (n_modes,)
        Standard deviation of the modal measurement noise per frame [nm].
    """

    optical_gain: Any = 1.0
    noise_std: Any = 0.0

    def arrays(self, n_modes: int) -> tuple[np.ndarray, np.ndarray]:
        og = np.broadcast_to(np.asarray(self.optical_gain, dtype=float), (n_modes,))
        ns = np.broadcast_to(np.asarray(self.noise_std, dtype=float), (n_modes,))
        if not (np.all(np.isfinite(og)) and np.all(og > 0)):
            raise ValueError("optical_gain must be finite and > 0 for every mode")
        if not (np.all(np.isfinite(ns)) and np.all(ns >= 0)):
            raise ValueError("noise_std must be finite and >= 0 for every mode")
        return og, ns


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
        return int(self.reconstructor.shape[0])

    def measure_map(self, opd: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Modal measurement ``(n_modes,)`` [nm] of one residual OPD map ``(n_pix, n_pix)``."""
        if self.photons is None:
            sig = self.wfs.signals(opd)
        else:
            sig = self.wfs.measure(opd, self.photons, self.read_noise, rng)
        return self.reconstructor @ sig


def _sensor_arrays(sensor: Any, n_modes: int) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(sensor, DiffractiveSensor):
        if sensor.n_modes != n_modes:
            raise ValueError(
                f"the sensor reconstructs {sensor.n_modes} modes, the controller has {n_modes}"
            )
        return np.ones(n_modes), np.zeros(n_modes)
    if isinstance(sensor, LinearModalSensor):
        return sensor.arrays(n_modes)
    if hasattr(sensor, "optical_gain") and hasattr(sensor, "noise_std"):
        return LinearModalSensor(sensor.optical_gain, sensor.noise_std).arrays(n_modes)
    raise TypeError(
        "sensor must be a LinearModalSensor or have optical_gain and noise_std attributes "
        f"(a linear modal WFS), or a DiffractiveSensor, got {type(sensor).__name__}"
    )


@dataclass(frozen=True)
class Stage:
    """One AO stage: controller, sensor, loop delay and DM stroke.

    Parameters
    ----------
    controller : ControllerBank
        Runs at the stage rate ``controller.fs`` [Hz].
    sensor : LinearModalSensor or a linear modal WFS
    latency_frames : float
        RTC latency beyond the one-frame WFS integration [frames] (as in ``loop_plant``).
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
    """

    controller: ControllerBank
    sensor: Any = field(default_factory=LinearModalSensor)
    latency_frames: float = 0.0
    stroke: Any = None
    dm_stroke: float | None = None
    m2c: Any = None
    name: str = "stage"

    def __post_init__(self) -> None:
        if not isinstance(self.controller, ControllerBank):
            raise TypeError(
                f"controller must be a ControllerBank, got {type(self.controller).__name__}"
            )
        check_nonnegative("latency_frames", self.latency_frames)
        _sensor_arrays(self.sensor, self.controller.n_modes)
        if self.dm_stroke is not None:
            check_positive("dm_stroke", self.dm_stroke)
            m2c = np.asarray(self.m2c, dtype=float) if self.m2c is not None else None
            if m2c is None or m2c.ndim != 2 or m2c.shape[1] != self.controller.n_modes:
                raise ValueError(
                    "dm_stroke needs m2c of shape (n_act, n_modes) with n_modes="
                    f"{self.controller.n_modes}, got "
                    f"{None if m2c is None else m2c.shape}"
                )
            object.__setattr__(self, "m2c", m2c)

    @property
    def fs(self) -> float:
        return self.controller.fs

    @property
    def n_modes(self) -> int:
        return self.controller.n_modes


@dataclass(frozen=True)
class LoopResult:
    """Result of one closed-loop run.

    Attributes
    ----------
    fs : float
        Loop rate [Hz].
    n_frames : int
    telemetry : dict of str -> ndarray (n_frames, n_modes) float32 [nm]
        Recorded among ``disturbance, measurements, commands, dm, residuals``.
    residual_variance : ndarray (n_modes,)
        Mean square residual per mode after ``settle_frames`` [nm^2].
    disturbance_variance : ndarray (n_modes,)
        Same for the disturbance [nm^2].
    saturation : ndarray (n_modes,) of int
        Frames in which each mode's DM command was clipped.
    settle_frames : int
        Frames discarded at the start for the statistics.
    science : object or None
        Science-camera result (Strehl, contrast) if a camera was given.
    metadata : dict
        Case and controller settings (JSON-serialisable), saved with the result.
    actuator_saturation : ndarray (n_act,) of int or None
        Frames in which each DM actuator was clipped (with ``Stage.dm_stroke``).
    """

    fs: float
    n_frames: int
    telemetry: dict
    residual_variance: np.ndarray
    disturbance_variance: np.ndarray
    saturation: np.ndarray
    settle_frames: int
    science: Any = None
    metadata: dict = field(default_factory=dict)
    actuator_saturation: np.ndarray | None = None

    @property
    def residual_rms(self) -> float:
        """Total modal residual RMS [nm] (sum over modes)."""
        return float(np.sqrt(np.sum(self.residual_variance)))

    def psd(self, name: str = "residuals", *, nperseg: int = 1024) -> tuple[np.ndarray, np.ndarray]:
        """One-sided PSD [nm^2/Hz] of a recorded signal after settling.

        :func:`aocontrol.analysis.welch_psd` (record mean removed once, one-sided at every
        bin). Returns ``freqs`` (n_f,) [Hz] and ``psd`` (n_modes, n_f).
        """
        if name not in self.telemetry:
            raise KeyError(f"{name!r} was not recorded; recorded: {sorted(self.telemetry)}")
        x = np.asarray(self.telemetry[name][self.settle_frames :], dtype=float)
        return welch_psd(x, self.fs, nperseg)

    def save(self, path: str | os.PathLike) -> None:
        """Write the result to ``path`` (.npz: arrays + JSON metadata), atomically."""
        path = os.fspath(path)
        arrays = {f"telemetry/{k}": v for k, v in self.telemetry.items()}
        arrays.update(
            residual_variance=self.residual_variance,
            disturbance_variance=self.disturbance_variance,
            saturation=self.saturation,
        )
        if self.actuator_saturation is not None:
            arrays["actuator_saturation"] = self.actuator_saturation
        science = None
        if self.science is not None and hasattr(self.science, "to_dict"):
            science = self.science.to_dict()
        meta = dict(
            fs=self.fs,
            n_frames=self.n_frames,
            settle_frames=self.settle_frames,
            metadata=self.metadata,
            science=science,
        )
        arrays["meta_json"] = np.array(json.dumps(meta, default=_json_default))
        directory = os.path.dirname(os.path.abspath(path))
        fd, tmp = tempfile.mkstemp(dir=directory, suffix=".npz.tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez_compressed(fh, **arrays)
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    @classmethod
    def load(cls, path: str | os.PathLike) -> LoopResult:
        """Read a result written by :meth:`save` (science as a plain dict)."""
        with np.load(os.fspath(path), allow_pickle=False) as data:
            meta = json.loads(str(data["meta_json"]))
            tele = {k.split("/", 1)[1]: data[k] for k in data.files if k.startswith("telemetry/")}
            return cls(
                fs=meta["fs"],
                n_frames=meta["n_frames"],
                telemetry=tele,
                residual_variance=data["residual_variance"],
                disturbance_variance=data["disturbance_variance"],
                saturation=data["saturation"],
                settle_frames=meta["settle_frames"],
                science=meta["science"],
                metadata=meta["metadata"],
                actuator_saturation=(
                    data["actuator_saturation"] if "actuator_saturation" in data.files else None
                ),
            )


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return str(obj)


def run_loop(
    stage: Stage,
    disturbance: DisturbanceSource,
    n_frames: int,
    *,
    rng: np.random.Generator | int | None = None,
    science: Any = None,
    basis: Any = None,
    science_every: int = 10,
    record: tuple[str, ...] = TELEMETRY,
    settle_frames: int | None = None,
    chunk: int = 1000,
    progress: bool = False,
    metadata: dict | None = None,
) -> LoopResult:
    """Run one AO stage in closed loop for ``n_frames`` frames.

    Parameters
    ----------
    stage : Stage
    disturbance : DisturbanceSource
        Modal disturbance (and phase maps when a science camera is used).
    n_frames : int
    rng : numpy.random.Generator or int
        Source of the measurement noise (required when the sensor is noisy).
    science : object with ``add(maps (n, n_pix, n_pix))`` and ``result()``, optional
        Long-exposure accumulator; fed every ``science_every`` frames with the residual phase
        ``phase - DM shape`` (needs ``basis`` and phase maps from the source).
    basis : object with ``synthesize(coeffs) -> (..., n_valid)`` and ``pupil``, optional
        Needed for the science camera and for a :class:`DiffractiveSensor` (which measures
        the residual map ``phase - DM shape`` every frame).
    record : tuple of str
        Telemetry to keep (float32), among ``disturbance, measurements, commands, dm,
        residuals``. Statistics are computed regardless.
    settle_frames : int, optional
        Frames excluded from the statistics (default: 1% of the run, at least 20).
    chunk : int
        Frames generated at once (memory vs. speed).
    progress : bool
        Show a tqdm progress bar.
    metadata : dict, optional
        Case/controller settings stored with the result.

    Raises
    ------
    LoopDivergedError
        If a residual blows up (unstable controller), naming the frame and modes.
    """
    n_frames = check_int("n_frames", n_frames, minimum=1)
    chunk = check_int("chunk", chunk, minimum=1)
    science_every = check_int("science_every", science_every, minimum=1)
    bad = set(record) - set(TELEMETRY)
    if bad:
        raise ValueError(f"record must be a subset of {TELEMETRY}, got unknown {sorted(bad)}")
    if not isinstance(disturbance, DisturbanceSource):
        raise TypeError("disturbance must provide n_modes and next(n_frames)")
    n = stage.n_modes
    if disturbance.n_modes != n:
        raise ValueError(f"disturbance has {disturbance.n_modes} modes, the controller {n}")
    if science is not None and basis is None:
        raise ValueError("a science camera needs basis= to form the DM shape")
    diffractive = isinstance(stage.sensor, DiffractiveSensor)
    if diffractive and basis is None:
        raise ValueError("a DiffractiveSensor needs basis= to form the residual phase map")
    og, noise_std = _sensor_arrays(stage.sensor, n)
    noisy = bool(np.any(noise_std > 0)) or (diffractive and stage.sensor.photons is not None)
    if noisy and rng is None:
        raise ValueError("rng is required with a noisy sensor (reproducibility)")
    rng = np.random.default_rng(rng)
    if diffractive and stage.sensor.photons is not None:
        # Modal noise level of the diffractive sensor (for the divergence guard only), from a
        # few measurements of a flat wavefront with a child generator: the loop's own noise
        # stream is unchanged.
        probe_rng = rng.spawn(1)[0]
        flat = basis.pupil.to_map(np.zeros(basis.pupil.n_valid))
        probe = np.array([stage.sensor.measure_map(flat, probe_rng) for _ in range(_NOISE_PROBES)])
        noise_std = probe.std(axis=0)
    settle = (
        max(20, n_frames // 100)
        if settle_frames is None
        else check_int("settle_frames", settle_frames, minimum=0)
    )
    if settle >= n_frames:
        raise ValueError(f"settle_frames={settle} must be < n_frames={n_frames}")

    k0 = math.floor(stage.latency_frames)
    frac = float(stage.latency_frames - k0)
    if abs(frac - round(frac)) < 1e-9:
        k0, frac = int(round(stage.latency_frames)), 0.0
    depth = k0 + 2
    hist = np.zeros((depth, n))  # ring buffer of applied commands, hist[k % depth] = u[k]
    stroke = (
        None
        if stage.stroke is None
        else np.broadcast_to(np.asarray(stage.stroke, dtype=float), (n,))
    )
    saturation = np.zeros(n, dtype=np.int64)
    act_stroke = stage.dm_stroke
    if act_stroke is not None:
        m2c = stage.m2c
        c2m = np.linalg.pinv(m2c)
        act_saturation = np.zeros(m2c.shape[0], dtype=np.int64)
    resid_map = None

    tele = {name: np.empty((n_frames, n), dtype=np.float32) for name in record}
    sum_e2 = np.zeros(n)
    sum_d2 = np.zeros(n)
    e_prev = np.zeros(n)
    dmax = np.zeros(n)
    ctrl = stage.controller
    ctrl.reset()

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_frames, desc=f"{stage.name} loop", unit="frame")
    k = 0
    try:
        while k < n_frames:
            m_chunk = min(chunk, n_frames - k)
            d, maps = disturbance.next(m_chunk)
            d = np.asarray(d, dtype=float)
            if (science is not None or diffractive) and maps is None:
                raise ValueError(
                    "the disturbance source gives no phase maps (needed by the "
                    "science camera and a DiffractiveSensor)"
                )
            if diffractive and resid_map is None:
                resid_map = basis.pupil.to_map(np.zeros(maps.shape[1]))
            linear_noise = noisy and not diffractive  # a DiffractiveSensor draws its own
            noise = (
                rng.standard_normal((m_chunk, n)) * noise_std
                if linear_noise
                else np.zeros((m_chunk, n))
            )
            np.maximum(dmax, np.abs(d).max(axis=0), out=dmax)
            # Scale of a healthy residual: the largest disturbance or noise (through T) of any
            # mode (modes couple through stroke clipping and diffractive sensing).
            limit = _DIVERGENCE_FACTOR * (dmax.max() + 10.0 * np.max(noise_std / og)) + 1.0
            out = {name: np.empty((m_chunk, n)) for name in record}
            sci_idx, sci_dm = [], []
            for j in range(m_chunk):
                if diffractive:
                    m = stage.sensor.measure_map(resid_map, rng)
                else:
                    m = og * e_prev + noise[j]
                u = ctrl.step(m)
                if stroke is not None:
                    over = np.abs(u) > stroke
                    if over.any():
                        saturation += over
                        u = np.clip(u, -stroke, stroke)
                if act_stroke is not None:
                    a = m2c @ u
                    over = np.abs(a) > act_stroke
                    if over.any():
                        act_saturation += over
                        saturation += np.abs(c2m[:, over]).sum(axis=1) > 0
                        u = c2m @ np.clip(a, -act_stroke, act_stroke)
                hist[k % depth] = u
                y = (1.0 - frac) * hist[(k - k0) % depth]
                if frac:
                    y = y + frac * hist[(k - k0 - 1) % depth]
                e = d[j] - y
                if not np.all(np.abs(e) < limit):
                    raise LoopDivergedError(k, np.flatnonzero(~(np.abs(e) < limit)))
                if k >= settle:
                    sum_e2 += e * e
                    sum_d2 += d[j] * d[j]
                for name, val in (
                    ("measurements", m),
                    ("commands", u),
                    ("dm", y),
                    ("residuals", e),
                ):
                    if name in out:
                        out[name][j] = val
                if science is not None and k >= settle and k % science_every == 0:
                    sci_idx.append(j)
                    sci_dm.append(y)
                e_prev = e
                if diffractive:
                    resid_map = basis.pupil.to_map(maps[j] - basis.synthesize(y))
                k += 1
            base = k - m_chunk
            for name in record:
                tele[name][base:k] = d if name == "disturbance" else out[name]
            if sci_idx:
                dm_shape = basis.synthesize(np.asarray(sci_dm))
                science.add(basis.pupil.to_map(maps[np.asarray(sci_idx)] - dm_shape))
            if bar is not None:
                bar.update(m_chunk)
    finally:
        if bar is not None:
            bar.close()
        ctrl.reset()

    n_stat = n_frames - settle
    result_science = science.result() if science is not None else None
    if saturation.any():
        logger.info("%s: DM saturated in %d mode-frames", stage.name, int(saturation.sum()))
    return LoopResult(
        fs=stage.fs,
        n_frames=n_frames,
        telemetry=tele,
        residual_variance=sum_e2 / n_stat,
        disturbance_variance=sum_d2 / n_stat,
        saturation=saturation,
        settle_frames=settle,
        science=result_science,
        metadata=dict(
            metadata or {},
            stage=stage.name,
            latency_frames=stage.latency_frames,
            controller=repr(stage.controller),
        ),
        actuator_saturation=act_saturation if act_stroke is not None else None,
    )
