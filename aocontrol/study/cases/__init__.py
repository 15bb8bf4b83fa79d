"""Science cases as data: one TOML file per case, loaded and validated into frozen dataclasses.

The shipped cases (``data/*.toml``) are the five science cases of the SAXO+ paper (Dinis et
al., "Science cases results": ``bright1-best``, ``bright1-worst``, ``red1-fast``,
``red3-medium``, ``red5-best``) and its ``vibration`` case (bright 1 best plus a tilt
vibration). Every value carries a comment in its file naming its source.

File format
-----------
Tables ``[atmosphere]``, ``[star]``, ``[stage1]``, ``[stage2]``, ``[science]``,
``[simulation]`` and, optionally, ``[vibration]``; a top-level ``base = "<case>"`` inherits a
shipped case (tables merged key by key). Dimensional values are strings with a unit, e.g.
``tau0 = "9 ms"``, ``fs = "3 kHz"``, ``wavelength = "1.04 um"``, ``seeing = "0.4 arcsec"``;
they are stored in canonical units: seconds, hertz, metres, arcseconds. Dimensionless values
(magnitudes, mode counts, gains, latencies in frames, read noise in e-, throughputs) are plain
numbers. Loading fails, naming the file, the key and the reason (:class:`CaseError`), for
unknown or missing keys, wrong types or units, non-physical values (negative seeing or
``tau0``, a rate <= 0), a stage-2 rate that is not an integer multiple of stage 1's, or more
modes than the stage's DM has (valid actuators of :class:`aocontrol.sim.dm.DeformableMirror`
minus piston).

A drifting atmosphere (:mod:`aocontrol.sim.drift`) is named by an optional sub-table
``[atmosphere.drift]`` with ``kind = "step"`` (keys ``at``, ``seeing``, ``wind``,
``direction``), ``"ramp"`` (``start``, ``stop``, ``seeing``, ``wind``, ``direction``) or
``"stochastic"`` (``duration``, ``seed``, optional ``knot_interval``, ``seeing_timescale``,
``seeing_rms_change_1h``, ``wind_timescale``, ``wind_log_sigma``) or ``"knots"``: the history
itself, any number of knots, ``times`` (an array of times with a unit) and, one value per knot,
``seeing``, ``wind`` and ``direction`` (arrays; missing ones hold 1, 1 and 0), linear between
knots, two knots at one time make a step. E.g. a wind ramp to twice the speed between 10 and
20 s and a seeing step to 1.5 times at 40 s::

    [atmosphere.drift]
    kind = "knots"
    times = ["10 s", "20 s", "40 s", "40 s"]
    wind = [1.0, 2.0, 2.0, 2.0]
    seeing = [1.0, 1.0, 1.0, 1.5]

``seeing`` and ``wind`` are factors on the case's values (> 0 and >= 0), ``direction`` an
offset in degrees, times with a unit (``at = "20 s"``). Negative factors or times, ``stop <
start``, decreasing knot times, arrays of another length than ``times`` and unknown keys are
refused naming the key.
"""

from __future__ import annotations

import copy
import decimal
import math
import os
import re
import sys
from collections.abc import Callable
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 (declared dependency tomli)
    import tomli as tomllib

from aocontrol.study.cases._specs import (  # noqa: F401 - re-exported
    AtmosphereSpec,
    Case,
    CaseError,
    DriftSpec,
    ScienceSpec,
    SimulationSpec,
    StageSpec,
    StarSpec,
    VibrationSpec,
)

__all__ = [
    "AtmosphereSpec",
    "DriftSpec",
    "Case",
    "CaseError",
    "ScienceSpec",
    "SimulationSpec",
    "StageSpec",
    "SENSORS",
    "OPTICAL_GAIN_SETTINGS",
    "StarSpec",
    "VibrationSpec",
    "apply_overrides",
    "case_path",
    "list_cases",
    "load_case",
]

