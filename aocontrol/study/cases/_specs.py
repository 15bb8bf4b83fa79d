"""The validated case as frozen dataclasses (:class:`Case` and its specifications) and
:class:`CaseError`; :mod:`aocontrol.study.cases` parses the TOML files into them."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any


class CaseError(ValueError):
    """Invalid case file or override: names the file, the key and the reason.

    Parameters
    ----------
    source : str
        The file (or ``"overrides"``) where the bad value is.
    key : str
        Dotted key, e.g. ``"stage2.fs"``.
    reason : str
        What is wrong and what was expected.
    """

    def __init__(self, source: str, key: str, reason: str) -> None:
        self.source, self.key, self.reason = str(source), str(key), str(reason)
        super().__init__(f"{self.source}: {self.key}: {self.reason}")


# ------------------------------------------------------------------------- specifications
@dataclass(frozen=True)
class DriftSpec:
    """A drifting-atmosphere scenario (``[atmosphere.drift]``), see :mod:`aocontrol.sim.drift`.

    Parameters
    ----------
    kind : str
        ``"step"``, ``"ramp"``, ``"stochastic"`` or ``"knots"``.
    seeing : float or tuple of float
        Seeing factor reached (step, ramp), > 0; one per knot (knots).
    wind : float or tuple of float
        Wind-speed factor reached (step, ramp), >= 0; one per knot (knots).
    direction : float or tuple of float
        Wind-direction offset reached [deg] (step, ramp); one per knot (knots).
    at : float
        Time of a step [s].
    start, stop : float
        Start and end of a ramp [s].
    duration : float
        Length of a stochastic history [s].
    seed : int
        Seed of a stochastic history.
    knot_interval, seeing_timescale, wind_timescale : float or None
        Stochastic model settings [s] (``None``: the module's defaults).
    seeing_rms_change_1h : float or None
        RMS seeing change over one hour [arcsec] (``None``: 0.16, Paranal).
    wind_log_sigma : float
        Log-standard deviation of the wind factor (0: no wind drift).
    times : tuple of float
        Knot times [s] (knots), non-decreasing.
    """

    kind: str
    seeing: float | tuple[float, ...] = 1.0
    wind: float | tuple[float, ...] = 1.0
    direction: float | tuple[float, ...] = 0.0
    at: float = 0.0
    start: float = 0.0
    stop: float = 0.0
    duration: float = 0.0
    seed: int = 0
    knot_interval: float | None = None
    seeing_timescale: float | None = None
    seeing_rms_change_1h: float | None = None
    wind_timescale: float | None = None
    wind_log_sigma: float = 0.0
    times: tuple[float, ...] = ()

    def build(self, base_seeing: float) -> Any:
        """The :class:`aocontrol.sim.drift.Drift` of this scenario.

        Parameters
        ----------
        base_seeing : float
            The case's seeing [arcsec] (median of the stochastic model).
        """
        from aocontrol.sim.drift import Drift

        if self.kind == "knots":
            return Drift(self.times, self.seeing, self.wind, self.direction, name="case knots")
        if self.kind == "step":
            return Drift.step(self.at, seeing=self.seeing, wind=self.wind, direction=self.direction)
        if self.kind == "ramp":
            return Drift.ramp(
                self.start,
                self.stop,
                seeing=self.seeing,
                wind=self.wind,
                direction=self.direction,
            )
        options = {
            k: getattr(self, k)
            for k in (
                "knot_interval",
                "seeing_timescale",
                "seeing_rms_change_1h",
                "wind_timescale",
            )
            if getattr(self, k) is not None
        }
        return Drift.stochastic(
            self.duration,
            self.seed,
            base_seeing=base_seeing,
            wind_log_sigma=self.wind_log_sigma,
            **options,
        )


@dataclass(frozen=True)
class AtmosphereSpec:
    """Turbulence of a case.

    Parameters
    ----------
    seeing : float
        Seeing FWHM at 500 nm [arcsec], > 0.
    tau0 : float
        Coherence time at 500 nm [s], > 0.
    L0 : float
        Von Karman outer scale [m], > 0.
    profile : str
        Turbulence profile name (``"eso-median"``, the ESO 35-layer median profile).
    n_layers : int
        Layers of the published profile (35).
    simulated_layers : int
        Equivalent layers simulated (compression of the profile, <= ``n_layers``).
    drift : DriftSpec or None
        Seeing and wind drift (``[atmosphere.drift]``), ``None`` for a stationary sky.
    """

    seeing: float
    tau0: float
    L0: float
    profile: str
    n_layers: int
    simulated_layers: int
    drift: DriftSpec | None = None


@dataclass(frozen=True)
class StarSpec:
    """Guide star.

    Parameters
    ----------
    G : float
        Gaia G magnitude (Vega), flux of stage 1.
    J : float
        J magnitude (Vega, 2MASS), flux of stage 2.
    """

    G: float
    J: float


@dataclass(frozen=True)
class StageSpec:
    """One AO stage.

    Parameters
    ----------
    fs : float
        Loop rate [Hz].
    n_modes : int
        Controlled KL modes.
    wavelength : float
        WFS wavelength [m].
    latency_frames : float
        RTC latency beyond the one-frame WFS integration [frames].
    n_actuators : int
        DM actuators across the diameter (Fried geometry).
    wfs : str
        ``"shack-hartmann"`` or ``"pyramid"``.
    n_subapertures : int
        Subapertures (detector pixels for the pyramid) across the pupil.
    band : str
        Photometric band of the flux (``"G"`` or ``"J"``).
    read_noise : float
        Detector read-out noise [e- RMS per pixel per frame].
    throughput : float
        Sky-to-detector efficiency in (0, 1].
    gain : float
        Gain of the reference integrator (stage 1 keeps it; stage 2's reference is scanned).
    dm_stroke : float or None
        Actuator stroke [m of OPD] (``None``: unlimited).
    modulation : float
        Pyramid modulation radius [lambda/D] (0 for a Shack-Hartmann).
    n_modulation_points : int
        Pyramid modulation points (0 for a Shack-Hartmann).
    pixels_per_subaperture : int
        Shack-Hartmann detector pixels across a subaperture (0 for a pyramid).
    pixel_scale : float
        Shack-Hartmann pixel scale [arcsec] (0 for a pyramid).
    sensor : {"linear", "diffractive"}
        The sensor in the loop: the linear modal model (the fast default) or the diffractive
        pyramid model (a pyramid stage only; the Shack-Hartmann of stage 1 stays linear).
    optical_gain : {"none", "calibrated", "tracked", "two-pass"}
        Optical-gain handling: the raw reconstructor (the loop sees the true gains), the
        compensation calibrated once around the fitting error, tracked online (modal
        dither, :class:`aocontrol.sim.DitherGainTracker`), or calibrated around the
        closed-loop residual of a first run (``two-pass``,
        :func:`aocontrol.study.compare.two_pass_scene`).
    latency_error : float
        Model error: the true latency is ``latency_frames + latency_error`` [frames] (the
        designs keep ``latency_frames``).
    optical_gain_error : float
        Model error: the sensor's true optical gains / the compensated ones.
    optical_gain_drift, optical_gain_drift_period : float
        Model error: relative amplitude and period [s] of a sinusoidal drift of those gains.
    dm_time_constant : float
        Model error: the DM's first-order time constant [s] (0: none).
    dm_resonance, dm_damping : float
        Model error: the DM's mechanical resonance [Hz] (``None``: none) and its damping.
    misregistration_shift_x, misregistration_shift_y, misregistration_rotation : float
        Model error: the DM moved against the WFS after calibration [subapertures, deg].
    """

    fs: float
    n_modes: int
    wavelength: float
    latency_frames: float
    n_actuators: int
    wfs: str
    n_subapertures: int
    band: str
    read_noise: float
    throughput: float
    gain: float
    dm_stroke: float | None = None
    modulation: float = 0.0
    n_modulation_points: int = 0
    pixels_per_subaperture: int = 0
    pixel_scale: float = 0.0
    sensor: str = "linear"
    optical_gain: str = "calibrated"
    latency_error: float = 0.0
    optical_gain_error: float = 1.0
    optical_gain_drift: float = 0.0
    optical_gain_drift_period: float = 60.0
    dm_time_constant: float = 0.0
    dm_resonance: float | None = None
    dm_damping: float = 0.1
    misregistration_shift_x: float = 0.0
    misregistration_shift_y: float = 0.0
    misregistration_rotation: float = 0.0

    @property
    def true_latency_frames(self) -> float:
        """The loop's true latency [frames]: the design's plus the model error."""
        return self.latency_frames + self.latency_error

    @property
    def misregistered(self) -> bool:
        """Whether the DM is misregistered against the WFS (a model error)."""
        return bool(
            self.misregistration_shift_x or self.misregistration_shift_y
            or self.misregistration_rotation
        )  # fmt: skip

    @property
    def dm_stroke_nm(self) -> float | None:
        """Actuator stroke [nm of OPD] (``None``: unlimited).

        The one metres-to-nanometres conversion of the stroke: cases give SI units, the
        simulator and the controllers work in nm (wavefronts as optical path in nm).
        """
        return None if self.dm_stroke is None else float(self.dm_stroke) * 1e9


@dataclass(frozen=True)
class ScienceSpec:
    """Science camera and exposure.

    Parameters
    ----------
    wavelength : float
        Science wavelength [m] (1.65 um).
    exposure : float
        Exposure after start-up [s].
    startup : float
        Start-up discarded before the exposure [s].
    science_every : int
        A PSF every this many stage-2 frames.
    field_of_view : float
        Half-width of the science image [lambda/D].
    coronagraph : str
        ``"perfect"``.
    """

    wavelength: float
    exposure: float
    startup: float
    science_every: int
    field_of_view: float
    coronagraph: str


@dataclass(frozen=True)
class SimulationSpec:
    """Sampling of the simulation (not a property of the sky).

    Parameters
    ----------
    n_pix : int
        Pupil samples across the diameter.
    diameter : float
        Telescope diameter [m].
    obstruction : float
        Central obstruction (fraction of the diameter).
    """

    n_pix: int
    diameter: float
    obstruction: float


@dataclass(frozen=True)
class VibrationSpec:
    """A vibration added to the atmosphere.

    Parameters
    ----------
    modes : tuple of int
        Modal indices (0 tip, 1 tilt) the vibration acts on.
    frequencies : tuple of float
        Peak frequencies [Hz].
    dampings : tuple of float
        Damping ratio of each peak (dimensionless, > 0).
    rms : tuple of float
        OPD RMS of each peak on the mode [m].
    fir_taps : int or None
        Length of the FIR filter fitted to the PSD [samples of the fast clock]; ``None`` for
        the default of :func:`aocontrol.sim.vibration.fir_from_psd`.
    """

    modes: tuple[int, ...]
    frequencies: tuple[float, ...]
    dampings: tuple[float, ...]
    rms: tuple[float, ...]
    fir_taps: int | None = None


@dataclass(frozen=True)
class Case:
    """A science case: every setting of one row of the paper's case tables and the rest.

    Parameters
    ----------
    name : str
        Case name (file stem).
    title : str
        Human-readable name.
    source : str
        File it was loaded from.
    atmosphere : AtmosphereSpec
    star : StarSpec
    stage1 : StageSpec
        SAXO (Shack-Hartmann).
    stage2 : StageSpec
        SAXO+ second stage (pyramid).
    science : ScienceSpec
    simulation : SimulationSpec
    vibration : VibrationSpec or None
    raw : dict
        The merged TOML tables (unit strings kept), used to apply overrides.
    """

    name: str
    title: str
    source: str
    atmosphere: AtmosphereSpec
    star: StarSpec
    stage1: StageSpec
    stage2: StageSpec
    science: ScienceSpec
    simulation: SimulationSpec
    vibration: VibrationSpec | None = None
    raw: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def rate_ratio(self) -> int:
        """Stage-2 frames per stage-1 frame (an integer by validation)."""
        return int(round(self.stage2.fs / self.stage1.fs))

    def to_dict(self) -> dict:
        """Every value in canonical units (JSON-serialisable, tuples as lists)."""
        out = asdict(self)
        out.pop("raw")
        return _jsonable(out)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj


# Documented, pickled and shown under the package that exports them.
for _cls in (
    CaseError,
    DriftSpec,
    AtmosphereSpec,
    StarSpec,
    StageSpec,
    ScienceSpec,
    SimulationSpec,
    VibrationSpec,
    Case,
):
    _cls.__module__ = "aocontrol.study.cases"
del _cls
