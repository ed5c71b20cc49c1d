"""The ISO 9283 tests measured while the robot moves: pose stabilisation and path characteristics.

What it offers: the kinds (``STABILISATION``: stabilisation time, overshoot, minimum positioning time;
``PATH``: AT/RT, corner CR/CO, path velocity AV/RV/FV), their parameters and procedure-file models, the
OPR poses carried to the tool point (``tool_poses``) and the figures in the export's shape
(``dynamic_figures``, ``DYNAMIC_KINDS``). Both kinds share the plan and the measured move (``_plan``),
the analysis of the streams (``_analysis``) and the twin's dense truth (``_truth``).
"""

from procedures.kinds.dynamic._analysis import tool_poses
from procedures.kinds.dynamic._export import DYNAMIC_KINDS, dynamic_figures
from procedures.kinds.dynamic._path import KIND as PATH
from procedures.kinds.dynamic._path import Iso9283Path, PathParameters
from procedures.kinds.dynamic._plan import DynamicParameters
from procedures.kinds.dynamic._stabilisation import KIND as STABILISATION
from procedures.kinds.dynamic._stabilisation import Iso9283Stabilisation, StabilisationParameters

__all__ = [
    "DYNAMIC_KINDS", "PATH", "STABILISATION", "DynamicParameters", "Iso9283Path", "Iso9283Stabilisation",
    "PathParameters", "StabilisationParameters", "dynamic_figures", "tool_poses",
]
