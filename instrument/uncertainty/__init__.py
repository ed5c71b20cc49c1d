"""Measurement uncertainty of the ISO 9283 figures: a GUM budget propagated by Monte Carlo.

The budget (JCGM 100) lists each error source with its distribution and how its error is shared
between the poses of a run; ``iso_uncertainty`` propagates it by Monte Carlo (JCGM 101/102)
through ``instrument.iso9283``'s own formulas and returns, for every figure, the value, its
standard and expanded (k = 2) uncertainty, the per-term contributions, the sampling interval and
the 25 % rule. ``calibration_residual_uncertainty`` does the same for a calibration's held-out
residual. ``synthetic_iso_run`` and ``coverage_study`` validate U against known truth.
Pure functions, SI units (m, rad), seeded randomness, no I/O. See docs/uncertainty.md.
"""

from instrument.uncertainty._budget import (
    COMPONENTS,
    BudgetTerm,
    Correlation,
    Distribution,
    UncertaintyBudget,
    compensation_term,
    environment_term,
    interferometer_terms,
    rotary_table_term,
    scaled,
    transform_term,
)
from instrument.uncertainty._calibration import calibration_residual_uncertainty
from instrument.uncertainty._coverage import (
    CoverageCase,
    CoverageRow,
    CoverageTable,
    coverage_study,
    coverage_table,
)
from instrument.uncertainty._errors import UncertaintyError
from instrument.uncertainty._noise import (
    frame_noise_from_calibration,
    frame_noise_from_frames,
    frame_noise_from_residuals,
)
from instrument.uncertainty._propagate import (
    RULE_FRACTION,
    FigureUncertainty,
    IsoRun,
    IsoUncertainty,
    iso_uncertainty,
)
from instrument.uncertainty._synthetic import SyntheticCell, SyntheticIsoRun, synthetic_iso_run

__all__ = [
    "COMPONENTS",
    "RULE_FRACTION",
    "BudgetTerm",
    "Correlation",
    "CoverageCase",
    "CoverageRow",
    "CoverageTable",
    "Distribution",
    "FigureUncertainty",
    "IsoRun",
    "IsoUncertainty",
    "SyntheticCell",
    "SyntheticIsoRun",
    "UncertaintyBudget",
    "UncertaintyError",
    "calibration_residual_uncertainty",
    "compensation_term",
    "coverage_study",
    "coverage_table",
    "environment_term",
    "frame_noise_from_calibration",
    "frame_noise_from_frames",
    "frame_noise_from_residuals",
    "interferometer_terms",
    "iso_uncertainty",
    "rotary_table_term",
    "scaled",
    "synthetic_iso_run",
    "transform_term",
]
