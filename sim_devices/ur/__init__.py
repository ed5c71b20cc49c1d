"""Protocol-level twin of a Universal Robots e-Series controller (PolyScope 5.15).

Speaks RTDE (30004), the dashboard (29999) and the script port (30003) to the real ``ur_rtde``
client, emulates ``rtde_control.script`` over the RTDE registers, moves a UR5e-class arm with
trapezoidal profiles in (optionally accelerated) simulated time, and writes the TRUE attained poses
(commanded pose ⊕ seeded repeatability error) into the shared ``World``.

Run it in its own process: ``TwinProcess("sim_devices.ur:standalone_host", {"host": "127.0.0.2"})``
or ``python -m sim_devices.ur --host 127.0.0.2``; a cell embeds ``URControllerTwin(world, host,
config)`` in its own (non-client) process.
"""

from sim_devices.ur._config import URTwinConfig
from sim_devices.ur._twin import URControllerTwin, standalone_host

__all__ = ["URControllerTwin", "URTwinConfig", "standalone_host"]
