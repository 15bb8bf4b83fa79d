"""Results of the simulator's loops: one stage (:class:`LoopResult`), a cascade
(:class:`CascadeResult`), and the divergence error."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aocontrol._atomic import atomic_path
from aocontrol._deprecation import declare, deprecated_call
from aocontrol.analysis import welch_psd

__all__ = ["TELEMETRY", "LoopDivergedError", "LoopResult", "CascadeResult"]

#: Telemetry that can be recorded, each ``(n_frames, n_modes)`` float32 [nm].
TELEMETRY = ("disturbance", "measurements", "commands", "dm", "residuals")


class LoopDivergedError(RuntimeError):
    """The closed loop diverged: raised with the stage, the frame and the modes concerned.

    Parameters
    ----------
    frame : int
        Frame (of the stage's own rate) at which the divergence was detected.
    modes : array_like of int
        Modes whose residual diverged.
    stage : str, optional
        Name of the stage (``Stage.name``).
    reason : str, optional
        What was detected (default: the residual exceeded 1e3 x the disturbance).
    """

    def __init__(
        self,
        frame: int,
        modes: np.ndarray,
        stage: str | None = None,
        reason: str | None = None,
    ) -> None:
        self.frame = int(frame)
        self.modes = np.asarray(modes, dtype=int)
        self.stage = stage
        shown = self.modes[:10].tolist()
        more = "" if self.modes.size <= 10 else f" (+{self.modes.size - 10} more)"
        where = "" if stage is None else f" in stage {stage!r}"
        what = reason or "exceeds 1e3 x the disturbance"
        super().__init__(
            f"closed loop diverged{where} at frame {self.frame}: residual of modes "
            f"{shown}{more} {what}; the controller is probably unstable for these "
            "modes (check aocontrol.analysis.is_stable)"
        )


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return str(obj)


_NPZ = (
    "aocontrol.sim.LoopResult.save and CascadeResult.save",
    ".npz results files",
    "write HDF5 with aocontrol.study.results.save_result(result, path, settings=...); convert "
    "existing .npz files with aocontrol.study.results.convert_npz(npz_path, h5_path)",
)
declare(*_NPZ)


def _warn_npz_writer() -> None:
    deprecated_call(*_NPZ, stacklevel=4)


def _atomic_savez(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` to ``path`` (.npz) atomically (:func:`aocontrol._atomic.atomic_path`)."""
    with atomic_path(path, suffix=".npz.tmp") as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)


