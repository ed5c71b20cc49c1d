"""Image → cross: pre-processing, IGCF sub-pixel stripe centres, bisquare line fits (method.md §2)."""

from instrument.vision._types import CrossMeasurement, CrossNotFound, StripeLine

__all__ = ["CrossMeasurement", "CrossNotFound", "StripeLine"]
