"""Self-contained HTML reports: a case comparison, a controller design.

A report is one HTML file with no external resource (inline CSS, every figure a base64 PNG in a
``data:`` URI), so it can be mailed, archived or attached to a ticket and still opens whole.
The builders take plain result objects -- a :class:`~aocontrol.study.compare.CaseComparison`,
or a :class:`DesignReportData` (arrays, controller banks, margins) -- compute nothing that the
control layer does not already provide (margins, sensitivities, predicted residuals), draw
through :mod:`aocontrol.study.plot` (the plots are the only modules that import matplotlib) and
write the file atomically (a report that exists is complete). The two reports live in private
modules (``_report_comparison``, ``_report_design``) over their shared pieces
(``_report_common``); their public names are here.

What a report holds:

* comparison: the table (Strehl, 4-6 lambda/D contrast, measured and predicted stage-2
  residual per scheme and controller), the margins of every stage-2 bank over its modes on the
  design plant, the rejection ``|S|^2`` of each controller over the design's disturbance PSD
  for representative modes, the stage-2 residual PSDs, the contrast curves, and for a case with
  a vibration the tilt residual;
* design: the predicted residual of each controller against the bounds (total and per mode),
  the certified margins per mode, the rejection for representative modes, the predicted
  residual PSDs.
"""

from aocontrol.study._report_common import modal_margins, representative_modes
from aocontrol.study._report_comparison import comparison_report
from aocontrol.study._report_design import DesignReportData, design_report, design_report_data

__all__ = [
    "DesignReportData",
    "comparison_report",
    "design_report",
    "design_report_data",
    "modal_margins",
    "representative_modes",
]