@dataclass(frozen=True)
class LoopResult:
    """Result of one closed-loop stage.

    Parameters
    ----------
    fs : float
        Loop rate [Hz] (the stage's own rate).
    n_frames : int
        Frames of the stage's own rate.
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
        Frames in which each DM actuator was clipped (with an actuator stroke,
        ``stage.dm.actuator_stroke``).
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
        bin).

        Parameters
        ----------
        name : str
            Recorded telemetry name.
        nperseg : int
            Welch segment length [frames].

        Returns
        -------
        freqs : ndarray (n_f,)
            Frequencies [Hz].
        psd : ndarray (n_modes, n_f)
            One-sided PSD [nm^2/Hz].
        """
        if name not in self.telemetry:
            raise KeyError(f"{name!r} was not recorded; recorded: {sorted(self.telemetry)}")
        x = np.asarray(self.telemetry[name][self.settle_frames :], dtype=float)
        return welch_psd(x, self.fs, nperseg)

    def _arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        arrays = {f"{prefix}telemetry/{k}": v for k, v in self.telemetry.items()}
        arrays[f"{prefix}residual_variance"] = self.residual_variance
        arrays[f"{prefix}disturbance_variance"] = self.disturbance_variance
        arrays[f"{prefix}saturation"] = self.saturation
        if self.actuator_saturation is not None:
            arrays[f"{prefix}actuator_saturation"] = self.actuator_saturation
        return arrays

    def _meta(self) -> dict:
        science = None
        if self.science is not None and hasattr(self.science, "to_dict"):
            science = self.science.to_dict()
        elif isinstance(self.science, dict):
            science = self.science
        return dict(
            fs=self.fs,
            n_frames=self.n_frames,
            settle_frames=self.settle_frames,
            metadata=self.metadata,
            science=science,
        )

    def save(self, path: str | os.PathLike) -> None:
        """Write the result to ``path`` (.npz: arrays + JSON metadata), atomically. Deprecated.

        Results are HDF5 files (``aocontrol.study.results.save_result``, opened by xarray);
        this older form stays readable (:meth:`load`, ``aocontrol.study.results.load_result``) and
        convertible (``aocontrol.study.results.convert_npz``).

        Parameters
        ----------
        path : str or os.PathLike
            Target file; a temporary file in the same directory is renamed onto it, so a
            failure leaves no partial file.

        Warns
        -----
        DeprecationWarning
            Always, pointing to ``save_result`` and ``convert_npz``.
        """
        _warn_npz_writer()
        arrays = self._arrays()
        arrays["meta_json"] = np.array(json.dumps(self._meta(), default=_json_default))
        _atomic_savez(path, arrays)

    @classmethod
    def _from(cls, data: Any, meta: dict, prefix: str = "") -> LoopResult:
        tele_key = f"{prefix}telemetry/"
        tele = {k[len(tele_key) :]: data[k] for k in data.files if k.startswith(tele_key)}
        act = f"{prefix}actuator_saturation"
        return cls(
            fs=meta["fs"],
            n_frames=meta["n_frames"],
            telemetry=tele,
            residual_variance=data[f"{prefix}residual_variance"],
            disturbance_variance=data[f"{prefix}disturbance_variance"],
            saturation=data[f"{prefix}saturation"],
            settle_frames=meta["settle_frames"],
            science=meta["science"],
            metadata=meta["metadata"],
            actuator_saturation=data[act] if act in data.files else None,
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> LoopResult:
        """Read a result written by :meth:`save` (science as a plain dict).

        Parameters
        ----------
        path : str or os.PathLike
            File written by :meth:`save`.

        Returns
        -------
        LoopResult
        """
        with np.load(os.fspath(path), allow_pickle=False) as data:
            meta = json.loads(str(data["meta_json"]))
            return cls._from(data, meta)


@dataclass(frozen=True)
class CascadeResult:
    """Result of a two-stage cascade (:func:`aocontrol.sim.loop.run_cascade`).

    Parameters
    ----------
    scheme : str
        ``"standalone"`` or ``"dcao"``.
    stages : tuple of (LoopResult, LoopResult)
        Stage 1 at its own rate and in its own modes: telemetry per stage-1 frame, the
        disturbance and residual being the means over the stage-1 frame (what its WFS
        integrates), ``residual_variance`` and ``disturbance_variance`` the mean squares over
        the fast frames after settling (the residual stage 2 receives). Stage 2 at the fast
        rate in its modes: ``disturbance`` is its input (``d2 - P y1`` in standalone, the
        full ``d2`` in dCAO), ``dm`` its DM shape (``delay(u2) - P y1`` in dCAO),
        ``commands`` the controller output ``u2``, ``residuals`` ``d2 - P y1 - dm``.
    science : object or None
        Science-camera result after both stages.
    metadata : dict
        Settings of the run (JSON-serialisable).
    fs : float
        Fast clock (stage 2's rate) [Hz].
    """

    scheme: str
    stages: tuple
    science: Any
    metadata: dict
    fs: float

    def __post_init__(self) -> None:
        if self.scheme not in ("standalone", "dcao"):
            raise ValueError(f"scheme must be 'standalone' or 'dcao', got {self.scheme!r}")
        if len(self.stages) != 2 or not all(isinstance(s, LoopResult) for s in self.stages):
            raise TypeError("stages must be a tuple of two LoopResult")

    @property
    def stage1(self) -> LoopResult:
        """Stage 1's result (its own rate and modes)."""
        return self.stages[0]

    @property
    def stage2(self) -> LoopResult:
        """Stage 2's result (fast rate, its modes)."""
        return self.stages[1]

    @property
    def rate_ratio(self) -> int:
        """``fs2 / fs1``."""
        return int(round(self.stages[1].fs / self.stages[0].fs))

    @property
    def final_residual_variance(self) -> np.ndarray:
        """Residual variance after both stages in stage-2 modes, shape (n_modes2,) [nm^2]."""
        return self.stages[1].residual_variance

    @property
    def residual_rms(self) -> float:
        """Total residual RMS after both stages in stage-2 modes [nm]."""
        return self.stages[1].residual_rms

    def save(self, path: str | os.PathLike) -> None:
        """Write both stages and the settings to ``path`` (.npz), atomically. Deprecated.

        As :meth:`LoopResult.save`: use ``aocontrol.study.results.save_result`` (HDF5).

        Parameters
        ----------
        path : str or os.PathLike
            Target file (a failure leaves no partial file).

        Warns
        -----
        DeprecationWarning
            Always, pointing to ``save_result`` and ``convert_npz``.
        """
        _warn_npz_writer()
        arrays: dict[str, np.ndarray] = {}
        metas = []
        for i, st in enumerate(self.stages):
            arrays.update(st._arrays(f"stage{i + 1}/"))
            metas.append(st._meta())
        science = None
        if self.science is not None and hasattr(self.science, "to_dict"):
            science = self.science.to_dict()
        elif isinstance(self.science, dict):
            science = self.science
        meta = dict(
            scheme=self.scheme, fs=self.fs, metadata=self.metadata, science=science, stages=metas
        )
        arrays["meta_json"] = np.array(json.dumps(meta, default=_json_default))
        _atomic_savez(path, arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> CascadeResult:
        """Read a result written by :meth:`save` (science results as plain dicts).

        Parameters
        ----------
        path : str or os.PathLike
            File written by :meth:`save`.

        Returns
        -------
        CascadeResult
        """
        with np.load(os.fspath(path), allow_pickle=False) as data:
            meta = json.loads(str(data["meta_json"]))
            stages = tuple(
                LoopResult._from(data, m, f"stage{i + 1}/") for i, m in enumerate(meta["stages"])
            )
        return cls(
            scheme=meta["scheme"],
            stages=stages,
            science=meta["science"],
            metadata=meta["metadata"],
            fs=meta["fs"],
        )
