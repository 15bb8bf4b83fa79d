"""Files in and out of the control layer: AOT telemetry and controller exports for an RTC.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.

* AOT (ESO's Adaptive Optics Telemetry standard, FITS, through ``aotpy``):
  :func:`read_aot` (a loop's modal telemetry, ready for
  :func:`aocontrol.synthesis.design_from_telemetry`), :func:`aot_loops`,
  :func:`write_aot_filter` / :func:`read_aot_filter` / :func:`aot_time_filter` (a bank in a
  loop's temporal filter, in ``aotpy``'s documented convention, stated in the file).
* Real-time export: :func:`export_controller` (one FITS table or a CSV: mode, b0..bn,
  a1..an, fs, latency, margin) and :func:`read_exported_controller`.
"""

from aocontrol.io._aot import (
    AOT_COMMAND_UNIT,
    AOTError,
    aot_loops,
    read_aot,
    write_system,
)
from aocontrol.io._aot_filter import (
    FILTER_CONVENTIONS,
    TFCONV_KEY,
    aot_time_filter,
    read_aot_filter,
    write_aot_filter,
)
from aocontrol.io._rtc import (
    EXPORT_FORMATS,
    ExportedController,
    export_controller,
    iir_coefficients,
    read_exported_controller,
)

__all__ = [
    "AOT_COMMAND_UNIT",
    "AOTError",
    "EXPORT_FORMATS",
    "FILTER_CONVENTIONS",
    "TFCONV_KEY",
    "aot_time_filter",
    "ExportedController",
    "aot_loops",
    "export_controller",
    "iir_coefficients",
    "read_aot",
    "read_aot_filter",
    "read_exported_controller",
    "write_aot_filter",
    "write_system",
]
