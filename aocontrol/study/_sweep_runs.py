"""What a sweep runs and reads (private to :mod:`aocontrol.study.sweep`): the runner
contract (:class:`SweepRunner`), the default runner (``run_configuration`` and HDF5 results
files) and the sweep's table rebuilt from the files alone (:func:`sweep_table`).
"""

from __future__ import annotations

import csv
import io
import json
import os
import pathlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from aocontrol._atomic import atomic_path
from aocontrol._deprecation import deprecated_function
from aocontrol.study._sweep_spec import _HASH_LEN, _NAME_KEYS, _canonical, run_hash


# ------------------------------------------------------------------------------------ runners
@dataclass(frozen=True)
class SweepRunner:
    """What a sweep calls: the run itself, the reader of its file and the valid names.

    Parameters
    ----------
    run : callable ``(settings: dict, path: pathlib.Path) -> None``
        Runs one configuration and writes its result file at ``path`` (any format the
        ``read`` callable understands). Must be importable by the workers (a module-level
        function or an instance of a module-level class).
    read : callable ``(path: pathlib.Path) -> dict``
        One summary row from a result file: ``{"settings": <the run's settings dict>, ...
        figures of merit}``.
    valid : mapping, optional
        Valid names per spec key (``"cases"``, ``"controllers"``, ``"schemes"``); a key that is
        absent is not checked.
    check : callable ``(settings: dict) -> None``, optional
        Raises ``ValueError`` for a run that cannot work (e.g. an override the case lacks);
        called on every run before any starts.
    """

    run: Callable[[dict, pathlib.Path], None]
    read: Callable[[pathlib.Path], dict]
    valid: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    check: Callable[[dict], None] | None = None

    def __post_init__(self) -> None:
        for name in ("run", "read"):
            if not callable(getattr(self, name)):
                raise TypeError(f"{name} must be callable, got {getattr(self, name)!r}")
        if self.check is not None and not callable(self.check):
            raise TypeError(f"check must be callable or None, got {self.check!r}")
        bad = set(self.valid) - set(_NAME_KEYS)
        if bad:
            raise ValueError(f"valid keys must be among {sorted(_NAME_KEYS)}, got {sorted(bad)}")


def _run_configuration_and_save(settings: dict, path: pathlib.Path) -> None:
    """Default run: :func:`aocontrol.study.compare.run_configuration` + ``save_result``."""
    from aocontrol.study.compare import run_configuration
    from aocontrol.study.results import save_result

    outcome = run_configuration(
        settings["case"],
        controller=settings["controller"],
        scheme=settings["scheme"],
        seconds=settings["seconds"],
        seed=settings["seed"],
        overrides=dict(settings["overrides"]) or None,
        quick=settings["quick"],
        progress=False,
    )
    full = dict(outcome.settings)
    full["sweep"] = {"hash": run_hash(settings), "request": settings}
    save_result(outcome.result, path, settings=full)


#: Columns of a results file's summary row kept in the sweep's table (E1's results module).
_RESULT_FIGURES = ("strehl", "mean_contrast_4_6", "residual_rms_nm", "fs", "n_frames")


def _read_result_row(path: pathlib.Path) -> dict:
    """Default read: the run's request (stored by the sweep) and its figures of merit."""
    from aocontrol.study.results import read_settings
    from aocontrol.study.results import summary_table as file_rows

    settings = read_settings(path)
    request = settings.get("sweep", {}).get("request")
    if request is None:  # a results file written outside a sweep
        request = {
            k: settings[k] for k in ("case", "controller", "scheme", "seed") if k in settings
        }
    row = file_rows([path])[0]
    return {"settings": request, **{k: row[k] for k in _RESULT_FIGURES if k in row}}


def _check_run(settings: dict) -> None:
    """Default check: the case loads and takes the overrides (before any run starts)."""
    from aocontrol.study.cases import apply_overrides, load_case

    apply_overrides(load_case(settings["case"]), dict(settings["overrides"]) or None)