# Canonical unit of each dimension and the accepted spellings (factor to the canonical unit).
# Factors are decimal strings so that "9 ms" gives exactly float("0.009").
_UNITS: dict[str, tuple[str, dict[str, str]]] = {
    "time": ("s", {"s": "1", "ms": "1e-3", "us": "1e-6"}),
    "frequency": ("Hz", {"Hz": "1", "kHz": "1e3"}),
    "length": ("m", {"m": "1", "mm": "1e-3", "um": "1e-6", "nm": "1e-9"}),
    "angle": ("arcsec", {"arcsec": "1", "mas": "1e-3"}),
}
_QUANTITY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z]+)\s*$")


# ------------------------------------------------------------------------- schema
# Each key: (kind, required). kinds: "q:<dimension>", "int", "float", "str", "bool",
# "list:float", "list:int", "list:q:<dimension>".
_SCHEMA: dict[str, dict[str, tuple[str, bool]]] = {
    "atmosphere": {
        "seeing": ("q:angle", True),
        "tau0": ("q:time", True),
        "L0": ("q:length", True),
        "profile": ("str", True),
        "n_layers": ("int", True),
        "simulated_layers": ("int", True),
    },
    "atmosphere.drift": {
        "kind": ("str", True),
        "seeing": ("float", False),
        "wind": ("float", False),
        "direction": ("float", False),
        "at": ("q:time", False),
        "start": ("q:time", False),
        "stop": ("q:time", False),
        "duration": ("q:time", False),
        "seed": ("int", False),
        "knot_interval": ("q:time", False),
        "seeing_timescale": ("q:time", False),
        "seeing_rms_change_1h": ("q:angle", False),
        "wind_timescale": ("q:time", False),
        "wind_log_sigma": ("float", False),
    },
    "star": {"G": ("float", True), "J": ("float", True)},
    "stage1": {},
    "stage2": {},
    "science": {
        "wavelength": ("q:length", True),
        "exposure": ("q:time", True),
        "startup": ("q:time", True),
        "science_every": ("int", True),
        "field_of_view": ("float", True),
        "coronagraph": ("str", True),
    },
    "simulation": {
        "n_pix": ("int", True),
        "diameter": ("q:length", True),
        "obstruction": ("float", True),
    },
    "vibration": {
        "modes": ("list:int", True),
        "frequencies": ("list:q:frequency", True),
        "dampings": ("list:float", True),
        "rms": ("list:q:length", True),
        "fir_taps": ("int", False),
    },
}
_STAGE_SCHEMA: dict[str, tuple[str, bool]] = {
    "fs": ("q:frequency", True),
    "n_modes": ("int", True),
    "wavelength": ("q:length", True),
    "latency_frames": ("float", True),
    "n_actuators": ("int", True),
    "wfs": ("str", True),
    "n_subapertures": ("int", True),
    "band": ("str", True),
    "read_noise": ("float", True),
    "throughput": ("float", True),
    "gain": ("float", True),
    "dm_stroke": ("q:length", False),
    "modulation": ("float", False),
    "n_modulation_points": ("int", False),
    "pixels_per_subaperture": ("int", False),
    "pixel_scale": ("q:angle", False),
    "sensor": ("str", False),
    "optical_gain": ("str", False),
    # Model errors (aocontrol.sim.model_errors): the instrument against the design's model.
    "latency_error": ("float", False),
    "optical_gain_error": ("float", False),
    "optical_gain_drift": ("float", False),
    "optical_gain_drift_period": ("q:time", False),
    "dm_time_constant": ("q:time", False),
    "dm_resonance": ("q:frequency", False),
    "dm_damping": ("float", False),
    "misregistration_shift_x": ("float", False),
    "misregistration_shift_y": ("float", False),
    "misregistration_rotation": ("float", False),
}
#: Sensors in the loop and optical-gain settings of a stage (keys ``sensor``, ``optical_gain``).
SENSORS = ("linear", "diffractive")
OPTICAL_GAIN_SETTINGS = ("none", "calibrated", "tracked", "two-pass")
_SCHEMA["stage1"] = _STAGE_SCHEMA
_SCHEMA["stage2"] = _STAGE_SCHEMA
_TOP = {"name", "title", "base", "description"}
_REQUIRED_TABLES = ("atmosphere", "star", "stage1", "stage2", "science", "simulation")
# Plausible ranges in canonical units: a value outside is almost surely a wrong unit or a typo.
_RANGES: dict[str, tuple[float, float]] = {
    "atmosphere.seeing": (0.0, 5.0),
    "atmosphere.tau0": (0.0, 0.2),
    "atmosphere.L0": (1.0, 1000.0),
    "science.wavelength": (0.3e-6, 5e-6),
    "stage.wavelength": (0.3e-6, 5e-6),
    "stage.fs": (0.0, 1e5),
    "stage.dm_stroke": (0.0, 1e-4),
    "science.exposure": (0.0, 3600.0),
    "science.startup": (0.0, 3600.0),
    "vibration.frequencies": (0.0, 1e4),
    "vibration.rms": (0.0, 1e-5),
}
_WFS = ("shack-hartmann", "pyramid")
_BANDS = ("G", "J", "H", "I", "R", "V")


