"""The state messages of UR's older client interfaces, encoded from the emulated controller.

Universal Robots' "client interfaces" page (Remote Control via TCP/IP) documents three streams
that a client reads by connecting (all big-endian; each port also accepts URScript):

* **Realtime, port 30003**: one packet per controller period (125 Hz CB3, 500 Hz e-Series):
  ``int32`` message size (the whole packet, these 4 bytes included) then doubles only.
  :data:`REALTIME_FIELDS` is the page's latest table ("RealTime 5.10", 1220 bytes): the emulator
  sends it for both emulated versions (3.15 and 5.11).
* **Primary 30001 / secondary 30002**: on connect the **version message** (message type 20,
  robot message type 3), then a **robot state message** (message type 16) at 10 Hz made of
  sub-packages, each ``int32`` size (its own 5-byte header included), ``uint8`` type:
  robot mode data (0), joint data (1), cartesian info (4). Clients (python-urx, the ROS driver's
  client library) skip the sub-packages they do not parse by their size.

Values the model does not simulate (currents, torques, forces, accelerometer, elbow, payload) are
zeros, as in the RTDE outputs. Nothing here imports the host's UR driver: the layouts are built
from the documents alone. No sockets here: the server sends what these functions return.
"""

from __future__ import annotations

import struct
from typing import Any, Protocol

#: (field, number of doubles) of a realtime packet after its int32 size, in wire order.
REALTIME_FIELDS: tuple[tuple[str, int], ...] = (
    ("time", 1), ("q_target", 6), ("qd_target", 6), ("qdd_target", 6), ("i_target", 6),
    ("m_target", 6), ("q_actual", 6), ("qd_actual", 6), ("i_actual", 6), ("i_control", 6),
    ("tool_vector_actual", 6), ("tcp_speed_actual", 6), ("tcp_force", 6),
    ("tool_vector_target", 6), ("tcp_speed_target", 6), ("digital_input_bits", 1),
    ("motor_temperatures", 6), ("controller_timer", 1), ("test_value", 1), ("robot_mode", 1),
    ("joint_modes", 6), ("safety_mode", 1), ("reserved_1", 6), ("tool_accelerometer_values", 3),
    ("reserved_2", 6), ("speed_scaling", 1), ("linear_momentum_norm", 1), ("reserved_3", 1),
    ("reserved_4", 1), ("v_main", 1), ("v_robot", 1), ("i_robot", 1), ("v_actual", 6),
    ("digital_outputs", 1), ("program_state", 1), ("elbow_position", 3), ("elbow_velocity", 3),
    ("safety_status", 1), ("reserved_5", 1), ("reserved_6", 1), ("reserved_7", 1),
    ("payload_mass", 1), ("payload_cog", 3), ("payload_inertia", 6),
)
REALTIME_DOUBLES = sum(n for _, n in REALTIME_FIELDS)
REALTIME_CODEC = struct.Struct(f">i{REALTIME_DOUBLES}d")
REALTIME_SIZE = REALTIME_CODEC.size  # 1220

#: The realtime field each double comes from: the RTDE output of the same meaning.
_REALTIME_SOURCE: dict[str, str] = {
    "time": "timestamp", "q_target": "target_q", "qd_target": "target_qd", "qdd_target": "target_qdd",
    "q_actual": "actual_q", "qd_actual": "actual_qd", "tool_vector_actual": "actual_TCP_pose",
    "tcp_speed_actual": "actual_TCP_speed", "tool_vector_target": "target_TCP_pose",
    "tcp_speed_target": "target_TCP_speed", "digital_input_bits": "actual_digital_input_bits",
    "motor_temperatures": "joint_temperatures", "controller_timer": "actual_execution_time",
    "robot_mode": "robot_mode", "joint_modes": "joint_mode", "safety_mode": "safety_mode",
    "speed_scaling": "speed_scaling", "v_main": "actual_main_voltage",
    "v_robot": "actual_robot_voltage", "digital_outputs": "actual_digital_output_bits",
    "program_state": "runtime_state", "safety_status": "safety_status",
}

MESSAGE_TYPE_ROBOT_STATE = 16
MESSAGE_TYPE_ROBOT_MESSAGE = 20
ROBOT_MESSAGE_TYPE_VERSION = 3
#: The robot message's ``source`` byte for the version message.
MESSAGE_SOURCE_CONTROLLER = -2
PACKAGE_ROBOT_MODE_DATA = 0
PACKAGE_JOINT_DATA = 1
PACKAGE_CARTESIAN_INFO = 4
#: Primary / secondary state messages per second.
STATE_RATE_HZ = 10.0

