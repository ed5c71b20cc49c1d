"""RTDE field tables of a PolyScope 5.15 controller (names and wire types) and their packing.

Types follow the UR RTDE guide: BOOL, UINT8, UINT32, UINT64, INT32, DOUBLE, VECTOR3D, VECTOR6D,
VECTOR6INT32, VECTOR6UINT32. Big-endian on the wire. A name the controller does not know is answered
``NOT_FOUND`` in the setup reply, exactly like a real controller (the ur_rtde client then throws).
"""

from __future__ import annotations

import struct
from typing import Any

#: struct format (without byte order) and element count per RTDE type.
TYPE_FORMATS: dict[str, tuple[str, int]] = {
    "BOOL": ("?", 1),
    "UINT8": ("B", 1),
    "UINT32": ("I", 1),
    "UINT64": ("Q", 1),
    "INT32": ("i", 1),
    "DOUBLE": ("d", 1),
    "VECTOR3D": ("3d", 3),
    "VECTOR6D": ("6d", 6),
    "VECTOR6INT32": ("6i", 6),
    "VECTOR6UINT32": ("6I", 6),
}


def _output_fields() -> dict[str, str]:
    fields: dict[str, str] = {"timestamp": "DOUBLE"}
    for name in ("target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q",
                 "actual_qd", "actual_current", "joint_control_output", "actual_TCP_pose", "actual_TCP_speed",
                 "actual_TCP_force", "target_TCP_pose", "target_TCP_speed", "joint_temperatures",
                 "actual_joint_voltage", "payload_inertia", "ft_raw_wrench"):
        fields[name] = "VECTOR6D"
    for name in ("actual_execution_time", "speed_scaling", "target_speed_fraction", "actual_momentum",
                 "actual_main_voltage", "actual_robot_voltage", "actual_robot_current", "standard_analog_input0",
                 "standard_analog_input1", "standard_analog_output0", "standard_analog_output1", "io_current",
                 "euromap67_24V_voltage", "euromap67_24V_current", "tool_analog_input0", "tool_analog_input1",
                 "tool_output_current", "tool_temperature", "tcp_force_scalar", "payload"):
        fields[name] = "DOUBLE"
    for name in ("actual_tool_accelerometer", "elbow_position", "elbow_velocity", "payload_cog"):
        fields[name] = "VECTOR3D"
    for name in ("runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types",
                 "euromap67_input_bits", "euromap67_output_bits", "tool_mode", "tool_analog_input_types",
                 "output_bit_registers0_to_31", "output_bit_registers32_to_63", "input_bit_registers0_to_31",
                 "input_bit_registers32_to_63", "script_control_line"):
        fields[name] = "UINT32"
    fields.update({"robot_mode": "INT32", "safety_mode": "INT32", "safety_status": "INT32",
                   "tool_output_voltage": "INT32", "joint_mode": "VECTOR6INT32",
                   "actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64",
                   "tool_output_mode": "UINT8", "tool_digital_output0_mode": "UINT8",
                   "tool_digital_output1_mode": "UINT8"})
    for i in range(64, 128):
        fields[f"output_bit_register_{i}"] = "BOOL"
        fields[f"input_bit_register_{i}"] = "BOOL"
    for i in range(48):
        fields[f"output_int_register_{i}"] = "INT32"
        fields[f"output_double_register_{i}"] = "DOUBLE"
        fields[f"input_int_register_{i}"] = "INT32"
        fields[f"input_double_register_{i}"] = "DOUBLE"
    return fields


def _input_fields() -> dict[str, str]:
    fields = {
        "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": "VECTOR6D",
    }
    for i in range(64, 128):
        fields[f"input_bit_register_{i}"] = "BOOL"
    for i in range(48):
        fields[f"input_int_register_{i}"] = "INT32"
        fields[f"input_double_register_{i}"] = "DOUBLE"
    return fields


#: Output (controller → client) fields of PolyScope 5.15.
OUTPUT_FIELDS: dict[str, str] = _output_fields()
#: Input (client → controller) fields of PolyScope 5.15.
INPUT_FIELDS: dict[str, str] = _input_fields()


class Recipe:
    """One set-up recipe: names, types, and a compiled big-endian struct for the data payload."""

    def __init__(self, recipe_id: int, names: list[str], table: dict[str, str]) -> None:
        self.id = recipe_id
        self.names = names
        self.types = [table.get(name, "NOT_FOUND") for name in names]
        self.valid = "NOT_FOUND" not in self.types
        self.struct = struct.Struct(">B" + "".join(TYPE_FORMATS[t][0] for t in self.types)) if self.valid else None
        self.sizes = [TYPE_FORMATS[t][1] if t in TYPE_FORMATS else 0 for t in self.types]

    def reply_payload(self) -> bytes:
        return struct.pack(">B", self.id if self.valid else 0) + ",".join(self.types).encode()

    def pack(self, values: list) -> bytes:
        """Pack one value per name (scalars, or sequences for vector types)."""
        flat: list = [self.id]
        for value, size in zip(values, self.sizes):
            if size == 1:
                flat.append(value)
            else:
                flat.extend(value)
        if self.struct is None:
            raise ValueError(f"recipe {self.id} names unknown fields; it carries no data")
        return self.struct.pack(*flat)

    def unpack(self, payload: bytes) -> dict[str, Any]:
        """Decode a data payload (after the recipe id byte). A short packet yields the leading fields
        only, so a client that sends fewer values than the recipe holds does not break the twin."""
        out: dict[str, Any] = {}
        offset = 0
        for name, typ in zip(self.names, self.types):
            fmt, count = TYPE_FORMATS[typ]
            size = struct.calcsize(">" + fmt)
            if offset + size > len(payload):
                break
            values = struct.unpack_from(">" + fmt, payload, offset)
            out[name] = values[0] if count == 1 else list(values)
            offset += size
        return out


def parse_names(text: bytes) -> list[str]:
    """``b"a,b,c,"`` (the client sends a trailing comma) → ``["a", "b", "c"]``."""
    return [n for n in text.decode("ascii", errors="replace").strip().split(",") if n]