def _parse_quantity(source: str, key: str, value: Any, dim: str) -> float:
    unit, table = _UNITS[dim]
    if isinstance(value, bool) or not isinstance(value, str):
        raise CaseError(
            source,
            key,
            f"expected a {dim} with a unit as a string, e.g. '1 {unit}' (units "
            f"{sorted(table)}), got {value!r}",
        )
    m = _QUANTITY.match(value)
    if not m:
        raise CaseError(source, key, f"expected '<number> <unit>' for a {dim}, got {value!r}")
    number, u = m.group(1), m.group(2)
    if u not in table:
        raise CaseError(
            source, key, f"wrong unit {u!r} for a {dim}: expected one of {sorted(table)}"
        )
    return float(decimal.Decimal(number) * decimal.Decimal(table[u]))


def _parse_value(source: str, key: str, value: Any, kind: str) -> Any:
    if kind.startswith("list:"):
        if not isinstance(value, list) or not value:
            raise CaseError(source, key, f"expected a non-empty array, got {value!r}")
        return tuple(_parse_value(source, f"{key}[{i}]", v, kind[5:]) for i, v in enumerate(value))
    if kind.startswith("q:"):
        return _parse_quantity(source, key, value, kind[2:])
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise CaseError(source, key, f"expected an integer, got {value!r}")
        return value
    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CaseError(source, key, f"expected a number, got {value!r}")
        if not math.isfinite(value):
            raise CaseError(source, key, f"expected a finite number, got {value!r}")
        return float(value)
    if kind == "str":
        if not isinstance(value, str):
            raise CaseError(source, key, f"expected a string, got {value!r}")
        return value
    raise AssertionError(kind)  # pragma: no cover


def _check_range(source: str, key: str, value: float, rkey: str) -> None:
    if rkey in _RANGES:
        lo, hi = _RANGES[rkey]
        values = value if isinstance(value, tuple) else (value,)
        for v in values:
            if not (lo < v <= hi):
                raise CaseError(
                    source,
                    key,
                    f"must be in ({lo:g}, {hi:g}] in canonical units, got {v:g}: a "
                    "non-physical value or a wrong unit",
                )


