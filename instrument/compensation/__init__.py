"""Error compensation of the six pose components (method.md §4; paper §3, eqs 18–37).

CSF (smoothing spline, λ by GCV on a log grid) → group alignment → PPSO-tuned CSF + ripple + ESN,
plus CSF + ripple (periodic errors a few calibration steps long) and baselines behind one
interface, direction-aware (hysteresis) fitting, an honest held-out evaluation (leave one point
out, leave one group out), and a versioned calibration record that says how close each component
is to its noise floor.
Pure: no I/O (procedures read and write the record's JSON text).

Quick use::

    record = calibrate(CalibrationData("x", measured, reference, group, point, direction))
    record.correct("x", value, direction=+1).corrected
"""

from instrument.compensation._align import GroupAlignment, align_groups, stable_interval
from instrument.compensation._baselines import (
    GaussianProcessCurve,
    PolynomialCurve,
    ZeroCurve,
    fit_gaussian_process,
    fit_polynomial,
)
from instrument.compensation._compensators import (
    AlignedPoints,
    Compensator,
    CsfPpsoEsnCompensator,
    Curve,
    FittedModel,
    GaussianProcessCompensator,
    NoCompensation,
    PolynomialCompensator,
    RippleSplineCompensator,
    SmoothingSplineCompensator,
    aligned_points,
    curve_from_dict,
    default_compensators,
)
from instrument.compensation._csf_esn import SELECTIONS, decode, tune_csf_esn
from instrument.compensation._data import (
    ANGULAR_COMPONENTS,
    ARCSEC,
    COMPONENTS,
    LINEAR_COMPONENTS,
    MICROMETRE,
    CalibrationData,
    InsufficientCalibrationData,
    display_unit,
    infer_points,
    noise_floor,
    point_means,
)
from instrument.compensation._esn import (
    CsfEsnCurve,
    EsnHyperparameters,
    Reservoir,
    features,
    joint_fit,
    make_reservoir,
)
from instrument.compensation._evaluate import (
    LOGO,
    LOPO,
    SCHEMES,
    EvaluationRow,
    EvaluationTable,
    evaluate,
    leave_one_group_out_residuals,
    leave_one_point_out_residuals,
)
from instrument.compensation._floor import FLOOR_RATIO_LIMITS, FloorRatio
from instrument.compensation._ppso import (
    ParetoResult,
    generational_distance,
    non_dominated_mask,
    ppso_minimize,
)
from instrument.compensation._record import (
    FORMAT_VERSION,
    READABLE_VERSIONS,
    CalibrationRecord,
    CalibrationRecordError,
    CorrectionResult,
    PoseCorrection,
    Provenance,
    calibrate,
)
from instrument.compensation._ripple import PERIOD_RANGE, RippleSearch, find_ripples, fit_ripple_spline
from instrument.compensation._spline import SplineCurve, fit_spline_curve, reinsch_penalty
from instrument.compensation._synthetic import (
    HARD_PROFILES,
    Campaign,
    HeldOutSet,
    SyntheticScenario,
    hard_campaign,
    held_out_residuals,
    paper_like_scenario,
    synthetic_calibration,
)

__all__ = [
    "ANGULAR_COMPONENTS",
    "ARCSEC",
    "COMPONENTS",
    "FLOOR_RATIO_LIMITS",
    "FORMAT_VERSION",
    "HARD_PROFILES",
    "LINEAR_COMPONENTS",
    "LOGO",
    "LOPO",
    "MICROMETRE",
    "PERIOD_RANGE",
    "READABLE_VERSIONS",
    "SCHEMES",
    "SELECTIONS",
    "AlignedPoints",
    "CalibrationData",
    "CalibrationRecord",
    "CalibrationRecordError",
    "Campaign",
    "Compensator",
    "CorrectionResult",
    "CsfEsnCurve",
    "CsfPpsoEsnCompensator",
    "Curve",
    "EsnHyperparameters",
    "EvaluationRow",
    "EvaluationTable",
    "FittedModel",
    "FloorRatio",
    "GaussianProcessCompensator",
    "GaussianProcessCurve",
    "GroupAlignment",
    "InsufficientCalibrationData",
    "HeldOutSet",
    "NoCompensation",
    "ParetoResult",
    "PolynomialCompensator",
    "PolynomialCurve",
    "PoseCorrection",
    "Provenance",
    "Reservoir",
    "RippleSearch",
    "RippleSplineCompensator",
    "SmoothingSplineCompensator",
    "SplineCurve",
    "SyntheticScenario",
    "ZeroCurve",
    "align_groups",
    "aligned_points",
    "calibrate",
    "curve_from_dict",
    "decode",
    "default_compensators",
    "display_unit",
    "evaluate",
    "features",
    "find_ripples",
    "fit_gaussian_process",
    "fit_polynomial",
    "fit_ripple_spline",
    "fit_spline_curve",
    "generational_distance",
    "hard_campaign",
    "held_out_residuals",
    "infer_points",
    "joint_fit",
    "leave_one_group_out_residuals",
    "leave_one_point_out_residuals",
    "make_reservoir",
    "noise_floor",
    "non_dominated_mask",
    "paper_like_scenario",
    "point_means",
    "ppso_minimize",
    "reinsch_penalty",
    "stable_interval",
    "synthetic_calibration",
    "tune_csf_esn",
]
