"""Laser interferometers: the ``Interferometer`` interface and adapters."""

from drivers.interferometer._interface import BeamInterrupted, FeedGap, Interferometer, Sample

__all__ = ["BeamInterrupted", "FeedGap", "Interferometer", "Sample"]
