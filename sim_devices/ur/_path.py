"""Moved to ``sim_devices.arm`` (shared by the robot twins); these names stay importable from here."""

from sim_devices.arm import Move, PathError, PathPlan

__all__ = ["Move", "PathError", "PathPlan"]
