"""Study layer: cases, comparisons, sweeps, results files, command line and plots.

Imports control and sim, never imported by them. Only :mod:`aocontrol.study.plot` (and its
private modules) imports matplotlib. The main jobs are here: :func:`run_configuration` (one
case, controller and scheme), :func:`compare_case` (the paper's protocol on a case),
:func:`build_scene` (what a case builds: pupil, bases, sensors) and :func:`run_sweep` (cases x
controllers x schemes x seeds, local or on Dask); they are imported on first use, so
``import aocontrol.study`` stays light.
"""

from aocontrol.study.aot import write_run_aot
from aocontrol.study.cases import Case, CaseError, list_cases, load_case
from aocontrol.study.results import (
    convert_npz,
    load_result,
    read_psds,
    read_settings,
    save_result,
    summary_table,
)

__all__: list[str] = [
    "save_result",
    "load_result",
    "convert_npz",
    "read_psds",
    "read_settings",
    "summary_table",
    "Case",
    "CaseError",
    "load_case",
    "list_cases",
    "write_run_aot",
    "run_configuration",
    "compare_case",
    "build_scene",
    "run_sweep",
]

# Main jobs, imported on first use (the simulator and Dask load only when a job is asked for).
_LAZY = {
    "run_configuration": "aocontrol.study.compare",
    "compare_case": "aocontrol.study.compare",
    "build_scene": "aocontrol.study.scene",
    "run_sweep": "aocontrol.study.sweep",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'aocontrol.study' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