_HEADER = struct.Struct(">iB")
# Robot mode data: timestamp; real robot connected, enabled, power on, emergency stopped, protective
# stopped, program running, program paused; robot mode, control mode; target speed fraction, speed
# scaling, target speed fraction limit; e-Series (5.x) one reserved byte more.
_ROBOT_MODE_CB3 = struct.Struct(">Q???????BBddd")
_ROBOT_MODE_E_SERIES = struct.Struct(">Q???????BBdddB")
# Joint data, per joint: q actual, q target, qd actual (double); I actual, V actual, T motor,
# T micro (float); joint mode (uint8).
_JOINT = struct.Struct(">dddffffB")
# Cartesian info: TCP pose X, Y, Z, Rx, Ry, Rz, then the TCP offset (6 doubles).
_CARTESIAN = struct.Struct(">12d")


class StateSource(Protocol):
    """What the encoders read of the controller: its RTDE outputs and version."""

    @property
    def timestamp_s(self) -> float: ...

    def output(self, name: str, rtde_type: str) -> Any: ...


def _values(ctl: StateSource, name: str, n: int) -> list[float]:
    source = _REALTIME_SOURCE.get(name)
    if source is None:
        return [0.0] * n
    v = ctl.output(source, "DOUBLE" if n == 1 else "VECTOR6D")
    return [float(v)] if n == 1 else [float(x) for x in v]


def realtime_packet(ctl: StateSource) -> bytes:
    """One realtime-interface packet (port 30003) of the controller's current state."""
    flat: list[float] = []
    for name, n in REALTIME_FIELDS:
        flat.extend(_values(ctl, name, n))
    return REALTIME_CODEC.pack(REALTIME_SIZE, *flat)


def _message(msg_type: int, body: bytes) -> bytes:
    return _HEADER.pack(_HEADER.size + len(body), msg_type) + body


def version_message(major: int, minor: int, bugfix: int, build: int, timestamp_s: float) -> bytes:
    """The primary/secondary version message: project name, major, minor, bugfix, build, build date."""
    project = b"URControl"
    body = (struct.pack(">Qbbb", int(timestamp_s * 1e6), MESSAGE_SOURCE_CONTROLLER,
                        ROBOT_MESSAGE_TYPE_VERSION, len(project))
            + project + struct.pack(">BBii", major, minor, bugfix, build) + b"21-11-2026, 12:00:00")
    return _message(MESSAGE_TYPE_ROBOT_MESSAGE, body)


def robot_state_message(ctl: StateSource, e_series: bool) -> bytes:
    """A primary/secondary robot state message: robot mode data, joint data, cartesian info."""
    o = ctl.output
    robot_mode = int(o("robot_mode", "INT32"))
    safety = int(o("safety_mode", "INT32"))
    runtime = int(o("runtime_state", "UINT32"))
    status_bits = int(o("robot_status_bits", "UINT32"))
    speed = float(o("speed_scaling", "DOUBLE"))
    flags = (True, True, bool(status_bits & 1), safety == 7, safety == 3, runtime == 2, runtime == 4)
    ts_us = int(ctl.timestamp_s * 1e6)
    if e_series:
        mode = _ROBOT_MODE_E_SERIES.pack(ts_us, *flags, robot_mode, 0, speed, speed, 1.0, 0)
    else:
        mode = _ROBOT_MODE_CB3.pack(ts_us, *flags, robot_mode, 0, speed, speed, 1.0)
    q, q_target, qd = o("actual_q", ""), o("target_q", ""), o("actual_qd", "")
    temps, jm = o("joint_temperatures", ""), o("joint_mode", "")
    v_robot = float(o("actual_robot_voltage", "DOUBLE"))
    joints = b"".join(_JOINT.pack(q[i], q_target[i], qd[i], 0.0, v_robot, temps[i], temps[i], jm[i])
                      for i in range(6))
    cart = _CARTESIAN.pack(*o("actual_TCP_pose", ""), *([0.0] * 6))
    body = b"".join(_message(t, b) for t, b in ((PACKAGE_ROBOT_MODE_DATA, mode),
                                                 (PACKAGE_JOINT_DATA, joints),
                                                 (PACKAGE_CARTESIAN_INFO, cart)))
    return _message(MESSAGE_TYPE_ROBOT_STATE, body)
