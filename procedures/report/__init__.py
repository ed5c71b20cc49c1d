"""Reports of runs: the HTML report (and its PDF), the exports, and the terminal's result summaries.

What it offers:

- ``render_report`` (one self-contained HTML document per run), ``render_pdf`` and ``PdfUnavailable``,
  ``robot_label``; ``report_title``, a run's title as its kind words it from the parameters in force (the
  report, ``instrument show``, the web view and OPC UA title a run by it, never by the procedure file's name);
  ``export_csv`` and ``export_json``;
- the registry of results sections, one per shape of results a kind declares (``SECTIONS``,
  ``ResultSection``, ``register_section``, ``unregister_section``) and the lookups through it:
  ``show_lines`` (``instrument show``), ``result_lines`` and ``result_summary`` (the end of ``run`` and
  ``resume``), ``history_procedures`` and ``history_figures`` (a robot's history);
- the terminal's and the web view's reading of ISO figures (``iso_rows``, ``point_figure``, ``changes``,
  ``shown``, ``figure_columns``, ``iso_points``) and of calibrations (``held_out_rows``,
  ``calibration_lines``);
- the building blocks its tests check: SVG plots (``lines``, ``scatter``, ``Circle``), the ISO section's
  ``figure``, ``Figure``, ``figure_cell``, ``MICROMETRES``, and ``quantity`` (SI values shown by their key).

Units are converted here, at the edge (µm, arc-seconds, mm/s, °C); the stored results stay SI. It reads the
kinds' results through their declared shape (``procedures.kinds``) and the store's samples; it never
imports the engine or the faces.
"""

from procedures.report._conditions import quantity, report_title
from procedures.report._document import render_report, robot_label
from procedures.report._export import export_csv, export_json
from procedures.report._format import MICROMETRES, Figure, figure_cell
from procedures.report._iso import figure
from procedures.report._pdf import PdfUnavailable, render_pdf
from procedures.report._sections import (
    SECTIONS,
    ResultSection,
    history_figures,
    history_procedures,
    register_section,
    result_lines,
    result_summary,
    show_lines,
    unregister_section,
)
from procedures.report._summaries import (
    calibration_lines,
    changes,
    figure_columns,
    held_out_rows,
    iso_points,
    iso_rows,
    point_figure,
    shown,
)
from procedures.report._svg import Circle, lines, scatter

__all__ = [
    "MICROMETRES", "SECTIONS", "Circle", "Figure", "PdfUnavailable", "ResultSection", "calibration_lines",
    "changes", "export_csv", "export_json", "figure", "figure_cell", "figure_columns", "held_out_rows",
    "history_figures", "history_procedures", "iso_points", "iso_rows", "lines", "point_figure", "quantity",
    "register_section", "render_pdf", "render_report", "report_title", "result_lines", "result_summary",
    "robot_label", "scatter", "show_lines", "shown", "unregister_section",
]