def _parse_table(
    source: str, name: str, table: Any, schema: dict[str, tuple[str, bool]] | None = None
) -> dict[str, Any]:
    if not isinstance(table, dict):
        raise CaseError(source, name, f"expected a table [{name}], got {table!r}")
    schema = _SCHEMA[name] if schema is None else schema
    unknown = sorted(set(table) - set(schema))
    if unknown:
        raise CaseError(
            source, f"{name}.{unknown[0]}", f"unknown key; valid keys: {sorted(schema)}"
        )
    out = {}
    for key, (kind, required) in schema.items():
        dotted = f"{name}.{key}"
        if key not in table:
            if required:
                raise CaseError(source, dotted, "missing required key")
            continue
        value = _parse_value(source, dotted, table[key], kind)
        rkey = f"stage.{key}" if name.startswith("stage") else dotted
        _check_range(source, dotted, value, rkey)
        out[key] = value
    return out


@lru_cache(maxsize=64)
def _valid_actuators(n_actuators: int, diameter: float, obstruction: float) -> int:
    """Valid actuators of the DM (geometric criterion, independent of the sampling)."""
    from aocontrol.sim.dm import DeformableMirror
    from aocontrol.sim.pupil import Pupil

    pupil = Pupil(n_pix=2 * (n_actuators - 1), diameter=diameter, obstruction=obstruction)
    return DeformableMirror(pupil, n_actuators=n_actuators).n_act


def _stage(source: str, name: str, t: dict[str, Any], sim: dict[str, Any]) -> StageSpec:
    def bad(key: str, reason: str) -> CaseError:
        return CaseError(source, f"{name}.{key}", reason)

    for key in ("n_modes", "n_actuators", "n_subapertures"):
        if t[key] < 1:
            raise bad(key, f"must be >= 1, got {t[key]}")
    if t["latency_frames"] < 0:
        raise bad("latency_frames", f"must be >= 0 frames, got {t['latency_frames']}")
    if t["wfs"] not in _WFS:
        raise bad("wfs", f"must be one of {list(_WFS)}, got {t['wfs']!r}")
    if t["band"] not in _BANDS:
        raise bad("band", f"must be one of {list(_BANDS)}, got {t['band']!r}")
    if t["read_noise"] < 0:
        raise bad("read_noise", f"must be >= 0 e-, got {t['read_noise']}")
    if not 0 < t["throughput"] <= 1:
        raise bad("throughput", f"must be in (0, 1], got {t['throughput']}")
    if not 0 < t["gain"] < 2:
        raise bad("gain", f"must be in (0, 2), got {t['gain']}")
    if t.get("sensor", "linear") not in SENSORS:
        raise bad("sensor", f"must be one of {list(SENSORS)}, got {t['sensor']!r}")
    if t.get("sensor") == "diffractive" and t["wfs"] != "pyramid":
        raise bad(
            "sensor",
            f"'diffractive' needs a pyramid WFS (this stage has {t['wfs']!r}: the "
            "Shack-Hartmann stays a linear modal model)",
        )
    if t.get("optical_gain", "calibrated") not in OPTICAL_GAIN_SETTINGS:
        raise bad(
            "optical_gain",
            f"must be one of {list(OPTICAL_GAIN_SETTINGS)}, got {t['optical_gain']!r}",
        )
    _check_model_errors(t, bad)
    if t["wfs"] == "pyramid":
        for key in ("modulation", "n_modulation_points"):
            if key not in t:
                raise bad(key, "missing required key for a pyramid WFS")
        if t["modulation"] < 0 or t["n_modulation_points"] < 1:
            raise bad("modulation", "needs modulation >= 0 and n_modulation_points >= 1")
    else:
        for key in ("pixels_per_subaperture", "pixel_scale"):
            if key not in t:
                raise bad(key, "missing required key for a Shack-Hartmann WFS")
        if t["pixels_per_subaperture"] < 2 or t["pixel_scale"] <= 0:
            raise bad("pixels_per_subaperture", "needs >= 2 pixels of a pixel_scale > 0")
    n_act = _valid_actuators(t["n_actuators"], sim["diameter"], sim["obstruction"])
    if t["n_modes"] > n_act - 1:
        raise bad(
            "n_modes",
            f"{t['n_modes']} modes exceed the DM's {n_act - 1} piston-free directions "
            f"({n_act} valid actuators for n_actuators={t['n_actuators']})",
        )
    if 2 * (t["n_actuators"] - 1) > sim["n_pix"]:
        raise CaseError(
            source,
            "simulation.n_pix",
            f"{sim['n_pix']} samples are too coarse for {name}'s {t['n_actuators']}-actuator "
            f"DM: need >= {2 * (t['n_actuators'] - 1)} (2 per pitch)",
        )
    return StageSpec(**t)


