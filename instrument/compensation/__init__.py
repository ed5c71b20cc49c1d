"""Error compensation of the six pose components (method.md §4; paper §3, eqs 18–37).

CSF (smoothing spline, λ by GCV on a log grid) → group alignment → PPSO-tuned ESN, plus
baselines behind one interface, an honest held-out evaluation, and a versioned calibration
record. Pure: no I/O (procedures read and write the record's JSON text).
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
    Compensator,
    CsfPpsoEsnCompensator,
    FittedModel,
    GaussianProcessCompensator,
    NoCompensation,
    PolynomialCompensator,
    SmoothingSplineCompensator,
    SumCurve,
    curve_from_dict,
    default_compensators,
)
from instrument.compensation._data import (
    ANGULAR_COMPONENTS,
    ARCSEC,
    COMPONENTS,
    LINEAR_COMPONENTS,
    CalibrationData,
    SyntheticScenario,
    display_unit,
    infer_points,
    noise_floor,
    paper_like_scenario,
    point_means,
    synthetic_calibration,
)
from instrument.compensation._esn import (
    EsnCurve,
    EsnHyperparameters,
    Reservoir,
    fit_esn,
    make_reservoir,
    tune_esn,
)
from instrument.compensation._evaluate import EvaluationRow, EvaluationTable, evaluate
from instrument.compensation._ppso import (
    ParetoResult,
    generational_distance,
    non_dominated_mask,
    ppso_minimize,
)
from instrument.compensation._record import (
    FORMAT_VERSION,
    CalibrationRecord,
    CalibrationRecordError,
    OutOfCalibrationRangeWarning,
    Provenance,
    calibrate,
)
from instrument.compensation._spline import SplineCurve, fit_spline_curve

__all__ = [
    "FORMAT_VERSION",
    "CalibrationRecord",
    "CalibrationRecordError",
    "OutOfCalibrationRangeWarning",
    "Provenance",
    "ANGULAR_COMPONENTS",
    "ARCSEC",
    "COMPONENTS",
    "LINEAR_COMPONENTS",
    "CalibrationData",
    "Compensator",
    "CsfPpsoEsnCompensator",
    "EsnCurve",
    "EsnHyperparameters",
    "EvaluationRow",
    "EvaluationTable",
    "FittedModel",
    "GaussianProcessCompensator",
    "GaussianProcessCurve",
    "GroupAlignment",
    "NoCompensation",
    "ParetoResult",
    "PolynomialCompensator",
    "PolynomialCurve",
    "Reservoir",
    "SmoothingSplineCompensator",
    "SplineCurve",
    "SumCurve",
    "SyntheticScenario",
    "ZeroCurve",
    "align_groups",
    "calibrate",
    "curve_from_dict",
    "default_compensators",
    "display_unit",
    "evaluate",
    "fit_esn",
    "fit_gaussian_process",
    "fit_polynomial",
    "fit_spline_curve",
    "generational_distance",
    "infer_points",
    "make_reservoir",
    "noise_floor",
    "non_dominated_mask",
    "paper_like_scenario",
    "point_means",
    "ppso_minimize",
    "stable_interval",
    "synthetic_calibration",
    "tune_esn",
]
