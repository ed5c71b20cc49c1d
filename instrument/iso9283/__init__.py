"""ISO 9283 pose characteristics (method.md §5): RP, AP, AD/RD, vAP, drift, the test cube, and
confidence intervals. Inputs are (n, 6) arrays [x, y, z, a, b, c] in metres and radians."""

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
from instrument.iso9283._errors import ISO9283Error

__all__ = [
    "DistanceCharacteristics",
    "ISO9283Error",
    "IsoCube",
    "MultiDirectionalVariation",
    "PoseAccuracy",
    "PoseDrift",
    "PoseRepeatability",
    "VISITING_ORDER",
    "circular_mean",
    "distance_characteristics",
    "iso_cube_points",
    "multidirectional_variation",
    "pose_accuracy",
    "pose_drift",
    "pose_repeatability",
    "unwrap_about_mean",
    "wrap_angle",
]
