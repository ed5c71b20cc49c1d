"""Twin of the precision rotary table: physics, Modbus TCP/RTU and PI-GCS-2.0-style serial and TCP faces.

See ``docs/rotary_table.md``. The host object ``RotaryTableTwin`` is what the cell embeds;
``make_host`` is the factory for ``TwinProcess``.
"""

from sim_devices.rotary_table._gcs import GcsController, GcsTableTwin
from sim_devices.rotary_table._gcs_tcp import PI_TCP_PORT, GcsTcpTwin
from sim_devices.rotary_table._host import TRANSPORTS, RotaryTableTwin, RotaryTableTwinConfig, make_host
from sim_devices.rotary_table._modbus import ModbusDrive, ModbusTableTwin
from sim_devices.rotary_table._physics import ARCSEC, CommandRefused, TableConfig, TablePhysics, ValueRefused
from sim_devices.rotary_table._register_map import DriveAlarmBits, DriveOpcodes, DriveRegisterMap, DriveStatusBits
from sim_devices.rotary_table._tcp_proxy import TcpFaultProxy

__all__ = [
    "ARCSEC",
    "CommandRefused",
    "DriveAlarmBits",
    "DriveOpcodes",
    "DriveRegisterMap",
    "DriveStatusBits",
    "GcsController",
    "GcsTableTwin",
    "GcsTcpTwin",
    "ModbusDrive",
    "ModbusTableTwin",
    "PI_TCP_PORT",
    "RotaryTableTwin",
    "RotaryTableTwinConfig",
    "TRANSPORTS",
    "TableConfig",
    "TablePhysics",
    "TcpFaultProxy",
    "ValueRefused",
    "make_host",
]
