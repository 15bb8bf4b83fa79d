"""AOT (ESO's Adaptive Optics Telemetry, FITS) in the control layer, through ``aotpy``.

Reading a loop's telemetry (:func:`read_aot`); a loop's temporal filter is read and written
by :mod:`aocontrol.io._aot_filter`. The writer of simulated runs belongs to the simulator's
study layer (:func:`aocontrol.study.aot.write_run_aot`).

Conventions (AOT fields of an ``aotpy.ControlLoop``):

* Frame rate: ``loop.framerate`` [Hz], else the input sensor's ``detector.frame_rate``.
* Delay: AOT's ``loop.delay`` is the full loop delay [frames] from the mid-point of the WFS
  integration to the mid-point of the applied command. In :func:`aocontrol.plant.loop_plant`
  that is the one-frame WFS integration (half a frame) plus the RTC latency plus the held
  command (half a frame): ``delay = 1 + latency_frames``.
* Modal measurements (``(n_frames, n_modes)``): ``loop.modal_coefficients`` when present;
  else the sensor's ``measurements`` (``t x d x s_v`` slopes) projected with a given matrix,
  the loop's ``measurements_to_modes`` or its ``control_matrix`` (then the "modes" are the
  corrector's actuators: the reconstructed residual in command space, the control matrix
  holding no loop gain, as in ESO's SPARTA where the gain is in the temporal filter).
* Modal commands: the loop's ``commands`` (``t x a_v``) mapped with a given matrix or the
  loop's ``commands_to_modes`` (``m x a_v``), the pseudo-inverse of ``modes_to_commands``,
  or unchanged when the measurements were projected with the control matrix. Measurements
  and commands must end in the same unit (``pol = m + G u``): the matrices carry it.
* Units (:mod:`aocontrol._units`). AOT fixes ``commands`` in metres on the actuators (a
  ``BUNIT`` of the commands image overrides it); modal coefficients and matrices are in "user
  defined units", stated by their ``BUNIT`` or not at all. The unit of the modal telemetry is
  the measurements': ``modal_coefficients``' ``BUNIT``, or ``measurements_to_modes``' when it
  is a length, or the commands' (metres) for measurements projected with the control matrix
  (they are then actuator commands), or the ``unit`` the caller states. A length unit is
  converted to nm once, here (both ``m`` and ``u``: the project's convention, modal
  coefficients of 1 nm RMS), and :attr:`LoopTelemetry.unit` is ``"nm"``; any other unit is
  kept and named, and none stated gives ``unit=None`` (figures labelled ``"a.u."``, never
  nm). A ``unit`` that contradicts the file's is refused unless ``override_metadata``.
* Sign: ``u = K m`` with the residual ``d - u`` (:mod:`aocontrol.analysis`);
  ``command_sign=-1`` for a system whose commands enter with the other sign (e.g. an RTC
  whose temporal filter has a negative gain); :func:`aocontrol.synthesis.design_from_telemetry`
  refuses telemetry whose sign the data contradict
  (:func:`aocontrol.synthesis.check_loop_telemetry`).
* Metadata given by the caller (``latency_frames``, ``unit``) that contradicts the file's
  (``delay - 1``, the ``BUNIT``) is refused unless ``override_metadata=True``.
* Temporal filter (``time_filter_num``/``time_filter_den``): :mod:`aocontrol.io._aot_filter`
  (:func:`~aocontrol.io.read_aot_filter`, :func:`~aocontrol.io.write_aot_filter`), whose
  docstring states the convention and what the standard's text and ESO's files say.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

from aocontrol._atomic import atomic_path
from aocontrol._units import NM, nm_per_unit
from aocontrol.synthesis import LoopTelemetry

__all__ = [
    "AOT_COMMAND_UNIT",
    "AOTError",
    "aot_loops",
    "read_aot",
    "write_system",
]


#: The unit AOT fixes for a loop's ``commands`` (``aotpy``: "in m units"), used when the
#: commands image states none.
AOT_COMMAND_UNIT = "m"


class AOTError(ValueError):
    """An AOT file that cannot give what was asked: the message names the file, loop and field.

    Parameters
    ----------
    path : str
        The file.
    loop : str or None
        The loop (``uid``), if one was chosen.
    field : str or None
        The AOT field at fault (``framerate``, ``delay``, ``commands``...).
    reason : str
        What is wrong and what was expected.
    """

    def __init__(self, path: str, loop: str | None, field: str | None, reason: str) -> None:
        where = [f"AOT file {path!r}"]
        if loop is not None:
            where.append(f"loop {loop!r}")
        if field is not None:
            where.append(f"field {field!r}")
        super().__init__(", ".join(where) + ": " + reason)
        self.path, self.loop, self.field = path, loop, field


def _aotpy():
    import aotpy

    return aotpy


def _read_system(path: str):
    if not os.path.isfile(path):
        raise AOTError(path, None, None, "no such file")
    aotpy = _aotpy()
    try:
        return aotpy.AOSystem.read_from_file(path, file_type="fits")
    except Exception as exc:  # aotpy raises bare Exceptions on non-AOT FITS
        raise AOTError(path, None, None, f"not a readable AOT FITS file ({exc})") from exc


def aot_loops(path: str | os.PathLike) -> list[str]:
    """Names (``uid``) of the control loops of an AOT file, in file order.

    Parameters
    ----------
    path : str or os.PathLike
        AOT FITS file.

    Returns
    -------
    list of str
    """
    path = os.fspath(path)
    system = _read_system(path)
    return [lp.uid for lp in system.loops if type(lp).__name__ == "ControlLoop"]


def _loop(system, path: str, name: str | None):
    loops = [lp for lp in system.loops if type(lp).__name__ == "ControlLoop"]
    names = [lp.uid for lp in loops]
    if name is None:
        if len(loops) != 1:
            raise AOTError(
                path, None, "loops", f"{len(loops)} control loops {names}: choose one (--loop)"
            )
        return loops[0]
    for lp in loops:
        if lp.uid == name:
            return lp
    raise AOTError(path, name, "loops", f"no such control loop; the file has {names}")


def _image(img, path: str, loop: str, field: str, ndim: tuple[int, ...]) -> np.ndarray | None:
    if img is None:
        return None
    arr = np.asarray(img.data, dtype=float)  # native byte order (FITS is big-endian)
    if arr.ndim not in ndim:
        raise AOTError(path, loop, field, f"expected {ndim} dimensions, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise AOTError(path, loop, field, "contains NaN or inf")
    return arr


def _matrix(value: object, path: str, loop: str, field: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 3:
        arr = arr.reshape(arr.shape[0], -1)
    if arr.ndim != 2:
        raise AOTError(path, loop, field, f"expected a 2-D or 3-D matrix, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise AOTError(path, loop, field, "contains NaN or inf")
    return arr


def _project(mat: np.ndarray, data: np.ndarray, path: str, loop: str, names: tuple[str, str]):
    if mat.shape[1] != data.shape[1]:
        raise AOTError(
            path,
            loop,
            names[0],
            f"shape {mat.shape} cannot map {names[1]} of {data.shape[1]} values per frame "
            f"(expected {mat.shape[0]} x {data.shape[1]})",
        )
    return data @ mat.T


def _frame_rate(lp, path: str) -> float:
    fs = lp.framerate
    if fs is None:
        det = getattr(lp.input_sensor, "detector", None)
        fs = None if det is None else det.frame_rate
    if fs is None or not np.isfinite(fs) or fs <= 0:
        raise AOTError(
            path,
            lp.uid,
            "framerate",
            f"a loop rate > 0 [Hz] is required (neither the loop's framerate nor the sensor "
            f"detector's frame_rate gives one, got {fs!r})",
        )
    return float(fs)


def read_aot(
    path: str | os.PathLike,
    loop: str | None = None,
    *,
    projection: object = None,
    command_projection: object = None,
    command_sign: float = 1.0,
    latency_frames: float | None = None,
    skip_frames: int = 0,
    unit: str | None = None,
    override_metadata: bool = False,
) -> LoopTelemetry:
    """Modal closed-loop telemetry of one control loop of an AOT file.

    Parameters
    ----------
    path : str or os.PathLike
        AOT FITS file.
    loop : str, optional
        The control loop's ``uid``; required when the file has several.
    projection : array_like, shape (n_modes, d * s_v) or (n_modes, d, s_v), optional
        Slopes -> modes matrix, instead of the file's (module docstring).
    command_projection : array_like, shape (n_modes, a_v), optional
        Actuator commands -> modes, instead of the file's ``commands_to_modes``.
    command_sign : {1.0, -1.0}, default 1.0
        Multiplies the commands (see the sign convention).
    latency_frames : float, optional
        RTC latency beyond the WFS integration [frames]; default ``loop.delay - 1``. When the
        file has a delay, a different value is refused unless ``override_metadata``.
    skip_frames : int, default 0
        Frames dropped at the start (e.g. a start-up transient).
    unit : str, optional
        Unit of the modal telemetry when the file does not state it (module docstring:
        ``"m"``, ``"um"``, ``"nm"`` are converted to nm; another is kept as a label). When
        the file states one, a different unit is refused unless ``override_metadata``.
    override_metadata : bool, default False
        Let ``latency_frames`` and ``unit`` replace the file's values.

    Returns
    -------
    LoopTelemetry
        ``source`` is ``"path[loop]"``; ``unit`` is ``"nm"`` when the unit is a known length
        (values converted), else the unit stated (``None`` if none).

    Raises
    ------
    AOTError
        (a ``ValueError``) No such file or loop, several loops and none chosen, no frame
        rate, no delay (and no ``latency_frames``), a delay below one frame, no
        measurements or commands, mismatched frames or matrix sizes, non-finite data, a
        ``latency_frames`` or ``unit`` that contradicts the file; the message names the file,
        the loop and the field.
    """
    path = os.fspath(path)
    system = _read_system(path)
    lp = _loop(system, path, loop)
    name = lp.uid
    fs = _frame_rate(lp, path)
    delay_ok = lp.delay is not None and np.isfinite(lp.delay) and lp.delay >= 1.0
    if latency_frames is None:
        if lp.delay is None:
            raise AOTError(
                path, name, "delay", "the loop delay [frames] is missing; pass latency_frames"
            )
        if not delay_ok:
            raise AOTError(
                path,
                name,
                "delay",
                f"the full loop delay must be >= 1 frame (WFS integration + RTC latency, "
                f"mid-point to mid-point), got {lp.delay!r}; pass latency_frames",
            )
        latency_frames = float(lp.delay) - 1.0
    elif delay_ok and not override_metadata:
        file_latency = float(lp.delay) - 1.0
        if not np.isclose(float(latency_frames), file_latency, rtol=1e-9, atol=1e-9):
            raise AOTError(
                path,
                name,
                "delay",
                f"latency_frames={latency_frames!r} contradicts the file's delay of "
                f"{float(lp.delay):g} frames (latency {file_latency:g} frame beyond the WFS "
                "integration); pass override_metadata=True (CLI: --override-metadata) to use "
                "the given value",
            )
    if command_sign not in (1.0, -1.0):
        raise ValueError(f"command_sign must be 1.0 or -1.0, got {command_sign!r}")

    modal = _image(lp.modal_coefficients, path, name, "modal_coefficients", (2,))
    in_command_space = False
    command_unit = _unit_of(lp.commands) or AOT_COMMAND_UNIT
    if modal is not None and projection is None:
        m = modal
        file_unit = _unit_of(lp.modal_coefficients)
    else:
        sensor = lp.input_sensor
        slopes = _image(
            None if sensor is None else sensor.measurements,
            path,
            name,
            "measurements",
            (2, 3),
        )
        if slopes is None:
            raise AOTError(
                path,
                name,
                "measurements",
                "no modal_coefficients and no sensor measurements: nothing to design on",
            )
        slopes = slopes.reshape(slopes.shape[0], -1)
        if projection is not None:
            mat, field = _matrix(projection, path, name, "projection"), "projection"
            file_unit = None
        elif lp.measurements_to_modes is not None:
            field = "measurements_to_modes"
            mat = _matrix(lp.measurements_to_modes.data, path, name, field)
            file_unit = _unit_of(lp.measurements_to_modes)
            file_unit = file_unit if nm_per_unit(file_unit) else None
        elif lp.control_matrix is not None:
            field = "control_matrix"
            mat = _matrix(lp.control_matrix.data, path, name, field)
            in_command_space = True
            # Actuator commands reconstructed (no gain): in the commands' unit.
            file_unit = _unit_of(lp.control_matrix)
            file_unit = file_unit if nm_per_unit(file_unit) else command_unit
        else:
            raise AOTError(
                path,
                name,
                "control_matrix",
                "sensor measurements but no matrix to project them to modes "
                "(measurements_to_modes, control_matrix) and no projection given",
            )
        m = _project(mat, slopes, path, name, (field, "measurements"))

    cmd = _image(lp.commands, path, name, "commands", (2,))
    if cmd is None:
        raise AOTError(path, name, "commands", "the loop has no commands")
    if command_projection is not None:
        mat = _matrix(command_projection, path, name, "command_projection")
        u = _project(mat, cmd, path, name, ("command_projection", "commands"))
    elif in_command_space:
        u = cmd
    elif lp.commands_to_modes is not None:
        mat = _matrix(lp.commands_to_modes.data, path, name, "commands_to_modes")
        u = _project(mat, cmd, path, name, ("commands_to_modes", "commands"))
    elif lp.modes_to_commands is not None:
        mat = _matrix(lp.modes_to_commands.data, path, name, "modes_to_commands")
        u = _project(np.linalg.pinv(mat), cmd, path, name, ("modes_to_commands", "commands"))
    else:
        raise AOTError(
            path,
            name,
            "commands_to_modes",
            "commands are actuator commands and no matrix maps them to modes "
            "(commands_to_modes, modes_to_commands) and no command_projection given",
        )
    if m.shape != u.shape:
        raise AOTError(
            path,
            name,
            "commands",
            f"modal commands {u.shape} and modal measurements {m.shape} must have the same "
            "shape (n_frames, n_modes)",
        )
    if not 0 <= skip_frames < m.shape[0]:
        raise ValueError(f"skip_frames must be in [0, {m.shape[0]}), got {skip_frames!r}")
    chosen = _chosen_unit(path, name, file_unit, unit, override_metadata)
    factor = nm_per_unit(chosen)
    if factor is not None:
        m, u, chosen = m * factor, u * factor, NM
    return LoopTelemetry(
        m[skip_frames:],
        command_sign * u[skip_frames:],
        fs,
        latency_frames,
        source=f"{path}[{name}]",
        unit=chosen,
    )


def _unit_of(img) -> str | None:
    """An image's ``BUNIT`` (``None`` when absent or blank)."""
    unit = None if img is None else getattr(img, "unit", None)
    if unit is None or not str(unit).strip():
        return None
    return str(unit).strip()


