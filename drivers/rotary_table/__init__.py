"""Rotary tables: the ``RotaryTable`` interface and adapters."""

from drivers.rotary_table._interface import RotaryTable, TableFault, TableState

__all__ = ["RotaryTable", "TableFault", "TableState"]
