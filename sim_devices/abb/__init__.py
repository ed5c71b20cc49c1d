"""Protocol-level twin of an ABB IRC5 controller (RobotWare 6) with an IRB 2600-class arm.

Serves Robot Web Services 1.0 (HTTP Digest, ``?json=1`` resources, the file service, the event
log, subscriptions over a WebSocket) to ``abb_robot_client``, runs abb_motion_program_exec's RAPID
module on the binary programs it uploads (decoded by the twin's own reader), streams EGM
``EgmRobot`` packets (the twin's own protobuf encoder) and moves the arm with the same controller
core and dynamics as the UR twin (``sim_devices.arm``), writing the TRUE attained poses into the
shared ``World``.

Run it in its own process: ``TwinProcess("sim_devices.abb:standalone_host", {"host": "127.0.0.3"})``
or ``python -m sim_devices.abb --host 127.0.0.3``; a cell embeds ``ABBControllerTwin(world, host,
config)``.
"""

from sim_devices.abb._config import ABBTwinConfig
from sim_devices.abb._twin import EGM_PORT, IRB2600_REFERENCE_FLANGE, RWS_PORT, ABBControllerTwin, standalone_host

__all__ = ["EGM_PORT", "IRB2600_REFERENCE_FLANGE", "RWS_PORT", "ABBControllerTwin", "ABBTwinConfig",
           "standalone_host"]
