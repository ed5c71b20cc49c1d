"""Simulated twins of every device and the world model they share.

This package never imports ``instrument``: the twins' physics is written independently of the
measurement core, so a convention error on either side fails a test instead of cancelling out.
"""

from sim_devices._process import TwinProcess, TwinProcessError
from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.world import World, WorldConfig, WorldState

__all__ = ["FaultKind", "FaultPlan", "TwinProcess", "TwinProcessError", "World", "WorldConfig", "WorldState"]
