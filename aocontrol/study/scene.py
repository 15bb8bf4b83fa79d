"""Build everything a science case needs: pupil, DMs and KL bases, the projection between the
stage bases, the atmosphere at the case's seeing and tau0, the sensors with their noise, the
plants, the science camera and the vibration.

Physics of the sensors
----------------------
- Photons: :func:`aocontrol.sim.noise.photons_per_frame` from the case's G (stage 1) and J
  (stage 2) magnitudes, the stage's frame time and throughput (photo-electrons per frame over
  the pupil).
- Stage 2, pyramid: the diffractive model (:class:`aocontrol.sim.wfs.PyramidWFS`, 3 lambda/D,
  20 modulation points) is calibrated on the stage-2 KL modes
  (as :meth:`aocontrol.sim.wfs.LinearModalSensor.from_diffractive` does, with exact-derivative
  interaction matrices): noise propagation per mode from
  the photon and read noise on its pixels, and optical gains around residual screens with the
  fitting-error spectrum (:func:`aocontrol.sim.wfs.fitting_residual_screens`) of RMS the
  fitting error of the finer of the two DMs (:func:`aocontrol.sim.modes.fitting_error`), the
  part of the residual no stage corrects. The loop's reconstructor compensates the optical
  gains (modal gain compensation, as a calibrated instrument does): the linear sensor has unit
  gain and noise ``sigma / g`` per mode. Approximation: the gains are those of the fitting
  error alone (servo-lag and noise residuals are smaller in the bright cases, not in the red
  ones, where the true gains are lower).
- Sensor in the loop and optical gains (the case's ``[stage2] sensor`` and ``optical_gain``,
  :meth:`StageScene.loop_sensor`): ``linear`` (above, the fast default) or ``diffractive``
  (the pyramid model itself every frame, photon and read noise on its pixels, then the
  reconstructor calibrated around a flat wavefront, as COMPASS does); optical gains ``none``
  (raw reconstructor: the loop sees the true gains), ``calibrated`` (the compensation above)
  or ``tracked`` (modal dither, :class:`aocontrol.sim.DitherGainTracker`, starting from the
  calibrated gains). Stage 1 stays linear.
- Stage 1, Shack-Hartmann: :func:`aocontrol.sim.wfs.shack_hartmann_calibration`, the
  reconstructor of the geometric model on the stage-1 KL modes and the slope noise of the
  diffractive model (spot sampled at lambda/(2d) per pixel, i.e. 0.356" at 0.69 um for the
  0.36" of SAXO; the model needs >= 4 pupil samples per subaperture, hence 8x8 pixels instead
  of SAXO's 6x6). The EMCCD excess-noise factor is not modelled (the case's read noise is the
  effective one).

Calibrations (DMs, bases, reconstructors, noise coefficients, optical gains) are cached in
memory per (sampling, seeing, stage geometry, quick): a gain scan, the calibration runs and
the configurations of a case share them, and a change of flux, rate or tau0 reuses them. They
are also cached on disk (:mod:`aocontrol.study._cache`: ``$AOCONTROL_CACHE`` or the user cache
folder, content-addressed, checked before use), shared by the workers of a sweep and by later
runs; ``cache=False`` bypasses both caches.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from aocontrol._deprecation import DeprecatedAttribute
from aocontrol.plant import loop_plant
from aocontrol.sim.atmosphere import Atmosphere
from aocontrol.sim.dm import DeformableMirror, ModalDM
from aocontrol.sim.loop import DitherGainTracker, projection_matrix
from aocontrol.sim.model_errors import DMResponse, OpticalGainError, misregistration_matrix
from aocontrol.sim.modes import ModalBasis, fitting_error, kl_basis
from aocontrol.sim.noise import photons_per_frame
from aocontrol.sim.profiles import eso_atmosphere, eso_median_profile, scale_to_tau0
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.science import ScienceCamera
from aocontrol.sim.turbulence import r0_from_seeing
from aocontrol.sim.vibration import TiltVibration, VibrationPSD, tilt_vibration_psd
from aocontrol.sim.wfs import (
    DiffractiveSensor,
    LinearModalSensor,
    PyramidWFS,
    WFSCalibration,
    calibrate,
    fitting_residual_screens,
    optical_gains,
    shack_hartmann_calibration,
)
from aocontrol.study._cache import cached as disk_cached
from aocontrol.study._seeds import seed_sequence
from aocontrol.study.cases import Case, StageSpec, apply_overrides, load_case

__all__ = ["QUICK_MODES", "Scene", "StageScene", "build_scene", "clear_scene_cache"]

logger = logging.getLogger(__name__)

#: Quick mode (tests, smoke runs): at most this many KL modes per stage (stage 1, stage 2).
QUICK_MODES = (100, 24)
# Residual screens averaged for the pyramid's optical gains (2 is enough: the gains of one
# screen differ from the mean of many by a few per cent for this spectrum).
_OG_SCREENS = 2
# Push-pull amplitude of the calibrations [nm RMS]: small against the 1.04-um wavelength
# (linear regime) and large against rounding.
_CAL_AMPLITUDE = 10.0
# Optical-gain tracking ("tracked"): dithered modes (log-spaced in order, where the gains
# vary fastest), dither amplitude [nm] (cost: n_probes * a^2 of residual variance, ~60 nm^2,
# a few per cent of a faint case's residual), update period [s] and memory (updates: a 2-s
# horizon). An estimate is used once its relative error is < 10 % (DitherGainTracker).
_DITHER_PROBES = 16
_DITHER_NM = 2.0
_DITHER_UPDATE_S = 0.1
_DITHER_MEMORY = 20.0
_CACHE: dict[str, Scene] = {}
_GEOMETRY_CACHE: dict[str, dict] = {}


@dataclass(frozen=True, eq=False)
class StageScene:
    """What one stage needs: DM, modal basis, plant and linear sensor.

    Parameters
    ----------
    spec : StageSpec
        The case's stage values.
    dm : DeformableMirror
        The mirror's geometry (influence functions; the KL basis is built on it). Its stroke
        in the loop is :meth:`modal_dm`'s.
    basis : ModalBasis
        ``spec.n_modes`` KL modes (fewer in quick mode).
    plant : control.TransferFunction
        ``loop_plant(fs, latency_frames)``.
    photons : float
        Photo-electrons per frame on the WFS.
    sensor : LinearModalSensor
        Unit optical gain (compensated), noise per mode [nm RMS per frame].
    calibrated_gains : ndarray, shape (n_modes,)
        Calibrated optical gains (compensated by the reconstructor; 1 for the Shack-Hartmann).
        (``optical_gain``, its former name, is deprecated: ``optical_gain`` names the
        handling setting, a string, everywhere else.)
    raw_noise_std : ndarray, shape (n_modes,)
        Noise per mode before the optical-gain compensation [nm RMS per frame].
    wfs : PyramidWFS, optional
        The diffractive model (``None`` for the Shack-Hartmann, which stays linear).
    calibration : WFSCalibration, optional
        Its calibration around a flat wavefront (reconstructor, noise coefficients).
    """

    spec: StageSpec
    dm: DeformableMirror
    basis: ModalBasis
    plant: Any
    photons: float
    sensor: LinearModalSensor
    calibrated_gains: np.ndarray
    raw_noise_std: np.ndarray
    wfs: Any = None
    calibration: WFSCalibration | None = None

    #: Deprecated name of :attr:`calibrated_gains`.
    optical_gain = DeprecatedAttribute(
        "calibrated_gains", "the calibrated optical gains; optical_gain names the handling"
    )

    @property
    def fs(self) -> float:
        """Loop rate [Hz]."""
        return self.spec.fs

    @property
    def n_modes(self) -> int:
        """Controlled modes."""
        return self.basis.n_modes

    @property
    def noise_std(self) -> np.ndarray:
        """Measurement noise per mode seen by the controller [nm RMS per frame]."""
        return np.asarray(self.sensor.noise_std)

    def modal_dm(self) -> ModalDM:
        """The stage's DM in the loop: the basis' ``m2c`` and the case's actuator stroke.

        The case's ``dm_stroke`` [m] enters once, converted by ``StageSpec.dm_stroke_nm``;
        the loop's :class:`~aocontrol.sim.Stage` takes this DM and the MPC its
        :attr:`~aocontrol.sim.dm.ModalDM.command_bound`. With the case's model errors: the
        mirror's temporal response and misregistration.
        """
        spec = self.spec
        return ModalDM(
            self.basis.n_modes,
            actuator_stroke=spec.dm_stroke_nm,
            m2c=self.basis.m2c,
            response=DMResponse(spec.dm_time_constant, spec.dm_resonance, spec.dm_damping),
            mixing=self.misregistration,
        )

    @cached_property
    def misregistration(self) -> np.ndarray | None:
        """The case's DM misregistration as the modes the mirror makes (``None``: none),
        :func:`aocontrol.sim.model_errors.misregistration_matrix`."""
        spec = self.spec
        if not spec.misregistered:
            return None
        return misregistration_matrix(
            self.dm,
            self.basis,
            shift_x=spec.misregistration_shift_x,
            shift_y=spec.misregistration_shift_y,
            rotation=spec.misregistration_rotation,
            subaperture=self.dm.pupil.diameter / spec.n_subapertures,
        )

    def optical_gain_error(self) -> OpticalGainError | None:
        """The case's optical-gain model error (``None``: the compensated gains are true)."""
        spec = self.spec
        err = OpticalGainError(
            spec.optical_gain_error, spec.optical_gain_drift, spec.optical_gain_drift_period
        )
        return None if err.is_identity else err

    def with_optical_gains(self, gains: np.ndarray) -> StageScene:
        """The same stage with other calibrated optical gains (the compensated linear sensor
        rebuilt from them).

        Parameters
        ----------
        gains : ndarray (n_modes,)
            Optical gains, > 0.
        """
        og = np.asarray(gains, dtype=float)
        if og.shape != (self.n_modes,) or not np.all(og > 0):
            raise ValueError(f"gains must be {self.n_modes} values > 0, got shape {og.shape}")
        sensor = LinearModalSensor(np.ones(self.n_modes), self.raw_noise_std / og)
        return dataclasses.replace(self, calibrated_gains=og, sensor=sensor)

    def loop_sensor(
        self, sensor: str | None = None, optical_gain: str | None = None
    ) -> tuple[Any, DitherGainTracker | None]:
        """The sensor in the loop and the optical-gain tracker, per the case's settings.

        Parameters
        ----------
        sensor : {"linear", "diffractive"}, optional
            Default ``spec.sensor``.
        optical_gain : {"none", "calibrated", "tracked", "two-pass"}, optional
            Default ``spec.optical_gain`` ("two-pass" compensates :attr:`calibrated_gains` like
            "calibrated": the scene's gains are then those of
            :func:`aocontrol.study.compare.two_pass_scene`).

        Returns
        -------
        sensor : LinearModalSensor or DiffractiveSensor
        tracker : DitherGainTracker or None
            Only for ``"tracked"`` (starting from the calibrated gains).

        Raises
        ------
        ValueError
            An unknown setting, or ``"diffractive"`` for a stage without a diffractive model.
        """
        from aocontrol.study.cases import OPTICAL_GAIN_SETTINGS, SENSORS

        kind = self.spec.sensor if sensor is None else sensor
        handling = self.spec.optical_gain if optical_gain is None else optical_gain
        if kind not in SENSORS:
            raise ValueError(f"sensor must be one of {list(SENSORS)}, got {kind!r}")
        if handling not in OPTICAL_GAIN_SETTINGS:
            raise ValueError(
                f"optical_gain must be one of {list(OPTICAL_GAIN_SETTINGS)}, got {handling!r}"
            )
        tracker = None
        if handling == "tracked":
            n = self.n_modes
            probes = np.unique(np.geomspace(1, n, min(n, _DITHER_PROBES)).round().astype(int) - 1)
            tracker = DitherGainTracker(
                amplitude=_DITHER_NM,
                update_every=max(10, int(round(_DITHER_UPDATE_S * self.fs))),
                memory=_DITHER_MEMORY,
                modes=probes,
                initial=np.clip(self.calibrated_gains, 0.05, 3.0),
            )
        if kind == "linear":
            if handling in ("calibrated", "two-pass"):  # two-pass: self.calibrated_gains is the
                return self.sensor, None  # closed-loop one (two_pass_scene)
            # the loop sees the (calibrated) gains: raw reconstructor
            return LinearModalSensor(self.calibrated_gains, self.raw_noise_std), tracker
        if self.wfs is None or self.calibration is None:
            raise ValueError(
                f"sensor='diffractive' needs a pyramid stage, this one has {self.spec.wfs!r}"
            )
        return (
            DiffractiveSensor(
                self.wfs,
                self.calibration.recon,
                photons=self.photons,
                read_noise=self.spec.read_noise,
                gain_compensation=(
                    self.calibrated_gains if handling in ("calibrated", "two-pass") else None
                ),
            ),
            tracker,
        )


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything built for one case (see the module docstring).

    Parameters
    ----------
    case : Case
    pupil : Pupil
    stage1, stage2 : StageScene
    projection : ndarray, shape (n_modes2, n_modes1)
        Stage-1 modal coefficients to stage-2 ones, from the phase over the pupil
        (:func:`aocontrol.sim.loop.projection_matrix`, the cascade's own).
    r0 : float
        Fried parameter at 500 nm [m].
    layers : tuple of Layer
        The simulated profile, winds scaled to ``tau0``.
    quick : bool
    """

    case: Case
    pupil: Pupil
    stage1: StageScene
    stage2: StageScene
    projection: np.ndarray
    r0: float
    layers: tuple
    quick: bool = False

    def atmosphere(
        self, rng: np.random.Generator | int | None, fs: float | None = None
    ) -> Atmosphere:
        """A fresh atmosphere at the fast clock (stage 2's rate by default).

        Parameters
        ----------
        rng : numpy.random.Generator or int
            Seed of the phase screens.
        fs : float, optional
            Frame rate [Hz]; default stage 2's.
        """
        atm = self.case.atmosphere
        return eso_atmosphere(
            self.pupil,
            atm.seeing,
            atm.tau0,
            self.stage2.fs if fs is None else fs,
            n_layers=atm.simulated_layers,
            L0=atm.L0,
            rng=rng,
            dtype=np.float32,
        )

    def camera(self) -> ScienceCamera:
        """The science camera: perfect coronagraph at the case's science wavelength."""
        sci = self.case.science
        return ScienceCamera(self.pupil, wavelength=sci.wavelength, field_of_view=sci.field_of_view)

    def vibration_psd(self) -> VibrationPSD:
        """The case's vibration PSD (one mode), :class:`aocontrol.sim.vibration.VibrationPSD`.

        Raises
        ------
        ValueError
            If the case has no vibration.
        """
        vib = self.case.vibration
        if vib is None:
            raise ValueError(f"case {self.case.name!r} has no [vibration] table")
        return tilt_vibration_psd(
            [
                (f, z, r * 1e9)
                for f, z, r in zip(vib.frequencies, vib.dampings, vib.rms, strict=True)
            ]
        )

    def vibration_source(self, rng: np.random.Generator | int) -> TiltVibration:
        """The vibration as a phase source at the fast clock (FIR-filtered white noise).

        Parameters
        ----------
        rng : numpy.random.Generator or int
            Source of the white noise.
        """
        vib = self.case.vibration
        psd = self.vibration_psd()
        return TiltVibration(
            self.stage2.fs,
            self.stage2.basis,
            rng,
            psd=psd,
            mode=vib.modes[0],
            numtaps=vib.fir_taps,
        )

    def settings(self) -> dict:
        """JSON-serialisable description of what was built (sampling, modes, noise)."""
        return {
            "n_pix": self.pupil.n_pix,
            "quick": self.quick,
            "r0": self.r0,
            "layers": [
                {"altitude": lay.altitude, "fraction": lay.fraction, "wind_speed": lay.wind_speed}
                for lay in self.layers
            ],
            "stage1": _stage_settings(self.stage1),
            "stage2": _stage_settings(self.stage2),
        }


def _stage_settings(st: StageScene) -> dict:
    return {
        "n_modes": st.n_modes,
        "photons_per_frame": st.photons,
        "noise_rms_nm_median": float(np.median(st.noise_std)),
        "noise_rms_nm_tiptilt": [float(x) for x in st.noise_std[:2]],
        "optical_gain_median": float(np.median(st.calibrated_gains)),
    }


def clear_scene_cache() -> None:
    """Forget every cached scene (frees the calibrations)."""
    _CACHE.clear()
    _GEOMETRY_CACHE.clear()


def build_scene(
    case: str | Case,
    *,
    overrides: dict | None = None,
    quick: bool = False,
    cache: bool = True,
    rng: int = 0,
    progress: bool = False,
) -> Scene:
    """Build (or fetch from the in-memory cache) the scene of a case.

    Parameters
    ----------
    case : str or Case
        Case name, TOML path or :class:`Case`.
    overrides : dict, optional
        Case values replaced (:func:`aocontrol.study.cases.apply_overrides`).
    quick : bool
        At most :data:`QUICK_MODES` modes per stage (fast calibration for tests).
    cache : bool
        Reuse a scene built for the same case values and ``quick``.
    rng : int
        Seed of the residual screens of the optical-gain calibration (its
        ``"optical_gain_screens"`` stream, :mod:`aocontrol.study._seeds`).
    progress : bool
        When the calibrations must be built (neither in memory nor in the disk cache), a
        progress bar over their steps that says what is built and where it is cached (a
        full-scale case takes minutes the first time, a second or two from the cache).

    Returns
    -------
    Scene

    Raises
    ------
    CaseError, ValueError
        Invalid case or overrides.
    """
    c = apply_overrides(load_case(case), overrides)
    key = json.dumps([c.to_dict(), bool(quick), int(rng)], sort_keys=True, default=str)
    if cache and key in _CACHE:
        return _CACHE[key]
    geo = _geometry(c, bool(quick), int(rng), cache, progress)
    s1 = _stage_scene(c, c.stage1, c.star.G, geo["stage1"])
    s2 = _stage_scene(c, c.stage2, c.star.J, geo["stage2"])
    layers = tuple(
        scale_to_tau0(
            eso_median_profile(c.atmosphere.simulated_layers), geo["r0"], c.atmosphere.tau0
        )
    )
    scene = Scene(c, geo["pupil"], s1, s2, geo["projection"], geo["r0"], layers, bool(quick))
    logger.info("scene %s built: %s", c.name, scene.settings())
    if cache:
        _CACHE[key] = scene
    return scene


#: The model-error keys of a stage (:mod:`aocontrol.sim.model_errors`): settings of the run,
#: not of the calibration (the calibration is the nominal instrument's).
MODEL_ERROR_KEYS = (
    "latency_error",
    "optical_gain_error",
    "optical_gain_drift",
    "optical_gain_drift_period",
    "dm_time_constant",
    "dm_resonance",
    "dm_damping",
    "misregistration_shift_x",
    "misregistration_shift_y",
    "misregistration_rotation",
)


def _geometry_key(c: Case, quick: bool, rng: int) -> str:
    """The case values the calibrations depend on (not the flux, rates, gains or tau0; in quick
    mode the modes actually built, at most :data:`QUICK_MODES`)."""
    flux = ("fs", "band", "read_noise", "throughput", "gain", "latency_frames", "dm_stroke")
    flux += ("sensor", "optical_gain")
    flux += MODEL_ERROR_KEYS  # the run's instrument, not the calibration's
    stages = [
        {k: v for k, v in dataclasses.asdict(s).items() if k not in flux}
        for s in (c.stage1, c.stage2)
    ]
    if quick:  # the modes built (a case's n_modes above the quick limit changes nothing)
        for st, limit in zip(stages, QUICK_MODES, strict=True):
            st["n_modes"] = min(st["n_modes"], limit)
    atm = (c.atmosphere.seeing, c.atmosphere.L0)
    return json.dumps([dataclasses.asdict(c.simulation), atm, stages, quick, rng], default=str)


def geometry_cache_key(c: Case, quick: bool, rng: int = 0) -> str:
    """The disk-cache key of a case's calibrations (:mod:`aocontrol.study._cache`).

    Parameters
    ----------
    c : Case
    quick : bool
    rng : int
        As in :func:`build_scene`.

    Returns
    -------
    str
    """
    return "scene geometry " + _geometry_key(c, quick, rng)


def _geometry(c: Case, quick: bool, rng: int, cache: bool, progress: bool = False) -> dict:
    """Pupil, DMs, KL bases, projection and WFS calibrations (cached; see the module notes)."""
    key = _geometry_key(c, quick, rng)
    if cache and key in _GEOMETRY_CACHE:
        return _GEOMETRY_CACHE[key]
    if cache:  # the disk cache, shared by processes and later runs (aocontrol.study._cache)
        from aocontrol.study._cache import cache_dir

        where = cache_dir()
        note = f"once: cached in {where}" if where is not None else "the disk cache is off"
        out = disk_cached(
            geometry_cache_key(c, quick, rng),
            lambda: _build_geometry(c, quick, rng, _Steps(c.name, note, progress)),
        )
        _GEOMETRY_CACHE[key] = out
        return out
    return _build_geometry(c, quick, rng, _Steps(c.name, "not cached", progress))


class _Steps:
    """The calibration's progress: a bar over its steps (``progress``), and a log line each."""

    def __init__(self, name: str, note: str, progress: bool) -> None:
        self.name, self.note, self.progress, self.bar = name, note, progress, None

    def __call__(self, what: str, total: int) -> None:
        """Announce the next step ``what`` of ``total``."""
        logger.info("calibrating %s: %s", self.name, what)
        if not self.progress:
            return
        if self.bar is None:
            from tqdm.auto import tqdm

            self.bar = tqdm(
                total=total,
                desc=f"calibrating {self.name} ({self.note})",
                unit="step",
                bar_format="{desc}: {n_fmt}/{total_fmt} steps, {elapsed}{postfix}",
            )
        else:
            self.bar.update(1)
        self.bar.set_postfix_str(what)

    def close(self) -> None:
        """Complete and close the bar."""
        if self.bar is not None:
            self.bar.update(self.bar.total - self.bar.n)
            self.bar.set_postfix_str("done")
            self.bar.close()


def _build_geometry(c: Case, quick: bool, rng: int, steps: _Steps | None = None) -> dict:
    steps = steps or _Steps(c.name, "", False)
    try:
        return _calibrations(c, quick, rng, steps)
    finally:
        steps.close()


def _calibrations(c: Case, quick: bool, rng: int, steps: _Steps) -> dict:
    sim = c.simulation
    pupil = Pupil(diameter=sim.diameter, n_pix=sim.n_pix, obstruction=sim.obstruction)
    r0 = r0_from_seeing(c.atmosphere.seeing)
    n1, n2 = c.stage1.n_modes, c.stage2.n_modes
    if quick:
        n1, n2 = min(n1, QUICK_MODES[0]), min(n2, QUICK_MODES[1])
    total = 5
    steps("deformable mirrors", total)
    dm1 = DeformableMirror(pupil, n_actuators=c.stage1.n_actuators)
    dm2 = DeformableMirror(pupil, n_actuators=c.stage2.n_actuators)
    steps(f"KL bases ({n1} + {n2} modes)", total)
    b1 = kl_basis(dm1, n1, r0=r0, L0=c.atmosphere.L0)
    b2 = kl_basis(dm2, n2, r0=r0, L0=c.atmosphere.L0)
    # Residual no stage corrects: fitting error of the basis with more modes.
    finer = b1 if n1 >= n2 else b2
    fit_rms = math.sqrt(fitting_error(finer, r0, c.atmosphere.L0))
    cutoff = (max(c.stage1.n_actuators, c.stage2.n_actuators) - 1) / (2 * sim.diameter)
    gen = np.random.default_rng(seed_sequence(rng, "optical_gain_screens"))
    steps("projection between the stage bases", total)
    out = {"pupil": pupil, "r0": r0, "projection": projection_matrix(b1, b2)}
    for name, spec, dm, basis in (("stage1", c.stage1, dm1, b1), ("stage2", c.stage2, dm2, b2)):
        steps(
            f"{name} {spec.wfs} interaction matrix"
            + (" and optical gains" if spec.wfs == "pyramid" else ""),
            total,
        )
        if spec.wfs == "pyramid":
            wfs = PyramidWFS(
                pupil,
                spec.wavelength,
                n_subapertures=spec.n_subapertures,
                modulation=spec.modulation,
                n_modulation_points=spec.n_modulation_points,
            )
            screens = fitting_residual_screens(
                pupil, fit_rms, _OG_SCREENS, gen, cutoff_frequency=cutoff, L0=c.atmosphere.L0
            )
            # The "derivative" interaction matrices (exact linearisation) cost half the
            # push-pull ones; the optical gains are by definition the linear sensitivity
            # around the residual screens.
            model = calibrate(wfs, basis, _CAL_AMPLITUDE, method="derivative")
            og = optical_gains(
                wfs,
                basis,
                screens,
                amplitude=_CAL_AMPLITUDE,
                recon=model.recon,
                method="derivative",
            )
        else:
            model = shack_hartmann_calibration(
                pupil, spec.wavelength, spec.n_subapertures, basis, _CAL_AMPLITUDE
            )
            og = np.ones(basis.n_modes)
            wfs = None
        if not np.all(og > 0):
            raise ValueError(f"{spec.wfs} optical gains must be > 0, got min {og.min()!r}")
        out[name] = (dm, basis, model, np.asarray(og, dtype=float), wfs)
    return out


def _stage_scene(case: Case, spec: StageSpec, magnitude: float, geo: tuple) -> StageScene:
    dm, basis, model, og, wfs = geo
    photons = photons_per_frame(
        magnitude,
        spec.band,
        fs=spec.fs,
        diameter=case.simulation.diameter,
        obstruction=case.simulation.obstruction,
        throughput=spec.throughput,
    )
    raw = np.sqrt(model.noise_variance(photons, spec.read_noise))
    # Modal gain compensation in the reconstructor: unit gain, noise raw / og.
    sensor = LinearModalSensor.from_calibration(
        model, photons, spec.read_noise, optical_gain=og, compensate=True
    )
    return StageScene(
        spec=spec,
        dm=dm,
        basis=basis,
        plant=loop_plant(spec.fs, spec.latency_frames),
        photons=photons,
        sensor=sensor,
        calibrated_gains=og,
        raw_noise_std=raw,
        wfs=wfs,
        calibration=model,
    )
