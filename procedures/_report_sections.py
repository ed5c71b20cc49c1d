"""The results sections of run reports: the building blocks the procedure kinds use.

Values are stored in SI; the sections convert to the report's units (µm, arc-seconds with degrees
beside) and say so in every header. The sections live in ``_report_iso`` and
``_report_calibration``; the formatting they share in ``_report_format``.
"""

from __future__ import annotations

from procedures._report_calibration import calibration_results_html, calibration_summary_lines
from procedures._report_format import ARCSEC, fmt
from procedures._report_iso import iso_results_html, iso_summary_lines

__all__ = ["ARCSEC", "calibration_results_html", "calibration_summary_lines", "fmt", "iso_results_html",
           "iso_summary_lines"]
