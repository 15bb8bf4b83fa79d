"""Controller files: one HDF5 file per controller bank, reloadable into the same bank.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.

File layout (plain HDF5, readable with h5py alone)::

    /                 attrs: format = "aocontrol-controller", format_version, class_name,
                             class_module, fs [Hz], n_modes, software_version, and the bank's
                             own scalar parameters (e.g. ``leak``)
    /<array name>     one dataset per coefficient array (e.g. ``b``, ``a``, ``gain``)

Protocol for a bank class (how LQG, MPC and future banks join): either define

* ``to_arrays(self) -> tuple[dict[str, ndarray], dict[str, scalar or str]]`` and
* a classmethod ``from_arrays(cls, arrays, attrs) -> bank``,

or call :func:`register_controller_format` with two such functions. Classes are found by
name (``type(bank).__name__``) when a file is read, so the class must be importable from
:mod:`aocontrol.controllers` (or registered) before :func:`load_controller` is called. The
round trip must be bit-identical: same coefficients, same ``step()`` output.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import h5py
import numpy as np

from aocontrol._atomic import atomic_path
from aocontrol._version import __version__
from aocontrol.controllers._base import ControllerBank, IIRBank, _command_limit_in
from aocontrol.controllers._integrator import Integrator

__all__ = ["save_controller", "load_controller", "register_controller_format"]

logger = logging.getLogger(__name__)

#: ``format`` attribute of a controller file.
CONTROLLER_FORMAT = "aocontrol-controller"
#: Layout version of controller files (bumped on incompatible changes).
CONTROLLER_FORMAT_VERSION = 1

ToArrays = Callable[[Any], tuple[dict[str, np.ndarray], dict[str, Any]]]
FromArrays = Callable[[Mapping[str, np.ndarray], Mapping[str, Any]], ControllerBank]

_REGISTRY: dict[str, tuple[ToArrays, FromArrays]] = {}
_RESERVED = {
    "format",
    "format_version",
    "class_name",
    "class_module",
    "fs",
    "n_modes",
    "software_version",
}


def register_controller_format(cls: type, to_arrays: ToArrays, from_arrays: FromArrays) -> None:
    """Teach :func:`save_controller` / :func:`load_controller` a bank class.

    Parameters
    ----------
    cls : type
        The bank class (a :class:`ControllerBank` subclass). Files name it by
        ``cls.__name__``.
    to_arrays : callable ``bank -> (arrays, attrs)``
        ``arrays``: dict of name -> ndarray (coefficients); ``attrs``: dict of name -> int,
        float, bool, str or None (scalar parameters). ``fs`` and ``n_modes`` are written by
        :func:`save_controller` and must not be returned.
    from_arrays : callable ``(arrays, attrs) -> bank``
        Inverse of ``to_arrays``; ``attrs`` also holds ``fs`` [Hz] and ``n_modes``.
    """
    if not isinstance(cls, type):
        raise TypeError(f"cls must be a class, got {cls!r}")
    _REGISTRY[cls.__name__] = (to_arrays, from_arrays)


def _iir_to_arrays(bank: IIRBank) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    arrays = {"b": np.asarray(bank.b), "a": np.asarray(bank.a)}
    if bank.command_limit is not None:
        arrays["command_limit"] = np.asarray(bank.command_limit)
    return arrays, {}


def _iir_from_arrays(arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> IIRBank:
    limit = _command_limit_in(arrays)
    return IIRBank(arrays["b"], arrays["a"], float(attrs["fs"]), command_limit=limit)


def _integrator_to_arrays(bank: Integrator) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    arrays = {"gain": bank.gain}
    if bank.command_limit is not None:
        arrays["command_limit"] = np.asarray(bank.command_limit)
    return arrays, {"leak": bank.leak}


def _integrator_from_arrays(
    arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]
) -> Integrator:
    return Integrator(
        arrays["gain"],
        float(attrs["fs"]),
        float(attrs["leak"]),
        command_limit=_command_limit_in(arrays),
    )


register_controller_format(IIRBank, _iir_to_arrays, _iir_from_arrays)
register_controller_format(Integrator, _integrator_to_arrays, _integrator_from_arrays)


def _subclasses(cls: type) -> Iterator[type]:
    for sub in cls.__subclasses__():
        yield sub
        yield from _subclasses(sub)


def _codec(name: str) -> tuple[ToArrays, FromArrays] | None:
    if name in _REGISTRY:
        return _REGISTRY[name]
    for sub in _subclasses(ControllerBank):
        if sub.__name__ == name and hasattr(sub, "to_arrays") and hasattr(sub, "from_arrays"):
            return (lambda bank: bank.to_arrays()), sub.from_arrays
    return None


def _known() -> list[str]:
    names = set(_REGISTRY)
    names.update(
        s.__name__
        for s in _subclasses(ControllerBank)
        if hasattr(s, "to_arrays") and hasattr(s, "from_arrays")
    )
    return sorted(names)


def _attr_value(name: str, value: Any) -> Any:
    if value is None:
        return "__none__"
    if isinstance(value, (bool, np.bool_)):
        return np.int8(bool(value))  # HDF5 has no boolean attribute; read back as bool below
    if isinstance(value, (int, float, str, np.integer, np.floating)):
        return value
    raise TypeError(
        f"controller attribute {name!r} must be int, float, bool, str or None, "
        f"got {type(value).__name__}"
    )


def _codec_for(bank: ControllerBank) -> tuple[ToArrays, FromArrays]:
    # The exact class only: a subclass without its own format would reload as its base and
    # lose its type, so it is refused.
    name = type(bank).__name__
    codec = _codec(name)
    if codec is None:
        raise TypeError(
            f"bank must be a controller with a file format, got {name}; known: {_known()} "
            "(add to_arrays()/from_arrays() or call register_controller_format)"
        )
    return codec


def save_controller(bank: ControllerBank, path: str | os.PathLike) -> str:
    """Write a controller bank to an HDF5 file, atomically.

    Parameters
    ----------
    bank : ControllerBank
        Any bank with a file format (:class:`IIRBank`, :class:`Integrator`, and classes that
        follow the protocol in this module's docstring).
    path : str or os.PathLike
        Output file (``.h5`` by convention). Written to a temporary name in the same folder,
        flushed and renamed, so an existing file is always complete.

    Returns
    -------
    str
        ``path``.

    Raises
    ------
    TypeError
        If ``bank`` has no file format (the message lists the known classes).
    """

    if not isinstance(bank, ControllerBank):
        raise TypeError(f"bank must be a ControllerBank, got {type(bank).__name__}")
    to_arrays, _ = _codec_for(bank)
    arrays, attrs = to_arrays(bank)
    clash = _RESERVED & set(attrs)
    if clash:
        raise ValueError(f"controller attributes must not use reserved names {sorted(clash)}")
    path = os.fspath(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as fh:
        fh.attrs["format"] = CONTROLLER_FORMAT
        fh.attrs["format_version"] = CONTROLLER_FORMAT_VERSION
        fh.attrs["class_name"] = type(bank).__name__
        fh.attrs["class_module"] = type(bank).__module__
        fh.attrs["fs"] = float(bank.fs)
        fh.attrs["n_modes"] = int(bank.n_modes)
        fh.attrs["software_version"] = __version__
        fh.attrs["bool_attrs"] = json.dumps(
            sorted(k for k, v in attrs.items() if isinstance(v, (bool, np.bool_)))
        )
        for key, value in attrs.items():
            fh.attrs[key] = _attr_value(key, value)
        for key, value in arrays.items():
            fh.create_dataset(key, data=np.asarray(value))
    logger.info("controller %s (%d modes) written to %s", type(bank).__name__, bank.n_modes, path)
    return path


def load_controller(path: str | os.PathLike) -> ControllerBank:
    """Read a controller bank written by :func:`save_controller`.

    Parameters
    ----------
    path : str or os.PathLike
        Controller file.

    Returns
    -------
    ControllerBank
        A bank of the saved class with the saved coefficients (bit-identical) and a fresh
        (zero) state.

    Raises
    ------
    ValueError
        If the file is not a controller file, or names a class with no known format.
    OSError
        If the file cannot be read.
    """
    path = os.fspath(path)
    with h5py.File(path, "r") as fh:
        fmt = fh.attrs.get("format")
        if fmt != CONTROLLER_FORMAT:
            raise ValueError(
                f"path {path!r} is not an aocontrol controller file "
                f"(format attribute {fmt!r}, expected {CONTROLLER_FORMAT!r})"
            )
        version = int(fh.attrs["format_version"])
        if version > CONTROLLER_FORMAT_VERSION:
            raise ValueError(
                f"path {path!r} has controller format_version {version}; this aocontrol reads "
                f"<= {CONTROLLER_FORMAT_VERSION}"
            )
        bools = set(json.loads(fh.attrs.get("bool_attrs", "[]")))
        attrs: dict[str, Any] = {}
        for key, value in fh.attrs.items():
            if isinstance(value, bytes):
                value = value.decode()
            if isinstance(value, np.generic):
                value = value.item()
            if value == "__none__":
                value = None
            if key in bools:
                value = bool(value)
            attrs[key] = value
        arrays = {key: fh[key][()] for key in fh.keys()}
    name = attrs["class_name"]
    codec = _codec(name)
    if codec is None:
        raise ValueError(
            f"path {path!r} holds a {name} controller, which this aocontrol cannot rebuild; "
            f"known: {_known()}"
        )
    bank = codec[1](arrays, attrs)
    if bank.n_modes != attrs["n_modes"]:
        raise ValueError(
            f"path {path!r}: rebuilt {name} has {bank.n_modes} modes, the file says "
            f"{attrs['n_modes']}"
        )
    return bank
