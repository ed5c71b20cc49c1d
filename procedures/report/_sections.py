"""The registry of results sections: how each shape of results is shown, found by the shape a kind declares.

A procedure kind declares the shape of its results (``ProcedureKind.result_shape``) and shows nothing
itself; a ``ResultSection`` says how one shape is shown: the report's results section (``html``), what
``instrument show`` prints (``show_lines``), the table ``run`` and ``resume`` print at the end
(``table_lines``) and the key results of the ``--jsonl`` ``done`` event (``key_results``, SI). The
report, the terminal and the web view look a run's section up here, through its kind; nothing here
names a kind. A kind of a new family registers the section of its shape (``register_section``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from html import escape
from types import MappingProxyType
from typing import Any

from procedures.kinds import KINDS, ProcedureKind, ResultShape
from procedures.report._calibration import calibration_results_html, calibration_summary_lines
from procedures.report._dynamic import path_html, path_lines, stabilisation_html, stabilisation_lines
from procedures.report._iso import iso_results_html, iso_summary_lines
from procedures.report._summaries import (
    calibration_key_results,
    calibration_lines,
    dynamic_key_results,
    iso_key_results,
    iso_table_lines,
)

Results = Mapping[str, Any]


def _no_lines(results: Results) -> list[str]:
    return []


def _no_key_results(results: Results) -> dict[str, Any] | None:
    return None


@dataclass(frozen=True)
class ResultSection:
    """How one shape of results is shown (each takes the run's stored ``results`` mapping, SI).

    html : the report's results section (``<section class=part id=results>`` …)
    show_lines : the lines ``instrument show`` prints under the run
    table_lines : what ``run`` and ``resume`` print when the run has finished
    key_results : the ``results`` of the ``--jsonl`` ``done`` event (JSON-able, SI), or None
    """

    html: Callable[[Results], str]
    show_lines: Callable[[Results], list[str]]
    table_lines: Callable[[Results], list[str]] = _no_lines
    key_results: Callable[[Results], dict[str, Any] | None] = _no_key_results


_BUILT_IN: dict[str, ResultSection] = {
    ResultShape.ISO_POSE: ResultSection(iso_results_html, iso_summary_lines, iso_table_lines, iso_key_results),
    ResultShape.CALIBRATION: ResultSection(calibration_results_html, calibration_summary_lines, calibration_lines,
                                           calibration_key_results),
    ResultShape.STABILISATION: ResultSection(stabilisation_html, stabilisation_lines, stabilisation_lines,
                                             dynamic_key_results),
    ResultShape.PATH: ResultSection(path_html, path_lines, path_lines, dynamic_key_results),
}
_SECTIONS: dict[str, ResultSection] = dict(_BUILT_IN)
SECTIONS: Mapping[str, ResultSection] = MappingProxyType(_SECTIONS)
"""Every section by the result shape it shows (read-only; ``register_section`` adds one)."""


def register_section(shape: str, section: ResultSection) -> None:
    """Show the results of ``shape`` (a kind's new shape) with ``section``."""
    if shape in _SECTIONS:
        raise ValueError(f"results of shape {shape!r} already have a section")
    _SECTIONS[shape] = section


def unregister_section(shape: str) -> None:
    """Remove a section ``register_section`` added (the built-in ones stay)."""
    if shape in _BUILT_IN:
        raise ValueError(f"{shape!r} is a built-in result shape")
    _SECTIONS.pop(shape, None)


def kind_of_run(run: Mapping[str, Any]) -> ProcedureKind[Any] | None:
    """The kind that ran ``run`` (a stored run row), or None for a procedure no longer known."""
    return KINDS.get(str(run["procedure"]))


def section_of(run: Mapping[str, Any]) -> ResultSection | None:
    """The section that shows ``run``'s results, or None (an unknown kind, or a shape without one)."""
    kind = kind_of_run(run)
    return None if kind is None else SECTIONS.get(kind.result_shape)


def results_html(run: Mapping[str, Any]) -> str:
    """The report's results section of a stored run (a note when it has none, or nothing shows them)."""
    results = run.get("results")
    if not results:
        return "<section class=part id=results><h2>Results</h2><p>No results: the run has not finished.</p></section>"
    section = section_of(run)
    if section is None:
        return (f"<section class=part id=results><h2>Results</h2><p>No report section for procedure "
                f"{escape(str(run['procedure']))}: results only in the export.</p></section>")
    return section.html(results)


def show_lines(run: Mapping[str, Any]) -> list[str]:
    """What ``instrument show`` prints of a run's results (nothing before it has them)."""
    results, section = run.get("results"), section_of(run)
    return section.show_lines(results) if results and section is not None else []


def result_lines(run: Mapping[str, Any]) -> list[str]:
    """The key results of a stored run as ``run``/``resume`` print them (empty when it has none)."""
    results, section = run.get("results"), section_of(run)
    return section.table_lines(results) if results and section is not None else []


def result_summary(run: Mapping[str, Any]) -> dict[str, Any] | None:
    """The key results as JSON (SI), or None."""
    results, section = run.get("results"), section_of(run)
    return section.key_results(results) if results and section is not None else None


def history_procedures() -> tuple[str, ...]:
    """The kinds whose runs a robot's history follows (they declare ``history_figures``), by name."""
    return tuple(name for name, kind in KINDS.items() if kind.history_figures)


def history_figures() -> tuple[str, ...]:
    """The figures a robot's history shows: those its kinds declare, in their order."""
    return tuple(dict.fromkeys(figure for kind in KINDS.values() for figure in kind.history_figures))