def _check_model_errors(t: dict[str, Any], bad: Callable[[str, str], CaseError]) -> None:
    """The model-error keys of a stage (``aocontrol.sim.model_errors``), each against its
    physical range."""
    if "latency_error" in t:
        err = t["latency_error"]
        if not -t["latency_frames"] <= err <= 5.0:
            raise bad(
                "latency_error",
                f"must be in [-latency_frames, 5] = [{-t['latency_frames']:g}, 5] frames (the "
                f"true latency latency_frames + latency_error >= 0), got {err:g}",
            )
    if t.get("optical_gain_error", 1.0) <= 0:
        raise bad("optical_gain_error", f"must be > 0 (true / compensated), got "
                  f"{t['optical_gain_error']:g}")  # fmt: skip
    if not 0 <= t.get("optical_gain_drift", 0.0) < 1:
        raise bad("optical_gain_drift", f"must be in [0, 1), got {t['optical_gain_drift']:g}")
    if t.get("optical_gain_drift_period", 1.0) <= 0:
        raise bad("optical_gain_drift_period", "must be > 0 s")
    if t.get("dm_time_constant", 0.0) < 0:
        raise bad("dm_time_constant", f"must be >= 0 s, got {t['dm_time_constant']:g}")
    if "dm_resonance" in t and not 0 < t["dm_resonance"] < t["fs"] / 2:
        raise bad(
            "dm_resonance",
            f"must be in (0, fs/2) = (0, {t['fs'] / 2:g}) Hz, got {t['dm_resonance']:g}",
        )
    if not 0 < t.get("dm_damping", 0.1) < 1:
        raise bad("dm_damping", f"must be in (0, 1), got {t['dm_damping']:g}")
    for key in ("misregistration_shift_x", "misregistration_shift_y"):
        if abs(t.get(key, 0.0)) > 2.0:
            raise bad(key, f"must be within +-2 subapertures, got {t[key]:g}")
    if abs(t.get("misregistration_rotation", 0.0)) > 45.0:
        raise bad("misregistration_rotation", "must be within +-45 deg")