def default_runner() -> SweepRunner:
    """The real runner: ``run_configuration`` of the case comparison, HDF5 results files.

    Returns
    -------
    SweepRunner
        Valid names from :func:`aocontrol.study.cases.list_cases`, the controller registry and
        the schemes of :mod:`aocontrol.study.compare`; every run's overrides are checked with
        :func:`aocontrol.study.cases.apply_overrides` before any run starts.
    """
    from aocontrol.study import compare
    from aocontrol.study.cases import list_cases

    valid = {
        "cases": tuple(list_cases()),
        "controllers": compare.controller_names(),
        "schemes": tuple(compare.SCHEMES),
    }
    return SweepRunner(
        run=_run_configuration_and_save, read=_read_result_row, valid=valid, check=_check_run
    )


# ------------------------------------------------------------------------------------ summary
def _flat_item(prefix: str, key: str, value: Any, row: dict) -> None:
    name = f"{prefix}{key}"
    if isinstance(value, Mapping):
        for k, v in value.items():
            _flat_item(f"{name}.", k, v, row)
    elif isinstance(value, list | tuple):
        row[name] = json.dumps(_canonical(value))
    else:
        row[name] = value


_FIRST = ("hash", "status", "case", "controller", "scheme", "seed", "seconds", "quick")


@deprecated_function(
    "aocontrol.study.sweep.summary_table",
    "sweep_table(out) of aocontrol.study.sweep (the name summary_table belongs to "
    "aocontrol.study.results.summary_table(paths))",
)
def summary_table(
    out: str | os.PathLike,
    *,
    runner: SweepRunner | None = None,
    csv_path: str | os.PathLike | None = "summary.csv",
) -> list[dict]:
    """Deprecated name of :func:`sweep_table` (same arguments, same rows).

    :func:`aocontrol.study.results.summary_table` (a list of files) keeps the name.

    Parameters
    ----------
    out : path
        Results folder of a sweep.
    runner : SweepRunner, optional
        As in :func:`sweep_table`.
    csv_path : path or None, default "summary.csv"
        As in :func:`sweep_table`.

    Returns
    -------
    list of dict

    Warns
    -----
    DeprecationWarning
        Always, pointing to :func:`sweep_table`.
    """
    return sweep_table(out, runner=runner, csv_path=csv_path)


def sweep_table(
    out: str | os.PathLike,
    *,
    runner: SweepRunner | None = None,
    csv_path: str | os.PathLike | None = "summary.csv",
) -> list[dict]:
    """One row per run file in ``out``, rebuilt from the files alone (and written as CSV).

    Parameters
    ----------
    out : path
        Results folder of a sweep.
    runner : SweepRunner, optional
        Its ``read`` turns a result file into a row; default :func:`default_runner`'s.
    csv_path : path or None, default "summary.csv"
        CSV file written (atomically); relative paths are inside ``out``; None writes nothing.

    Returns
    -------
    list of dict
        Sorted by hash. Keys: ``hash``, ``status`` (``"done"`` or ``"failed"``), the request
        (``case``, ``controller``, ``scheme``, ``seed``, ``seconds``, ``quick``,
        ``overrides.<key>``), then the reader's figures (nested keys joined by dots); failed
        runs have ``error``.
    """
    out = pathlib.Path(out)
    read = (runner or default_runner()).read
    rows = []
    for path in sorted(out.glob("*.h5")):
        if len(path.stem) != _HASH_LEN:
            continue
        data = dict(read(path))
        settings = data.pop("settings", {})
        row = {"hash": path.stem, "status": "done"}
        for k, v in settings.items():
            _flat_item("", k, v, row)
        for k, v in data.items():
            _flat_item("", k, v, row)
        rows.append(row)
    for path in sorted(out.glob("*.error.json")):
        hash_ = path.name.split(".")[0]
        if (out / f"{hash_}.h5").exists():
            continue  # a later attempt succeeded
        record = json.loads(path.read_text())
        row = {"hash": hash_, "status": "failed"}
        for k, v in record.get("settings", {}).items():
            _flat_item("", k, v, row)
        row["error"] = f"{record.get('error_type')}: {record.get('error')}"
        rows.append(row)
    rows.sort(key=lambda r: r["hash"])
    if csv_path is not None:
        target = pathlib.Path(csv_path)
        target = target if target.is_absolute() else out / target
        keys = [k for k in _FIRST if any(k in r for r in rows)]
        keys += sorted({k for r in rows for k in r} - set(keys))
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        with atomic_path(target) as tmp:
            pathlib.Path(tmp).write_text(buf.getvalue())
    return rows
