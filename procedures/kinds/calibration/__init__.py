"""The two calibrations of the optical pose reference: displacement (interferometer) and angle (rotary table).

What it offers: the kinds (``DISPLACEMENT``, ``ANGLE``), their parameters and procedure-file models, and
the calibration results' parts its tests check (``before_after``, ``off_axis_slopes``). Both kinds share
the point grid and the analysis into a calibration record (``_common``, with ``_results`` for the held-out
evaluation, the before/after statistics and the residual uncertainty).
"""

from procedures.kinds.calibration._angle import KIND as ANGLE
from procedures.kinds.calibration._angle import AngleCalibration, AngleParameters
from procedures.kinds.calibration._displacement import KIND as DISPLACEMENT
from procedures.kinds.calibration._displacement import DisplacementCalibration, DisplacementParameters
from procedures.kinds.calibration._results import before_after, off_axis_slopes

__all__ = [
    "ANGLE", "DISPLACEMENT", "AngleCalibration", "AngleParameters", "DisplacementCalibration",
    "DisplacementParameters", "before_after", "off_axis_slopes",
]