def _same_unit(a: str, b: str) -> bool:
    fa, fb = nm_per_unit(a), nm_per_unit(b)
    if fa is not None and fb is not None:
        return fa == fb
    return a.strip().lower() == b.strip().lower()


def _chosen_unit(
    path: str, loop: str, file_unit: str | None, given: str | None, override: bool
) -> str | None:
    """The unit of the modal telemetry: the file's, or the caller's (module docstring)."""
    if given is None:
        return file_unit
    if not isinstance(given, str) or not given.strip():
        raise ValueError(f"unit must be a non-empty string such as 'nm' or 'm', got {given!r}")
    if file_unit is not None and not override and not _same_unit(given, file_unit):
        raise AOTError(
            path,
            loop,
            "unit",
            f"unit={given!r} contradicts the file's unit {file_unit!r} of the modal telemetry "
            "(AOT commands are in metres); pass override_metadata=True (CLI: "
            "--override-metadata) to use the given unit",
        )
    return given.strip()


def write_system(system: object, path: str | os.PathLike, **kwargs: Mapping) -> str:
    """Write an ``aotpy.AOSystem`` as AOT FITS, whole or not at all (:mod:`aocontrol._atomic`).

    Parameters
    ----------
    system : aotpy.AOSystem
        The system to write (with ``aotpy``'s own FITS writer).
    path : str or os.PathLike
        Output file.
    **kwargs
        Options of ``aotpy``'s writer.

    Returns
    -------
    str
        The path written.
    """
    path = os.fspath(path)
    with atomic_path(path, suffix=".fits") as tmp:
        system.write_to_file(tmp, file_type="fits", overwrite=True, **kwargs)
    return path
