"""Results files: one self-describing HDF5 (netCDF-4) file per run.

Layout (netCDF-4 through h5netcdf, so ``xarray.open_dataset(path, engine="h5netcdf")`` opens
it with named dimensions and ``units``, and plain h5py reads it as ordinary HDF5)::

    /  attrs   format = "aocontrol-result", format_version, kind = "loop" | "cascade",
               software versions, created (UTC), settings_json (the run's settings, JSON) and
               the same settings flattened to scalars (``case.name``, ``seed``, ...: COMPASS's
               convention of parameters as root attributes), figures of merit (``strehl``,
               ``mean_contrast_4_6``, ``residual_rms_nm``)
       one loop: the loop variables below at the root
       cascade:  attrs scheme, fs; the camera's science variables at the root;
                 groups ``stage1`` and ``stage2`` with the loop variables of each stage

    loop variables (dimensions ``mode``, ``frequency``, ``radius``, ``frame``, ``actuator``):
      mode (mode)                          KL mode index
      residual_variance (mode)             nm^2, after the settling frames
      disturbance_variance (mode)          nm^2
      saturation (mode)                    frames in which the mode's command was clipped
      actuator_saturation (actuator)       frames (only with a DM stroke per actuator)
      frequency (frequency)                Hz
      residual_psd, disturbance_psd (mode, frequency)   nm^2/Hz, one-sided (Welch, density)
      frame (frame)                        frame index (whenever the run recorded telemetry)
      residual_rms, disturbance_rms (frame)  nm, float32: each frame's modal RMS (square
                                           root of the sum over modes), settling included
      telemetry_<name> (frame, mode)       nm, float32, only with ``telemetry=True``
      radius (radius), contrast_profile (radius), strehl, mean_contrast_4_6   (science)
    attrs: fs [Hz], n_frames, settle_frames, residual_rms_nm, metadata_json

PSDs need the residual/disturbance telemetry of the run (recorded by default by
:func:`aocontrol.sim.run_loop`); they are computed when the file is written, so a file without
telemetry still holds them. Files are written atomically (temporary name in the same folder,
flush + fsync, :func:`os.replace`): a file with the final name is always complete.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
from collections.abc import Iterable, Mapping
from typing import Any

import h5netcdf
import h5py
import numpy as np

from aocontrol._atomic import atomic_path
from aocontrol._version import __version__
from aocontrol.sim import CascadeResult, LoopResult, ScienceResult

__all__ = [
    "save_result",
    "load_result",
    "convert_npz",
    "read_psds",
    "read_settings",
    "summary_table",
    "flatten_settings",
]

logger = logging.getLogger(__name__)

#: ``format`` root attribute of a results file.
RESULT_FORMAT = "aocontrol-result"
#: Layout version of results files (bumped on incompatible changes).
RESULT_FORMAT_VERSION = 1
#: Telemetry PSD segment length [frames] (reduced for short runs).
PSD_NPERSEG = 1024
# Root attributes written by this module; flattened settings with these names are prefixed.
_RESERVED = {
    "format",
    "format_version",
    "kind",
    "software_version",
    "numpy_version",
    "h5py_version",
    "created",
    "settings_json",
    "metadata_json",
    "strehl",
    "mean_contrast_4_6",
    "residual_rms_nm",
    "scheme",
    "fs",
    "n_frames",
    "settle_frames",
}
_PSD_SOURCES = {"residuals": "residual_psd", "disturbance": "disturbance_psd"}
# Per-frame RMS series written whenever the run recorded the telemetry (dimension ``frame``,
# a few kB per second of run, against ``n_modes`` times that for the telemetry itself).
_RMS_SERIES = {"residuals": "residual_rms", "disturbance": "disturbance_rms"}
# Fields of the result types that the file layout stores (a test checks them against the
# dataclasses, so a new field cannot be silently lost by a round trip).
_LOOP_FIELDS = frozenset(
    {
        "fs",
        "n_frames",
        "telemetry",
        "residual_variance",
        "disturbance_variance",
        "saturation",
        "settle_frames",
        "science",
        "metadata",
        "actuator_saturation",
    }
)
_CASCADE_FIELDS = frozenset({"scheme", "stages", "science", "metadata", "fs"})


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if hasattr(obj, "to_dict"):
        return obj.to_dict()
    return str(obj)


def _dumps(obj: Any) -> str:
    return json.dumps(obj, default=_json_default, sort_keys=True)


def flatten_settings(settings: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Flatten nested settings to ``{"a.b.c": scalar}`` (root attributes of a results file).

    Parameters
    ----------
    settings : mapping
        JSON-able settings (nested dicts, lists, numbers, strings, booleans, None).
    prefix : str
        Prefix of every key (used in the recursion).

    Returns
    -------
    dict
        Scalars only: int, float and str kept, booleans as int 0/1 (netCDF has no boolean
        attribute), numeric lists as float arrays, other lists as JSON strings, None dropped.
    """
    out: dict[str, Any] = {}
    for key, value in settings.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten_settings(value, prefix=name + "."))
        elif value is None:
            continue
        elif isinstance(value, (bool, np.bool_)):
            out[name] = int(bool(value))
        elif isinstance(value, (int, float, str, np.integer, np.floating)):
            out[name] = value.item() if isinstance(value, np.generic) else value
        else:
            arr = np.asarray(value) if isinstance(value, (list, tuple, np.ndarray)) else None
            if arr is not None and arr.ndim == 1 and arr.size and arr.dtype.kind in "iuf":
                out[name] = arr.astype(float)
            else:
                out[name] = _dumps(value)
    return out


