"""Rotary tables: the ``RotaryTable`` interface, the settings, the register map and adapters.

``create(settings, name=...)`` builds the adapter that ``settings.adapter`` names:
``modbus_tcp`` / ``modbus_rtu`` (``ModbusTable``, a servo drive described by a ``RegisterMap``) or
``gcs_serial`` / ``gcs_tcp`` (``GcsTable``, a PI GCS 2.0 controller on its serial or TCP interface).
The table is not opened yet: call ``open()`` (servo on, reference move if needed) or use it as a
context manager.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from drivers._extras import load_adapter
from drivers._settings import SettingsUnion
from drivers.rotary_table._interface import CommandRefused, RotaryTable, TableFault, TableState
from drivers.rotary_table._registers import AlarmBits, Opcodes, RegisterMap, StatusBits
from drivers.rotary_table._settings import (
    GcsSerialSettings,
    GcsTcpSettings,
    ModbusRtuSettings,
    ModbusTcpSettings,
    RotaryTableSettings,
)

if TYPE_CHECKING:
    from drivers.rotary_table._gcs import GcsTable
    from drivers.rotary_table._modbus import ModbusTable

_ADAPTER_CLASSES = {  # class name → (module, client libraries): imported when first needed (drivers._extras)
    "GcsTable": ("drivers.rotary_table._gcs", ("serial",)),
    "ModbusTable": ("drivers.rotary_table._modbus", ("pymodbus", "serial")),
}


def __getattr__(name: str) -> Any:
    if name in _ADAPTER_CLASSES:
        return _adapter_class(name, "rotary_table", name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _adapter_class(name: str, device: str, adapter: str) -> Any:
    module, libraries = _ADAPTER_CLASSES[name]
    return load_adapter(module, name, device=device, adapter=adapter, libraries=libraries, extra="rotary-table")


_SETTINGS_UNION: SettingsUnion[RotaryTableSettings] = SettingsUnion(RotaryTableSettings, "rotary_table")
ADAPTERS = tuple(_SETTINGS_UNION.models)


def create(settings: RotaryTableSettings | Mapping[str, Any], *, name: str = "rotary_table") -> RotaryTable:
    """The rotary-table adapter for ``settings`` (a model, or a mapping validated as one).

    Parameters
    ----------
    settings : RotaryTableSettings or mapping
        The station file's ``devices.rotary_table`` entry.
    name : str
        Device name used in every error.

    Raises
    ------
    SettingsError
        For a mapping that is not valid settings (one line naming the adapter and the setting).
    """
    checked = _SETTINGS_UNION.validate(settings, name=name)
    table_class = "GcsTable" if isinstance(checked, GcsSerialSettings | GcsTcpSettings) else "ModbusTable"
    adapter_class = _adapter_class(table_class, name, checked.adapter)
    table: RotaryTable = adapter_class(checked, name=name)
    return table


__all__ = [
    "ADAPTERS",
    "AlarmBits",
    "CommandRefused",
    "GcsSerialSettings",
    "GcsTable",
    "GcsTcpSettings",
    "ModbusRtuSettings",
    "ModbusTable",
    "ModbusTcpSettings",
    "Opcodes",
    "RegisterMap",
    "RotaryTable",
    "RotaryTableSettings",
    "StatusBits",
    "TableFault",
    "TableState",
    "create",
]