def _build(source: str, data: dict[str, Any]) -> Case:
    tables_ok = set(_SCHEMA) - {"atmosphere.drift"}  # a sub-table, not a top-level one
    unknown = sorted(set(data) - _TOP - tables_ok)
    if unknown:
        raise CaseError(source, unknown[0], f"unknown key; valid: {sorted(_TOP | tables_ok)}")
    for key in ("name", "title"):
        if key not in data:
            raise CaseError(source, key, "missing required key")
        if not isinstance(data[key], str):
            raise CaseError(source, key, f"expected a string, got {data[key]!r}")
    for table in _REQUIRED_TABLES:
        if table not in data:
            raise CaseError(source, table, f"missing required table [{table}]")
    tables = dict(data)
    drift_table = None
    if isinstance(data["atmosphere"], dict) and "drift" in data["atmosphere"]:
        tables["atmosphere"] = {k: v for k, v in data["atmosphere"].items() if k != "drift"}
        drift_table = data["atmosphere"]["drift"]
    parsed = {name: _parse_table(source, name, tables[name]) for name in _REQUIRED_TABLES}
    atm, sim, sci = parsed["atmosphere"], parsed["simulation"], parsed["science"]
    if drift_table is not None:
        atm["drift"] = _drift(source, drift_table)
    if not 1 <= atm["simulated_layers"] <= atm["n_layers"]:
        raise CaseError(
            source,
            "atmosphere.simulated_layers",
            f"must be in [1, n_layers={atm['n_layers']}], got {atm['simulated_layers']}",
        )
    if atm["profile"] != "eso-median":
        raise CaseError(
            source, "atmosphere.profile", f"must be 'eso-median', got {atm['profile']!r}"
        )
    if not 0 <= sim["obstruction"] < 1:
        raise CaseError(source, "simulation.obstruction", "must be in [0, 1)")
    if sim["n_pix"] < 8:
        raise CaseError(source, "simulation.n_pix", f"must be >= 8, got {sim['n_pix']}")
    if sci["science_every"] < 1:
        raise CaseError(source, "science.science_every", "must be >= 1")
    if sci["coronagraph"] != "perfect":
        raise CaseError(source, "science.coronagraph", "must be 'perfect'")
    if not 0 < sci["field_of_view"] <= sim["n_pix"] / 2:
        raise CaseError(
            source,
            "science.field_of_view",
            f"must be in (0, n_pix/2 = {sim['n_pix'] / 2}] lambda/D, got {sci['field_of_view']}",
        )
    s1 = _stage(source, "stage1", parsed["stage1"], sim)
    s2 = _stage(source, "stage2", parsed["stage2"], sim)
    ratio = s2.fs / s1.fs
    if abs(ratio - round(ratio)) > 1e-9 * ratio or round(ratio) < 1:
        raise CaseError(
            source,
            "stage2.fs",
            f"stage-2 rate {s2.fs:g} Hz must be an integer multiple of stage 1's "
            f"{s1.fs:g} Hz (ratio {ratio:g})",
        )
    vib = None
    if "vibration" in data:
        v = _parse_table(source, "vibration", data["vibration"])
        n = len(v["frequencies"])
        if len(v["dampings"]) != n or len(v["rms"]) != n:
            raise CaseError(
                source, "vibration.dampings", "frequencies, dampings and rms need one entry each"
            )
        if any(not 0 < d < 1 for d in v["dampings"]):
            raise CaseError(source, "vibration.dampings", "each damping must be in (0, 1)")
        if len(v["modes"]) != 1:
            raise CaseError(source, "vibration.modes", "one mode expected (e.g. [1], tilt)")
        if any(m < 0 or m >= s2.n_modes for m in v["modes"]):
            raise CaseError(source, "vibration.modes", f"modes must be in [0, {s2.n_modes})")
        if v.get("fir_taps", 8) < 8:
            raise CaseError(source, "vibration.fir_taps", "must be >= 8")
        if max(v["frequencies"]) >= s2.fs / 2:
            raise CaseError(source, "vibration.frequencies", "must be below stage 2's Nyquist")
        vib = VibrationSpec(**v)
    return Case(
        name=data["name"],
        title=data["title"],
        source=source,
        atmosphere=AtmosphereSpec(**atm),
        star=StarSpec(**parsed["star"]),
        stage1=s1,
        stage2=s2,
        science=ScienceSpec(**sci),
        simulation=SimulationSpec(**sim),
        vibration=vib,
        raw=data,
    )


# Keys each drift kind requires and accepts (beyond "kind").
_DRIFT_KINDS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "step": (("at",), ("at", "seeing", "wind", "direction")),
    "ramp": (("start", "stop"), ("start", "stop", "seeing", "wind", "direction")),
    "stochastic": (
        ("duration", "seed"),
        (
            "duration",
            "seed",
            "knot_interval",
            "seeing_timescale",
            "seeing_rms_change_1h",
            "wind_timescale",
            "wind_log_sigma",
        ),
    ),
}


# The "knots" drift: the piecewise-linear history itself (aocontrol.sim.drift.Drift), one value
# per knot; any number of knots, two at one time make a step.
_DRIFT_KNOTS_SCHEMA: dict[str, tuple[str, bool]] = {
    "kind": ("str", True),
    "times": ("list:q:time", True),
    "seeing": ("list:float", False),
    "wind": ("list:float", False),
    "direction": ("list:float", False),
}


