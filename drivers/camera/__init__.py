"""Cameras: the ``Camera`` interface and adapters."""

from drivers.camera._interface import Camera, Frame, GrabFailed, Roi

__all__ = ["Camera", "Frame", "GrabFailed", "Roi"]
