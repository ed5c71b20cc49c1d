"""ISO 9283 characteristics (method.md §5). Pose characteristics: RP, AP, AD/RD, vAP, drift, the
test cube and confidence intervals, from (n, 6) arrays [x, y, z, a, b, c] in metres and radians.
Dynamic characteristics (docs/dynamic.md), from time series of measured poses: position
stabilisation time and overshoot, positioning time, path accuracy and repeatability, cornering
deviations, path velocity."""

from instrument.iso9283._characteristics import (
    DistanceCharacteristics,
    MultiDirectionalVariation,
    PoseAccuracy,
    PoseDrift,
    PoseRepeatability,
    distance_characteristics,
    multidirectional_variation,
    pose_accuracy,
    pose_drift,
    pose_repeatability,
)
from instrument.iso9283._cube import VISITING_ORDER, IsoCube, iso_cube_points
from instrument.iso9283._data import circular_mean, unwrap_about_mean, wrap_angle
from instrument.iso9283._dynamic import (
    MinimumPositioningTime,
    PoseStabilisation,
    PositioningTime,
    minimum_positioning_time,
    pose_stabilisation,
    positioning_time,
)
from instrument.iso9283._errors import ISO9283Error
from instrument.iso9283._path import (
    CommandPath,
    CornerDeviation,
    PathCharacteristics,
    PathVelocity,
    circular_path,
    corner_deviation,
    linear_path,
    path_characteristics,
    path_speed,
    path_velocity,
)

__all__ = [
    "CommandPath",
    "CornerDeviation",
    "DistanceCharacteristics",
    "ISO9283Error",
    "IsoCube",
    "MinimumPositioningTime",
    "MultiDirectionalVariation",
    "PathCharacteristics",
    "PathVelocity",
    "PoseAccuracy",
    "PoseDrift",
    "PoseRepeatability",
    "PoseStabilisation",
    "PositioningTime",
    "VISITING_ORDER",
    "circular_mean",
    "circular_path",
    "corner_deviation",
    "distance_characteristics",
    "iso_cube_points",
    "linear_path",
    "minimum_positioning_time",
    "multidirectional_variation",
    "path_characteristics",
    "path_speed",
    "path_velocity",
    "pose_accuracy",
    "pose_drift",
    "pose_repeatability",
    "pose_stabilisation",
    "positioning_time",
    "unwrap_about_mean",
    "wrap_angle",
]