def _drift_knots(source: str, table: dict) -> DriftSpec:
    """Parse and check a ``kind = "knots"`` drift."""
    d = _parse_table(source, "atmosphere.drift", table, _DRIFT_KNOTS_SCHEMA)
    times = d["times"]

    def bad(key: str, reason: str) -> CaseError:
        return CaseError(source, f"atmosphere.drift.{key}", reason)

    if any(t < 0 for t in times):
        raise bad("times", f"must be >= 0 s, got {[f'{t:g} s' for t in times]}")
    if any(b < a for a, b in zip(times[:-1], times[1:], strict=True)):
        raise bad(
            "times",
            f"must be non-decreasing (two equal times make a step), got "
            f"{[f'{t:g} s' for t in times]}",
        )
    for key in ("seeing", "wind", "direction"):
        if key in d and len(d[key]) != len(times):
            raise bad(key, f"must have one value per knot ({len(times)} times), got {len(d[key])}")
    if any(v <= 0 for v in d.get("seeing", ())):
        raise bad("seeing", f"must be factors > 0 on the case's seeing, got {list(d['seeing'])}")
    if any(v < 0 for v in d.get("wind", ())):
        raise bad("wind", f"must be factors >= 0 on the case's wind speeds, got {list(d['wind'])}")
    n = len(times)
    return DriftSpec(
        kind="knots",
        times=tuple(times),
        seeing=d.get("seeing", (1.0,) * n),
        wind=d.get("wind", (1.0,) * n),
        direction=d.get("direction", (0.0,) * n),
    )


def _drift(source: str, table: Any) -> DriftSpec:
    """Parse and check ``[atmosphere.drift]``."""
    if isinstance(table, dict) and table.get("kind") == "knots":
        return _drift_knots(source, table)
    d = _parse_table(source, "atmosphere.drift", table)
    kind = d["kind"]
    if kind not in _DRIFT_KINDS:
        raise CaseError(
            source,
            "atmosphere.drift.kind",
            f"must be one of {sorted([*_DRIFT_KINDS, 'knots'])}, got {kind!r}",
        )
    required, allowed = _DRIFT_KINDS[kind]
    for key in d:
        if key != "kind" and key not in allowed:
            raise CaseError(
                source,
                f"atmosphere.drift.{key}",
                f"not a key of a {kind!r} drift; valid keys: {sorted(allowed)}",
            )
    for key in required:
        if key not in d:
            raise CaseError(source, f"atmosphere.drift.{key}", f"missing for a {kind!r} drift")

    def bad(key: str, reason: str) -> CaseError:
        return CaseError(source, f"atmosphere.drift.{key}", reason)

    if d.get("seeing", 1.0) <= 0:
        raise bad("seeing", f"must be a factor > 0 on the case's seeing, got {d['seeing']}")
    if d.get("wind", 1.0) < 0:
        raise bad("wind", f"must be a factor >= 0 on the case's wind speeds, got {d['wind']}")
    for key in ("at", "start", "stop"):
        if d.get(key, 0.0) < 0:
            raise bad(key, f"must be >= 0 s, got {d[key]:g} s")
    for key in ("duration", "knot_interval", "seeing_timescale", "wind_timescale"):
        if key in d and d[key] <= 0:
            raise bad(key, f"must be > 0 s, got {d[key]:g} s")
    for key in ("seeing_rms_change_1h", "wind_log_sigma"):
        if d.get(key, 0.0) < 0:
            raise bad(key, f"must be >= 0, got {d[key]:g}")
    if kind == "ramp" and d["stop"] < d["start"]:
        raise bad("stop", f"must be >= start = {d['start']:g} s, got {d['stop']:g} s")
    return DriftSpec(**d)


