"""The static ISO 9283 test: pose repeatability and accuracy over the cube's points P1…P5.

What it offers: the kind (``REPEATABILITY``, whose ``procedure:`` name the registry in
``procedures.kinds`` knows), its parameters and procedure-file models (``IsoParameters``,
``Iso9283Repeatability``) and the cube's points in the cycle's order (``cube_path``); from its analysis
the figure names (``POINT_FIGURES``), a figure object without uncertainty
(``figure_without_uncertainty``) and a finished run as a ``CoverageCase`` (``coverage_case``); from its
test conditions ``largest_cube_edge``; and the uncertainty budget's parts (``iso_budget``,
``squareness_terms``, ``environment_scale_term``, ``off_axis_error``, ``BudgetUnavailable``).

Inside, one module per part, each importing only those below it: ``_parameters`` ← ``_test_conditions``,
``_budget`` ← ``_analysis`` ← ``_repeatability`` (the kind).
"""

from procedures.kinds.iso._analysis import POINT_FIGURES, coverage_case, figure_without_uncertainty
from procedures.kinds.iso._budget import (
    BudgetUnavailable,
    environment_scale_term,
    iso_budget,
    off_axis_error,
    squareness_terms,
)
from procedures.kinds.iso._parameters import Iso9283Repeatability, IsoParameters, cube_path
from procedures.kinds.iso._repeatability import KIND as REPEATABILITY
from procedures.kinds.iso._test_conditions import largest_cube_edge

__all__ = [
    "POINT_FIGURES", "REPEATABILITY", "BudgetUnavailable", "Iso9283Repeatability", "IsoParameters", "coverage_case",
    "cube_path", "environment_scale_term", "figure_without_uncertainty", "iso_budget", "largest_cube_edge",
    "off_axis_error", "squareness_terms",
]
