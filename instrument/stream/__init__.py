"""Measuring while the robot moves: frame triples → a stream of timestamped poses, and the camera
clocks put on the robot controller's clock (docs/dynamic.md). Pure: no I/O, no threads."""

from instrument.stream._clock import (
    ClockError,
    ClockModel,
    TimeLag,
    estimate_clock_offset,
    estimate_time_lag,
)
from instrument.stream._stream import (
    DEFAULT_MAX_TIMESTAMP_SPREAD,
    Drop,
    FrameTriple,
    PoseSample,
    PoseStream,
    PoseStreamer,
    PoseTracker,
)

__all__ = [
    "DEFAULT_MAX_TIMESTAMP_SPREAD",
    "ClockError",
    "ClockModel",
    "Drop",
    "FrameTriple",
    "PoseSample",
    "PoseStream",
    "PoseStreamer",
    "PoseTracker",
    "TimeLag",
    "estimate_clock_offset",
    "estimate_time_lag",
]
