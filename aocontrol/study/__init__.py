"""Study layer: demo, command line and plots (imports control and sim, never imported by them).

Only :mod:`aocontrol.study.plot` imports matplotlib.
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
]