def _data_dir() -> Path:
    return Path(str(resources.files(__name__).joinpath("data")))


def list_cases() -> list[str]:
    """Names of the shipped cases, sorted.

    Returns
    -------
    list of str
        E.g. ``["bright1-best", ..., "vibration"]``.
    """
    return sorted(p.stem for p in _data_dir().glob("*.toml"))


def case_path(name: str) -> Path:
    """Path of the shipped case ``name``.

    Parameters
    ----------
    name : str
        One of :func:`list_cases`.

    Raises
    ------
    ValueError
        Unknown name (the message lists the shipped ones).
    """
    path = _data_dir() / f"{name}.toml"
    if not path.is_file():
        raise ValueError(f"unknown case {name!r}; shipped cases: {list_cases()}")
    return path


def _merge(base: dict, top: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _read(path: Path, seen: tuple[str, ...] = ()) -> dict:
    source = str(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise CaseError(source, "<file>", f"invalid TOML: {exc}") from None
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise CaseError(source, "base", f"expected a case name, got {base!r}")
    if base in seen:
        raise CaseError(source, "base", f"circular inheritance through {base!r}")
    try:
        base_path = case_path(base)
    except ValueError as exc:
        raise CaseError(source, "base", str(exc)) from None
    return _merge(_read(base_path, (*seen, base)), data)


def load_case(name_or_path: str | os.PathLike | Case) -> Case:
    """Load and validate a case: a shipped name (:func:`list_cases`) or a TOML file path.

    Parameters
    ----------
    name_or_path : str, path-like or Case
        A shipped case name, a path to a ``.toml`` file, or a :class:`Case` (returned as is).

    Returns
    -------
    Case

    Raises
    ------
    CaseError
        Invalid file: the message names the file, the key and the reason.
    ValueError
        Unknown case name (lists the shipped ones) or missing file.
    """
    if isinstance(name_or_path, Case):
        return name_or_path
    text = os.fspath(name_or_path)
    path = Path(text)
    if not (text.endswith(".toml") or path.is_file()):
        path = case_path(text)
    if not path.is_file():
        raise ValueError(f"case file {text!r} does not exist")
    return _build(str(path), _read(path))


def _resolve_key(raw: dict, key: str) -> tuple[str, str]:
    if "." in key:
        table, sub = key.split(".", 1)
        return table, sub
    hits = [t for t in _SCHEMA if key in _SCHEMA[t] and t in raw]
    if len(hits) != 1:
        raise CaseError(
            "overrides",
            key,
            f"ambiguous or unknown key (found in {hits}); use 'table.key', e.g. 'stage2.fs'",
        )
    return hits[0], key


def apply_overrides(case: Case, overrides: dict | None) -> Case:
    """A new case with some values replaced, validated like a file.

    Parameters
    ----------
    case : Case
    overrides : dict
        ``{"table.key": value}`` (or a bare key found in one table only, e.g. ``"seeing"``).
        Dimensional values: a unit string (``"5 ms"``) or a number in canonical units (s, Hz,
        m, arcsec).

    Returns
    -------
    Case

    Raises
    ------
    CaseError
        Unknown key or invalid value (``source`` is ``"overrides"``).
    """
    if not overrides:
        return case
    raw = copy.deepcopy(case.raw)
    for key, value in overrides.items():
        table, sub = _resolve_key(raw, str(key))
        if table not in _SCHEMA or sub not in _SCHEMA[table]:
            raise CaseError("overrides", key, "unknown key")
        kind = _SCHEMA[table][sub][0]
        if kind.startswith("q:") and not isinstance(value, str) and not isinstance(value, bool):
            value = f"{value!r} {_UNITS[kind[2:]][0]}"
        raw.setdefault(table, {})[sub] = value
    try:
        return _build(f"{case.source} + overrides", raw)
    except CaseError as exc:
        raise CaseError("overrides", exc.key, exc.reason) from None
