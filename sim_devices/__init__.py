"""Simulated twins of every device and the world model they share.

This package never imports ``instrument``: the twins' physics is written independently of the
measurement core, so a convention error on either side fails a test instead of cancelling out.
For the same reason it takes from ``drivers`` only the shared errors and the camera interface:
each twin encodes its wire protocol (register map, word order, scaling, CAN frames, CRC) with its
own code, from the device documentation. See ``docs/simulated_cell.md`` for the cell.
"""

from sim_devices._process import TwinProcess, TwinProcessError
from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.world import World, WorldConfig, WorldState

__all__ = ["FaultKind", "FaultPlan", "TwinProcess", "TwinProcessError", "World", "WorldConfig", "WorldState"]
