"""Simulated runs written as AOT telemetry (ESO's Adaptive Optics Telemetry, through ``aotpy``).

:func:`write_run_aot` turns a :class:`~aocontrol.sim.loop.LoopResult` or a two-stage
:class:`~aocontrol.sim.loop.CascadeResult` into an AOT FITS file that another system (or
:func:`aocontrol.io.read_aot`) reads: one ``ControlLoop`` per stage, named after the stage,
with its frame rate, its delay (AOT's full delay, ``1 + latency_frames``), the modal
measurements in ``modal_coefficients`` [nm], the commands in ``commands`` [m] and the matrices
that map them to modes (``commands_to_modes``, ``modes_to_commands``), and the stage's
temporal filter when its controller is given (:func:`aocontrol.io.aot_time_filter`:
``aotpy``'s documented convention, stated in the images' ``TFCONV``). The modal commands are
the corrector's commands (one "actuator" per mode, 1 nm = 1e-9 m) unless a modes-to-actuators
matrix is given for the stage; then the commands are actuator commands and
``commands_to_modes`` its pseudo-inverse.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from aocontrol.controllers import ControllerBank
from aocontrol.io import aot_time_filter, write_system

__all__ = ["write_run_aot"]

# AOT commands are in metres; our modal telemetry is in nm.
_NM = 1e-9


def _stages(result: Any) -> list[tuple[str, Any]]:
    stages = getattr(result, "stages", None)
    if stages is None:
        return [(str(result.metadata.get("stage") or "stage"), result)]
    out = []
    for i, st in enumerate(stages, start=1):
        out.append((str(st.metadata.get("stage") or f"stage{i}"), st))
    names = [n for n, _ in out]
    if len(set(names)) != len(names):
        out = [(f"stage{i}", st) for i, (_, st) in enumerate(out, start=1)]
    return out


def write_run_aot(
    result: Any,
    path: str | os.PathLike,
    *,
    controllers: Mapping[str, ControllerBank] | None = None,
    modes_to_actuators: Mapping[str, np.ndarray] | None = None,
    name: str = "aocontrol simulation",
) -> str:
    """Write a simulated run's telemetry as an AOT FITS file, whole or not at all.

    Parameters
    ----------
    result : LoopResult or CascadeResult
        A run recorded with ``measurements`` and ``commands`` telemetry (``(n_frames,
        n_modes)`` [nm] per stage).
    path : str or os.PathLike
        Output ``.fits`` file.
    controllers : mapping of str to ControllerBank, optional
        Per stage name, the bank whose filters go into ``time_filter_num``/``_den``.
    modes_to_actuators : mapping of str to ndarray (n_act, n_modes), optional
        Per stage name, the DM's modes-to-actuators matrix [actuator m per modal m]: the
        commands are then written as actuator commands.
    name : str
        The AOT system's name.

    Returns
    -------
    str
        The path written.

    Raises
    ------
    ValueError
        A stage without measurements or commands telemetry, an unknown stage name in
        ``controllers``/``modes_to_actuators``, a matrix of the wrong shape.
    """
    import aotpy

    stages = _stages(result)
    names = [n for n, _ in stages]
    controllers = dict(controllers or {})
    m2a = dict(modes_to_actuators or {})
    for label, given in (("controllers", controllers), ("modes_to_actuators", m2a)):
        unknown = sorted(set(given) - set(names))
        if unknown:
            raise ValueError(f"{label} names stages {unknown}; the run has stages {names}")
    telescope = aotpy.MainTelescope("VLT", enclosing_diameter=8.0)
    system = aotpy.AOSystem(
        ao_mode="SCAO", name=name, main_telescope=telescope, config="written by aocontrol"
    )
    source = aotpy.NaturalGuideStar("NGS")
    system.sources.append(source)
    for stage_name, st in stages:
        tele = st.telemetry
        missing = [k for k in ("measurements", "commands") if k not in tele]
        if missing:
            raise ValueError(
                f"stage {stage_name!r} has no {missing} telemetry (record them in the run)"
            )
        meas = np.asarray(tele["measurements"], dtype=float)
        cmd = np.asarray(tele["commands"], dtype=float)
        n_frames, n_modes = meas.shape
        frames = aotpy.Time(f"{stage_name} FRAMES", frame_numbers=list(range(n_frames)))
        if stage_name in m2a:
            mat = np.asarray(m2a[stage_name], dtype=float)
            if mat.ndim != 2 or mat.shape[1] != n_modes:
                raise ValueError(
                    f"modes_to_actuators[{stage_name!r}] must have shape (n_act, {n_modes}), "
                    f"got {mat.shape}"
                )
            actuators = _NM * cmd @ mat.T
            to_modes = np.linalg.pinv(mat) / _NM
            to_commands = mat * _NM
        else:
            actuators = _NM * cmd
            to_modes = np.eye(n_modes) / _NM
            to_commands = np.eye(n_modes) * _NM
        sensor = aotpy.ShackHartmann(
            f"{stage_name} WFS",
            source=source,
            n_valid_subapertures=n_modes,
        )
        dm = aotpy.DeformableMirror(
            f"{stage_name} DM", telescope=telescope, n_valid_actuators=actuators.shape[1]
        )
        loop = aotpy.ControlLoop(
            stage_name,
            commanded_corrector=dm,
            input_sensor=sensor,
            time=frames,
            framerate=float(st.fs),
            delay=1.0 + float(st.metadata.get("latency_frames", np.nan)),
            commands=aotpy.Image(f"{stage_name} COMMANDS", actuators, unit="m", time=frames),
            modal_coefficients=aotpy.Image(
                f"{stage_name} MODAL_COEFFICIENTS", meas, unit="nm", time=frames
            ),
            commands_to_modes=aotpy.Image(f"{stage_name} COMMANDS_TO_MODES", to_modes),
            modes_to_commands=aotpy.Image(f"{stage_name} MODES_TO_COMMANDS", to_commands),
        )
        if stage_name in controllers:
            loop.time_filter_num, loop.time_filter_den = aot_time_filter(
                controllers[stage_name], stage_name
            )
        system.wavefront_sensors.append(sensor)
        system.wavefront_correctors.append(dm)
        system.loops.append(loop)
    return write_system(system, path)
