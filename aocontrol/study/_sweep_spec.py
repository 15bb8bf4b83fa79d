"""Sweep specs: the validated cases x controllers x schemes x overrides x seeds, and run hashes.

See :mod:`aocontrol.study.sweep` for the file format and the execution.
"""

from __future__ import annotations

import difflib
import hashlib
import itertools
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["SPEC_KEYS", "SweepRun", "SweepSpec", "SweepSpecError", "run_hash"]

#: Keys of a sweep spec file.
SPEC_KEYS = ("cases", "controllers", "schemes", "seeds", "seconds", "quick", "overrides")
_HASH_LEN = 16
_NAME_KEYS = {"cases": "cases", "controllers": "controllers", "schemes": "schemes"}


class SweepSpecError(ValueError):
    """A sweep spec that cannot run: names the file, the key and what was expected."""


def _canonical(value: Any) -> Any:
    """JSON-ready copy of ``value`` with integral floats as ints (stable hashing)."""
    if isinstance(value, Mapping):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_canonical(v) for v in value]
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def run_hash(settings: Mapping[str, Any]) -> str:
    """Stable name of a run: first 16 hex digits of the SHA-256 of its sorted, compact JSON.

    Parameters
    ----------
    settings : mapping
        JSON-serialisable run settings (nested mappings allowed).

    Returns
    -------
    str
        16 lowercase hex digits.

    Examples
    --------
    >>> run_hash({"a": 1, "b": [0.5]}) == run_hash({"b": [0.5], "a": 1.0})
    True
    >>> len(run_hash({"a": 1}))
    16
    """
    text = json.dumps(_canonical(settings), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:_HASH_LEN]


@dataclass(frozen=True)
class SweepRun:
    """One run of a sweep.

    Parameters
    ----------
    settings : mapping
        ``{case, controller, scheme, seed, seconds, quick, overrides}`` (JSON-serialisable).
    """

    settings: Mapping[str, Any]

    @property
    def hash(self) -> str:
        """The run's file stem, :func:`run_hash` of its settings."""
        return run_hash(self.settings)


def _fail(source: str, key: str, message: str) -> SweepSpecError:
    return SweepSpecError(f"{source}: {key}: {message}")


def _names(source: str, key: str, value: Any, valid: Sequence[str] | None) -> tuple[str, ...]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list | tuple) or not value:
        raise _fail(source, key, f"must be a non-empty list of names, got {value!r}")
    for v in value:
        if not isinstance(v, str) or not v:
            raise _fail(source, key, f"must contain names (strings), got {v!r}")
        if valid is not None and v not in valid:
            hint = difflib.get_close_matches(v, list(valid), n=1)
            maybe = f" (did you mean {hint[0]!r}?)" if hint else ""
            raise _fail(
                source, key, f"unknown name {v!r}{maybe}; valid: {', '.join(sorted(valid))}"
            )
    if len(set(value)) != len(value):
        dup = sorted({v for v in value if list(value).count(v) > 1})
        raise _fail(source, key, f"lists {dup} more than once")
    return tuple(value)


