"""Rotary tables: the ``RotaryTable`` interface and adapters.

``create(config, name=...)`` picks the adapter from ``config["adapter"]``; the other keys are the
adapter's settings:

- ``modbus_tcp``: ``host``, ``port`` (502), ``unit`` (1), ``register_map`` (mapping, see
  ``RegisterMap``), ``timeout`` (0.5 s), ``retries`` (2), ``poll_interval`` (0.01 s).
- ``modbus_rtu``: ``port`` (serial device path), ``baudrate`` (115200), ``unit``, ``register_map``,
  ``timeout``, ``retries``, ``poll_interval``.
- ``gcs_serial``: ``port`` (path or pyserial URL), ``baudrate`` (115200), ``axis`` ("1"), ``timeout``,
  ``retries``, ``poll_interval``.

The returned table is not connected yet: use it as a context manager or call ``connect()``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from drivers.rotary_table._gcs import GcsTable
from drivers.rotary_table._interface import RotaryTable, TableFault, TableState
from drivers.rotary_table._modbus import ModbusTable
from drivers.rotary_table._registers import AlarmBits, Opcodes, RegisterMap, StatusBits

ADAPTERS = ("modbus_tcp", "modbus_rtu", "gcs_serial")
_COMMON = {"timeout", "retries", "poll_interval"}
_SETTINGS = {
    "modbus_tcp": ({"host"}, {"port", "unit", "register_map"} | _COMMON),
    "modbus_rtu": ({"port"}, {"baudrate", "unit", "register_map"} | _COMMON),
    "gcs_serial": ({"port"}, {"baudrate", "axis"} | _COMMON),
}


def create(config: Mapping[str, Any], *, name: str = "rotary_table") -> RotaryTable:
    """Build the rotary-table adapter described by ``config`` (see the module docstring)."""
    settings = dict(config)
    adapter = settings.pop("adapter", None)
    if adapter not in _SETTINGS:
        raise ValueError(f"{name}: unknown rotary_table adapter {adapter!r}; choose one of {list(ADAPTERS)}")
    required, optional = _SETTINGS[adapter]
    missing = required - set(settings)
    unknown = set(settings) - required - optional
    if missing or unknown:
        problems = []
        if missing:
            problems.append(f"missing {sorted(missing)}")
        if unknown:
            problems.append(f"unknown {sorted(unknown)}")
        raise ValueError(f"{name}: rotary_table adapter {adapter!r}: {', '.join(problems)}; "
                         f"allowed settings {sorted(required | optional)}")
    if "register_map" in settings:
        settings["register_map"] = RegisterMap.from_config(settings["register_map"])
    if adapter == "modbus_tcp":
        return ModbusTable.tcp(name, **settings)
    if adapter == "modbus_rtu":
        return ModbusTable.rtu(name, **settings)
    return GcsTable(name, **settings)


__all__ = [
    "ADAPTERS",
    "AlarmBits",
    "GcsTable",
    "ModbusTable",
    "Opcodes",
    "RegisterMap",
    "RotaryTable",
    "StatusBits",
    "TableFault",
    "TableState",
    "create",
]
