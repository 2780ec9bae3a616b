"""RTDE wire format (server side), as the ``ur-rtde`` 1.6.5 client speaks it.

Every message: ``>HB`` header (total size including the 3-byte header, type byte), then a body.
Types and value layouts follow Universal Robots' RTDE guide and ``reference/ur-rtde.md``.
"""

from __future__ import annotations

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

# RTDE type name -> struct code (without the leading '>').
TYPE_CODES: dict[str, str] = {
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

_VEC6 = "VECTOR6D"

# Outputs the emulator can serve: name -> RTDE type. The client parses by its own table
# (6 doubles per vector except the 3D ones named below), so these types must agree with it.
OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": _VEC6, "target_qd": _VEC6, "target_qdd": _VEC6, "target_current": _VEC6,
    "target_moment": _VEC6, "actual_q": _VEC6, "actual_qd": _VEC6, "actual_qdd": _VEC6,
    "actual_current": _VEC6, "actual_current_as_torque": _VEC6, "actual_moment": _VEC6,
    "joint_control_output": _VEC6, "actual_TCP_pose": _VEC6, "actual_TCP_speed": _VEC6,
    "actual_TCP_force": _VEC6, "target_TCP_pose": _VEC6, "target_TCP_speed": _VEC6,
    "actual_digital_input_bits": "UINT64", "joint_temperatures": _VEC6,
    "actual_execution_time": "DOUBLE", "robot_mode": "INT32", "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32", "safety_status": "INT32", "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE", "actual_joint_voltage": _VEC6,
    "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
    "robot_status_bits": "UINT32", "safety_status_bits": "UINT32",
    "standard_analog_input0": "DOUBLE", "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE", "standard_analog_output1": "DOUBLE",
    "ft_raw_wrench": _VEC6, "payload": "DOUBLE", "payload_cog": "VECTOR3D",
    "payload_inertia": _VEC6, "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D",
    "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
    **{f"output_int_register_{i}": "INT32" for i in range(48)},
    **{f"output_double_register_{i}": "DOUBLE" for i in range(48)},
    # The RTDE guide lists the general purpose input registers among the outputs too: a client reads
    # back what any client (or a program) wrote to them.
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    **{f"input_bit_register_{i}": "BOOL" for i in range(64, 128)},
    **{f"input_int_register_{i}": "INT32" for i in range(48)},
    **{f"input_double_register_{i}": "DOUBLE" for i in range(48)},
}

# Inputs a client may set up: name -> RTDE type.
INPUT_TYPES: dict[str, str] = {
    **{f"input_int_register_{i}": "INT32" for i in range(48)},
    **{f"input_double_register_{i}": "DOUBLE" for i in range(48)},
    **{f"input_bit_register_{i}": "BOOL" for i in range(64, 128)},
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": _VEC6,
    "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
}


#: The type an input setup reply names for a variable another connection already writes (RTDE guide:
#: the recipe id is then 0 and the set-up failed).
IN_USE = "IN_USE"
#: The type a setup reply names for a variable the controller does not know.
NOT_FOUND = "NOT_FOUND"


class ProtocolViolationError(Exception):
    """The peer sent bytes that are not valid RTDE (the connection is closed)."""


def pack(msg_type: int, body: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(body), msg_type) + body


def split_names(body: bytes) -> list[str]:
    """Comma-joined variable names; the ur-rtde client appends a trailing comma (dropped here)."""
    return [n for n in body.decode("ascii", errors="replace").strip().split(",") if n]


@dataclass(frozen=True)
class Recipe:
    """A set-up recipe: id, names, their RTDE types and the struct that (un)packs one data package."""

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]
    codec: struct.Struct
    sizes: tuple[int, ...]  # values per name (1, 3 or 6)

    @classmethod
    def build(cls, recipe_id: int, names: list[str], table: dict[str, str]) -> Recipe | None:
        """None when a name is unknown (the caller answers NOT_FOUND)."""
        if any(n not in table for n in names):
            return None
        types = tuple(table[n] for n in names)
        codes = [TYPE_CODES[t] for t in types]
        sizes = tuple(int(c[:-1]) if len(c) > 1 else 1 for c in codes)
        return cls(recipe_id, tuple(names), types, struct.Struct(">" + "".join(codes)), sizes)

    def unpack(self, payload: bytes) -> dict[str, object]:
        """Decode one input data package body (after the recipe id byte) into name -> value."""
        if len(payload) != self.codec.size:
            raise ProtocolViolationError(
                f"recipe {self.recipe_id}: {len(payload)} bytes, expected {self.codec.size}")
        flat = self.codec.unpack(payload)
        out: dict[str, object] = {}
        i = 0
        for name, n in zip(self.names, self.sizes, strict=True):
            out[name] = flat[i] if n == 1 else tuple(flat[i:i + n])
            i += n
        return out