def _write_variable(
    group: Any, name: str, dims: tuple[str, ...], data: Any, units: str | None, **attrs: Any
) -> None:
    """Write one variable (the single writer of every dataset of a results file)."""
    data = np.asarray(data)
    var = group.create_variable(name, dims, data.dtype, data=data)
    if units is not None:
        var.attrs["units"] = units
    for key, value in attrs.items():
        var.attrs[key] = value


def _science(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return ScienceResult.from_dict(dict(obj))
    return obj


def _write_science(group: Any, science: Any) -> None:
    sci = _science(science)
    if sci is None:
        return
    group.dimensions["radius"] = sci.radii_ld.size
    _write_variable(
        group,
        "radius",
        ("radius",),
        sci.radii_ld,
        "lambda/D",
        long_name="mean separation of the annulus",
    )
    _write_variable(
        group,
        "contrast_profile",
        ("radius",),
        sci.contrast_profile,
        "1",
        long_name="azimuthal mean raw contrast (star peak = 1)",
    )
    _write_variable(group, "strehl", (), sci.strehl, "1", long_name="long-exposure Strehl ratio")
    _write_variable(
        group,
        "mean_contrast_4_6",
        (),
        sci.mean_contrast_4_6,
        "1",
        long_name="mean raw contrast over 4-6 lambda/D",
    )
    _write_variable(
        group,
        "mean_contrast_1_2",
        (),
        sci.mean_contrast_1_2,
        "1",
        long_name="mean raw contrast over 1-2 lambda/D",
    )
    group.attrs["science_n_frames"] = sci.n_frames
    group.attrs["science_wavelength_m"] = sci.wavelength
    group.attrs["science_coronagraph"] = int(sci.coronagraph)


def _read_science(group: h5py.Group) -> ScienceResult | None:
    if "contrast_profile" not in group:
        return None
    return ScienceResult(
        strehl=float(group["strehl"][()]),
        mean_contrast_4_6=float(group["mean_contrast_4_6"][()]),
        mean_contrast_1_2=(
            float(group["mean_contrast_1_2"][()]) if "mean_contrast_1_2" in group else np.nan
        ),
        radii_ld=group["radius"][()],
        contrast_profile=group["contrast_profile"][()],
        n_frames=int(_attr(group, "science_n_frames")),
        wavelength=float(_attr(group, "science_wavelength_m")),
        coronagraph=bool(_attr(group, "science_coronagraph")),
    )


def _write_loop(group: Any, loop: LoopResult, *, telemetry: bool) -> None:
    n_modes = int(np.asarray(loop.residual_variance).size)
    group.attrs["fs"] = float(loop.fs)
    group.attrs["n_frames"] = int(loop.n_frames)
    group.attrs["settle_frames"] = int(loop.settle_frames)
    group.attrs["residual_rms_nm"] = float(loop.residual_rms)
    group.attrs["metadata_json"] = _dumps(loop.metadata)
    group.dimensions["mode"] = n_modes
    _write_variable(group, "mode", ("mode",), np.arange(n_modes), None, long_name="KL mode index")
    _write_variable(group, "residual_variance", ("mode",), loop.residual_variance, "nm^2")
    _write_variable(group, "disturbance_variance", ("mode",), loop.disturbance_variance, "nm^2")
    _write_variable(
        group,
        "saturation",
        ("mode",),
        loop.saturation,
        "frames",
        long_name="frames with the mode's command clipped",
    )
    if loop.actuator_saturation is not None:
        group.dimensions["actuator"] = int(np.asarray(loop.actuator_saturation).size)
        _write_variable(
            group,
            "actuator_saturation",
            ("actuator",),
            loop.actuator_saturation,
            "frames",
            long_name="frames with the actuator clipped",
        )
    have = [k for k in _PSD_SOURCES if k in loop.telemetry]
    if have and loop.n_frames - loop.settle_frames >= 2:
        freqs = None
        for key in have:
            f, p = loop.psd(key, nperseg=PSD_NPERSEG)
            if freqs is None:
                freqs = f
                group.dimensions["frequency"] = f.size
                _write_variable(group, "frequency", ("frequency",), f, "Hz")
            _write_variable(
                group,
                _PSD_SOURCES[key],
                ("mode", "frequency"),
                p,
                "nm^2/Hz",
                long_name=f"one-sided Welch PSD of the {key} after settling",
            )
    series = {k: v for k, v in _RMS_SERIES.items() if k in loop.telemetry}
    if series or (telemetry and loop.telemetry):
        group.dimensions["frame"] = int(loop.n_frames)
        _write_variable(
            group,
            "frame",
            ("frame",),
            np.arange(loop.n_frames),
            None,
            long_name=f"frame index (frame period {1.0 / loop.fs:.6g} s)",
        )
        for key, name in series.items():
            x = np.asarray(loop.telemetry[key], dtype=float)
            _write_variable(
                group,
                name,
                ("frame",),
                np.sqrt(np.sum(x * x, axis=1)).astype(np.float32),
                "nm",
                long_name=f"RMS of the modal {key} of each frame (square root of the sum "
                "over modes), settling frames included",
            )
    if telemetry and loop.telemetry:
        for key, value in loop.telemetry.items():
            _write_variable(group, f"telemetry_{key}", ("frame", "mode"), value, "nm")
    _write_science(group, loop.science)


def _read_loop(group: h5py.Group) -> LoopResult:
    tele = {
        name[len("telemetry_") :]: group[name][()]
        for name in group
        if name.startswith("telemetry_")
    }
    return LoopResult(
        fs=float(_attr(group, "fs")),
        n_frames=int(_attr(group, "n_frames")),
        telemetry=tele,
        residual_variance=group["residual_variance"][()],
        disturbance_variance=group["disturbance_variance"][()],
        saturation=group["saturation"][()],
        settle_frames=int(_attr(group, "settle_frames")),
        science=_read_science(group),
        metadata=json.loads(_attr(group, "metadata_json")),
        actuator_saturation=(
            group["actuator_saturation"][()] if "actuator_saturation" in group else None
        ),
    )


def _plain(value: Any) -> Any:
    """An attribute as a Python scalar (netCDF stores scalars as 1-element arrays)."""
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.reshape(()).item()
    if isinstance(value, np.generic):
        value = value.item()
    return value.decode() if isinstance(value, bytes) else value


def _attr(group: h5py.Group, name: str) -> Any:
    return _plain(group.attrs[name])


def _figures(result: Any) -> dict[str, float]:
    """Figures of merit of a run: Strehl, mean contrast 4-6 lambda/D, residual RMS [nm]."""
    stages = getattr(result, "stages", None)
    last = stages[-1] if stages is not None else result
    out = {"residual_rms_nm": float(last.residual_rms)}
    sci = _science(result.science)
    if sci is not None:
        out["strehl"] = float(sci.strehl)
        out["mean_contrast_4_6"] = float(sci.mean_contrast_4_6)
    return out


def save_result(
    result: Any,
    path: str | os.PathLike,
    *,
    settings: Mapping[str, Any] | None = None,
    telemetry: bool = False,
) -> str:
    """Write a run's result to one self-describing HDF5 file, atomically.

    Parameters
    ----------
    result : LoopResult or CascadeResult
        A single-stage result, or a cascade (``scheme``, ``stages`` (stage 1, stage 2),
        ``science``, ``metadata``, ``fs``): one group per stage.
    path : str or os.PathLike
        Output file (``.h5`` by convention). Its folder must exist.
    settings : mapping, optional
        The run's settings (case, controllers with their parameters, seeds, ...), JSON-able.
        Stored as ``settings_json`` and flattened to root attributes. Default: the result's
        ``metadata``.
    telemetry : bool
        Also store the recorded telemetry ``(n_frames, n_modes)`` float32 [nm] of each stage.

    Returns
    -------
    str
        ``path``.

    Raises
    ------
    TypeError
        If ``result`` is neither a loop nor a cascade result.
    """

    cascade = isinstance(result, CascadeResult)
    if not cascade and not isinstance(result, LoopResult):
        raise TypeError(
            f"result must be a LoopResult or a CascadeResult, got {type(result).__name__}"
        )
    if settings is None:
        settings = dict(result.metadata)
    settings_json = _dumps(settings)
    path = os.fspath(path)
    with atomic_path(path) as tmp:
        with h5netcdf.File(tmp, "w") as fh:
            fh.attrs["format"] = RESULT_FORMAT
            fh.attrs["format_version"] = RESULT_FORMAT_VERSION
            fh.attrs["kind"] = "cascade" if cascade else "loop"
            fh.attrs["software_version"] = __version__
            fh.attrs["numpy_version"] = np.__version__
            fh.attrs["h5py_version"] = h5py.__version__
            fh.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
            fh.attrs["settings_json"] = settings_json
            for key, value in flatten_settings(json.loads(settings_json)).items():
                fh.attrs[f"settings.{key}" if key in _RESERVED else key] = value
            for key, value in _figures(result).items():
                fh.attrs[key] = value
            if cascade:
                fh.attrs["scheme"] = str(result.scheme)
                fh.attrs["fs"] = float(result.fs)
                fh.attrs["metadata_json"] = _dumps(result.metadata)
                for i, stage in enumerate(result.stages, start=1):
                    _write_loop(fh.create_group(f"stage{i}"), stage, telemetry=telemetry)
                _write_science(fh, result.science)
            else:
                _write_loop(fh, result, telemetry=telemetry)
    logger.info("result written to %s", path)
    return path


def _open_checked(path: str) -> h5py.File:
    try:
        fh = h5py.File(path, "r")
    except OSError as exc:
        raise OSError(f"path {path!r} is not a readable HDF5 file: {exc}") from exc
    fmt = _plain(fh.attrs.get("format"))
    if fmt != RESULT_FORMAT:
        fh.close()
        raise ValueError(
            f"path {path!r} is not an aocontrol results file (format attribute {fmt!r}, "
            f"expected {RESULT_FORMAT!r})"
        )
    version = int(_attr(fh, "format_version"))
    if version > RESULT_FORMAT_VERSION:
        fh.close()
        raise ValueError(
            f"path {path!r} has results format_version {version}; this aocontrol reads "
            f"<= {RESULT_FORMAT_VERSION}"
        )
    return fh


def _load_npz(path: str) -> LoopResult:
    res = LoopResult.load(path)
    if isinstance(res.science, Mapping):
        res = LoopResult(
            fs=res.fs,
            n_frames=res.n_frames,
            telemetry=res.telemetry,
            residual_variance=res.residual_variance,
            disturbance_variance=res.disturbance_variance,
            saturation=res.saturation,
            settle_frames=res.settle_frames,
            science=_science(res.science),
            metadata=res.metadata,
            actuator_saturation=res.actuator_saturation,
        )
    return res


def load_result(path: str | os.PathLike) -> Any:
    """Read a result written by :func:`save_result` (or a legacy ``.npz`` + JSON result).

    Parameters
    ----------
    path : str or os.PathLike
        Results file (``.h5``), or a ``.npz`` written by :meth:`LoopResult.save`.

    Returns
    -------
    LoopResult or CascadeResult
        The result with the saved arrays (telemetry empty unless it was saved) and its
        science as a :class:`~aocontrol.sim.ScienceResult`.

    Raises
    ------
    ValueError
        If the file is not an aocontrol results file.
    OSError
        If the file cannot be read.
    """
    path = os.fspath(path)
    if path.endswith(".npz"):
        return _load_npz(path)
    with _open_checked(path) as fh:
        if _attr(fh, "kind") == "loop":
            return _read_loop(fh)
        return CascadeResult(
            scheme=_attr(fh, "scheme"),
            stages=(_read_loop(fh["stage1"]), _read_loop(fh["stage2"])),
            science=_read_science(fh),
            metadata=json.loads(_attr(fh, "metadata_json")),
            fs=float(_attr(fh, "fs")),
        )


def read_settings(path: str | os.PathLike) -> dict:
    """The settings stored with a run (the ``settings_json`` root attribute), as a dict.

    Parameters
    ----------
    path : str or os.PathLike
        Results file.

    Returns
    -------
    dict
        The ``settings`` given to :func:`save_result` (JSON round trip: tuples as lists).
    """
    with _open_checked(os.fspath(path)) as fh:
        return json.loads(_attr(fh, "settings_json"))


def read_psds(
    path: str | os.PathLike, stage: str | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Residual and disturbance PSDs stored in a results file.

    Parameters
    ----------
    path : str or os.PathLike
        Results file.
    stage : str, optional
        ``"stage1"`` or ``"stage2"`` for a cascade (default: the last stage; ignored for a
        single loop).

    Returns
    -------
    freqs : ndarray, shape (n_freqs,)
        [Hz].
    psds : dict of str -> ndarray (n_modes, n_freqs)
        ``"residuals"`` and/or ``"disturbance"``, one-sided [nm^2/Hz]; empty if the run
        recorded neither.
    """
    with _open_checked(os.fspath(path)) as fh:
        group = fh
        if _attr(fh, "kind") == "cascade":
            name = stage or "stage2"
            if name not in fh:
                raise ValueError(f"stage must be 'stage1' or 'stage2', got {stage!r}")
            group = fh[name]
        if "frequency" not in group:
            return np.zeros(0), {}
        psds = {k: group[v][()] for k, v in _PSD_SOURCES.items() if v in group}
        return group["frequency"][()], psds


def convert_npz(
    path_npz: str | os.PathLike,
    path_h5: str | os.PathLike,
    *,
    settings: Mapping[str, Any] | None = None,
    telemetry: bool = True,
) -> str:
    """Convert a legacy ``.npz`` + JSON result (:meth:`LoopResult.save`) to a results file.

    Parameters
    ----------
    path_npz : str or os.PathLike
        Legacy result.
    path_h5 : str or os.PathLike
        New results file (written atomically).
    settings : mapping, optional
        Settings to store (default: the legacy file's metadata).
    telemetry : bool
        Keep the legacy file's telemetry (default True: nothing is lost).

    Returns
    -------
    str
        ``path_h5``.
    """
    res = _load_npz(os.fspath(path_npz))
    return save_result(res, path_h5, settings=settings, telemetry=telemetry)


def summary_table(paths: Iterable[str | os.PathLike]) -> list[dict[str, Any]]:
    """One row per results file, rebuilt from the files' root attributes (no array is read).

    Parameters
    ----------
    paths : iterable of str or os.PathLike
        Results files.

    Returns
    -------
    list of dict
        In the order of ``paths``: ``path``, ``kind``, every flattened setting (``case.name``,
        ``seed``, ...) and the figures of merit ``strehl``, ``mean_contrast_4_6``,
        ``residual_rms_nm`` (missing when the run had no science camera). Numeric-array
        settings are left out of the rows.
    """
    skip = {"format", "format_version", "settings_json", "metadata_json"}
    rows = []
    for p in paths:
        p = os.fspath(p)
        with _open_checked(p) as fh:
            row: dict[str, Any] = {"path": p}
            for key, value in fh.attrs.items():
                if key in skip:
                    continue
                value = _plain(value)
                if isinstance(value, np.ndarray):
                    continue
                row[key] = value
            rows.append(row)
    return rows