@dataclass(frozen=True)
class SweepSpec:
    """A validated sweep: cases x controllers x schemes x override combinations x seeds.

    Parameters
    ----------
    cases, controllers, schemes : tuple of str
        Names (validated against the runner's registries by :func:`load_sweep_spec`).
    seeds : tuple of int, default (0,)
        Seeds, integers >= 0, no repeats.
    seconds : float, default 5.0
        Simulated exposure per run [s], > 0.
    quick : bool, default False
        Quick mode of the runner (short calibration, fewer scan points).
    overrides : tuple of (key, tuple of values), default ()
        Case values to replace, each with the list of values to sweep (every combination).
    source : str, default "<spec>"
        Where the spec came from (named in error messages).
    """

    cases: tuple[str, ...]
    controllers: tuple[str, ...]
    schemes: tuple[str, ...]
    seeds: tuple[int, ...] = (0,)
    seconds: float = 5.0
    quick: bool = False
    overrides: tuple[tuple[str, tuple[Any, ...]], ...] = ()
    source: str = "<spec>"

    def __post_init__(self) -> None:
        src = self.source
        for key in ("cases", "controllers", "schemes"):
            object.__setattr__(self, key, _names(src, key, getattr(self, key), None))
        seeds = self.seeds
        if isinstance(seeds, int) and not isinstance(seeds, bool):
            seeds = (seeds,)
        if not isinstance(seeds, list | tuple) or not seeds:
            raise _fail(src, "seeds", f"must be a non-empty list of integers >= 0, got {seeds!r}")
        for s in seeds:
            if isinstance(s, bool) or not isinstance(s, int) or s < 0:
                raise _fail(src, "seeds", f"must contain integers >= 0, got {s!r}")
        if len(set(seeds)) != len(seeds):
            raise _fail(src, "seeds", f"lists a seed more than once: {list(seeds)}")
        object.__setattr__(self, "seeds", tuple(int(s) for s in seeds))
        sec = self.seconds
        if isinstance(sec, bool) or not isinstance(sec, int | float) or not 0 < sec < float("inf"):
            raise _fail(src, "seconds", f"must be a finite number > 0 [s], got {sec!r}")
        object.__setattr__(self, "seconds", float(sec))
        if not isinstance(self.quick, bool):
            raise _fail(src, "quick", f"must be true or false, got {self.quick!r}")
        over = self.overrides
        items = over.items() if isinstance(over, Mapping) else over
        clean = []
        for item in items:
            if not (isinstance(item, list | tuple) and len(item) == 2):
                raise _fail(src, "overrides", f"must map keys to lists of values, got {item!r}")
            key, values = item
            if not isinstance(key, str) or not key:
                raise _fail(src, "overrides", f"keys must be non-empty strings, got {key!r}")
            if not isinstance(values, list | tuple):
                values = (values,)
            if not values:
                raise _fail(src, f"overrides.{key}", "must list at least one value, got []")
            for v in values:
                if isinstance(v, Mapping | list | tuple) or v is None:
                    raise _fail(
                        src, f"overrides.{key}", f"values must be numbers or strings, got {v!r}"
                    )
            if len({json.dumps(_canonical(v)) for v in values}) != len(values):
                raise _fail(src, f"overrides.{key}", f"lists a value twice: {list(values)}")
            clean.append((key, tuple(values)))
        keys = [k for k, _ in clean]
        if len(set(keys)) != len(keys):
            raise _fail(src, "overrides", f"repeats a key: {keys}")
        object.__setattr__(self, "overrides", tuple(sorted(clean)))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str = "<spec>") -> SweepSpec:
        """Spec from a parsed TOML table, rejecting unknown keys.

        Parameters
        ----------
        data : mapping
            The spec's keys (:data:`SPEC_KEYS`); ``cases``, ``controllers``, ``schemes`` needed.
        source : str
            File name for the error messages.

        Raises
        ------
        SweepSpecError
            Unknown or missing key, wrong type.
        """
        if not isinstance(data, Mapping):
            raise _fail(source, "<root>", f"must be a table, got {type(data).__name__}")
        for key in data:
            if key not in SPEC_KEYS:
                hint = difflib.get_close_matches(key, SPEC_KEYS, n=1)
                maybe = f" (did you mean {hint[0]!r}?)" if hint else ""
                raise _fail(source, key, f"unknown key{maybe}; valid keys: {', '.join(SPEC_KEYS)}")
        for key in ("cases", "controllers", "schemes"):
            if key not in data:
                raise _fail(source, key, "missing (a list of names is required)")
        overrides = data.get("overrides", {})
        if not isinstance(overrides, Mapping):
            raise _fail(source, "overrides", f"must be a table, got {overrides!r}")
        return cls(
            cases=data["cases"],
            controllers=data["controllers"],
            schemes=data["schemes"],
            seeds=data.get("seeds", (0,)),
            seconds=data.get("seconds", 5.0),
            quick=data.get("quick", False),
            overrides=tuple(overrides.items()),
            source=source,
        )

    def runs(self) -> tuple[SweepRun, ...]:
        """Every run, in the order cases, controllers, schemes, overrides, seeds."""
        keys = [k for k, _ in self.overrides]
        combos = list(itertools.product(*(v for _, v in self.overrides)))
        out = []
        for case, ctrl, scheme, combo, seed in itertools.product(
            self.cases, self.controllers, self.schemes, combos, self.seeds
        ):
            settings = {
                "case": case,
                "controller": ctrl,
                "scheme": scheme,
                "seed": seed,
                "seconds": self.seconds,
                "quick": self.quick,
                "overrides": dict(zip(keys, combo, strict=True)),
            }
            out.append(SweepRun(settings))
        return tuple(out)
