"""RTDE wire format (protocol version 2): message framing, UR's standard variable table, recipe packing.

Every message is a big-endian uint16 total length (header included), a uint8 type, then the payload.
Types of variables follow UR's published RTDE table; clients decode with their own copy of it.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

HEADER = struct.Struct(">HB")

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
CONTROL_PACKAGE_START = ord("S")
CONTROL_PACKAGE_PAUSE = ord("P")

# RTDE type name -> struct format (big-endian applied by the caller).
TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
TYPE_WIDTH = {name: int(fmt[0]) if fmt[0].isdigit() else 1 for name, fmt in TYPE_FORMATS.items()}

# Controller outputs (readable by an output recipe), from UR's RTDE guide.
_OUTPUTS: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D",
    "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "actual_current": "VECTOR6D",
    "actual_current_window": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D",
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "euromap67_input_bits": "UINT32",
    "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE",
    "euromap67_24V_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D",
    "script_control_line": "UINT32",
    "ft_raw_wrench": "VECTOR6D",
    "joint_position_deviation_ratio": "DOUBLE",
    "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "INT32",
    "actual_current_as_torque": "VECTOR6D",
}

# Controller inputs (writable by an input recipe).
_INPUTS: dict[str, str] = {
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}

_REGISTER = re.compile(r"^(input|output)_(bit|int|double)_register_(\d+)$")
_REGISTER_TYPES = {"bit": "BOOL", "int": "INT32", "double": "DOUBLE"}


def _register_type(name: str) -> tuple[str, str] | None:
    """('input'|'output', type) of a numbered register name, or None if it is not a valid register."""
    match = _REGISTER.match(name)
    if not match:
        return None
    side, kind, index = match.group(1), match.group(2), int(match.group(3))
    if kind == "bit" and not 64 <= index <= 127:
        return None
    if kind != "bit" and not 0 <= index <= 47:
        return None
    return side, _REGISTER_TYPES[kind]


def output_type(name: str) -> str | None:
    """RTDE type of a variable an output recipe may read, None if the controller does not know it."""
    if name in _OUTPUTS:
        return _OUTPUTS[name]
    reg = _register_type(name)
    if reg:  # both input and output registers are readable
        return reg[1]
    return None


def input_type(name: str) -> str | None:
    """RTDE type of a variable an input recipe may write, None if it is not writable."""
    if name in _INPUTS:
        return _INPUTS[name]
    reg = _register_type(name)
    if reg and reg[0] == "input":
        return reg[1]
    return None


@dataclass(frozen=True)
class Recipe:
    """A numbered list of variables with their types and a compiled struct for packing."""

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]
    packer: struct.Struct

    @classmethod
    def build(cls, recipe_id: int, names: list[str], types: list[str]) -> Recipe:
        fmt = ">" + "".join(TYPE_FORMATS[t] for t in types)
        return cls(recipe_id, tuple(names), tuple(types), struct.Struct(fmt))

    def pack(self, values: list) -> bytes:
        """Flatten per-variable values (scalars or sequences) into the wire payload (after the id byte)."""
        flat: list = []
        for value, type_name in zip(values, self.types, strict=True):
            if TYPE_WIDTH[type_name] == 1:
                flat.append(value)
            else:
                flat.extend(value)
        return self.packer.pack(*flat)

    def unpack(self, payload: bytes) -> dict[str, object]:
        """Decode a payload into {name: value}; raises struct.error if the size does not match."""
        flat = self.packer.unpack(payload)
        out: dict[str, object] = {}
        i = 0
        for name, type_name in zip(self.names, self.types, strict=True):
            width = TYPE_WIDTH[type_name]
            out[name] = flat[i] if width == 1 else tuple(flat[i : i + width])
            i += width
        return out


def frame(message_type: int, payload: bytes = b"") -> bytes:
    """One RTDE message: length, type, payload."""
    return HEADER.pack(HEADER.size + len(payload), message_type) + payload


def split_names(payload: bytes) -> list[str]:
    """Comma-separated variable names as sent by clients (ur-rtde adds a trailing comma)."""
    text = payload.decode("ascii", errors="replace")
    return [name.strip() for name in text.split(",") if name.strip()]
