"""The UR controller's wire facts the driver and its probe share, written once (reference/ur-rtde.md,
Universal Robots' RTDE guide): the TCP ports, the RTDE header and message types, the codes of
``robot_mode``, ``safety_mode``, ``runtime_state`` and the ``safety_status_bits``, and the RTDE rate
of each controller family. No I/O.

RTDE (TCP 30004) is big-endian; every message starts with the header ``>HB``: the total size
including the 3-byte header, then the type byte.
"""

from __future__ import annotations

import struct
from enum import IntEnum, IntFlag
from typing import Literal

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003

HEADER = struct.Struct(">HB")
#: RTDE message types (the type byte of the header).
REQUEST_PROTOCOL_VERSION = ord("V")  # client: >H version; reply one byte, 1 = accepted
GET_CONTROLLER_VERSION = ord("v")  # reply >IIII major, minor, bugfix, build
SETUP_OUTPUTS = ord("O")  # client: >d frequency + comma-joined names; reply recipe id (0 = refused) + types
SETUP_INPUTS = ord("I")
START = ord("S")  # reply one byte, 1 = ok
PAUSE = ord("P")  # reply one byte, 1 = ok
DATA_PACKAGE = ord("U")  # recipe id, then the values in the order of the recipe
TEXT_MESSAGE = ord("M")
PROTOCOL_VERSION = 2

ControllerFamily = Literal["cb3", "e_series"]
#: RTDE rate of each controller family (Hz): CB3 (PolyScope 3.x) 125, e-Series (5.x) 500.
CONTROLLER_RATE_HZ: dict[ControllerFamily, float] = {"cb3": 125.0, "e_series": 500.0}
#: The family of each supported PolyScope major version.
FAMILY_BY_MAJOR: dict[int, ControllerFamily] = {3: "cb3", 5: "e_series"}


def rate_family(major: int) -> ControllerFamily:
    """The family whose RTDE rate a controller of this major version streams at: the client picks
    125 Hz when major <= 3, else 500 Hz."""
    return "cb3" if major <= 3 else "e_series"


class RobotModeCode(IntEnum):
    """RTDE ``robot_mode`` (the dashboard's ``robotmode`` names)."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    UPDATING_FIRMWARE = 8


class SafetyModeCode(IntEnum):
    """RTDE ``safety_mode`` (the dashboard's ``safetymode`` names)."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    VALIDATE_JOINT_ID = 10
    UNDEFINED_SAFETY_MODE = 11
    AUTOMATIC_MODE_SAFEGUARD_STOP = 12
    SYSTEM_THREE_POSITION_ENABLING_STOP = 13


class RuntimeState(IntEnum):
    """RTDE ``runtime_state``; a program runs when it is PLAYING."""

    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


class SafetyStatusBit(IntFlag):
    """The RTDE ``safety_status_bits`` the driver reads (ur-rtde ``SafetyStatus``)."""

    PROTECTIVE_STOPPED = 1 << 2
    SAFEGUARD_STOPPED = 1 << 4
    SYSTEM_EMERGENCY_STOPPED = 1 << 5
    ROBOT_EMERGENCY_STOPPED = 1 << 6
    EMERGENCY_STOPPED = 1 << 7
    VIOLATION = 1 << 8
    FAULT = 1 << 9
