"""Raw clients of a UR controller's sockets, written from Universal Robots' published documents only
(the RTDE guide; the client interfaces page for 30001-30003), for tests that check the emulator
from a client's side. Nothing here imports the emulator or the driver's codec.
"""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Callable
from typing import Any

_RTDE_HEADER = struct.Struct(">HB")   # RTDE guide: uint16 size (header included), uint8 type
_V, _O, _I, _S, _U = (ord(c) for c in "VOISU")

#: RTDE type -> struct code (RTDE guide's data types).
RTDE_CODES = {"BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
              "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i"}


class RawRtde:
    """An RTDE client on port 30004 (protocol version 2). Blocking, 5 s socket timeout."""

    def __init__(self, host: str) -> None:
        self.sock = socket.create_connection((host, 30004), timeout=5.0)
        self._out_codec: struct.Struct | None = None
        self._out_names: list[str] = []
        self._out_types: list[str] = []
        reply = self._request(_V, struct.pack(">H", 2))
        assert reply == b"\x01", f"protocol version 2 refused: {reply!r}"

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> RawRtde:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _recv_exact(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("RTDE connection closed")
            buf += chunk
        return buf

    def _recv(self) -> tuple[int, bytes]:
        size, typ = _RTDE_HEADER.unpack(self._recv_exact(_RTDE_HEADER.size))
        return typ, self._recv_exact(size - _RTDE_HEADER.size)

    def _send(self, typ: int, body: bytes) -> None:
        self.sock.sendall(_RTDE_HEADER.pack(_RTDE_HEADER.size + len(body), typ) + body)

    def _request(self, typ: int, body: bytes) -> bytes:
        self._send(typ, body)
        reply_type, reply = self._recv()
        assert reply_type == typ, f"reply type {chr(reply_type)!r} to {chr(typ)!r}"
        return reply

    def setup_outputs(self, names: list[str], frequency_hz: float = 125.0) -> tuple[int, list[str]]:
        """Output recipe: (recipe id, variable types as the controller named them)."""
        reply = self._request(_O, struct.pack(">d", frequency_hz) + ",".join(names).encode())
        types = reply[1:].decode().split(",")
        if "NOT_FOUND" not in types:
            self._out_names, self._out_types = names, types
            self._out_codec = struct.Struct(">B" + "".join(RTDE_CODES[t] for t in types))
        return reply[0], types

    def setup_inputs(self, names: list[str]) -> tuple[int, list[str]]:
        """Input recipe: (recipe id, 0 when the set-up failed; the variable types or NOT_FOUND/IN_USE)."""
        reply = self._request(_I, ",".join(names).encode())
        return reply[0], reply[1:].decode().split(",")

    def start(self) -> None:
        assert self._request(_S, b"") == b"\x01"

    def send_inputs(self, recipe_id: int, types: list[str], values: list[Any]) -> None:
        fmt = ">B" + "".join(RTDE_CODES[t] for t in types)
        self._send(_U, struct.pack(fmt, recipe_id, *values))

    def next_outputs(self) -> dict[str, Any]:
        """The next data package of the started output recipe: name -> value."""
        assert self._out_codec is not None, "no output recipe"
        while True:
            typ, body = self._recv()
            if typ == _U:
                break
        flat = self._out_codec.unpack(body)[1:]
        out: dict[str, Any] = {}
        i = 0
        for name, typ_name in zip(self._out_names, self._out_types, strict=True):
            n = int(RTDE_CODES[typ_name][:-1]) if len(RTDE_CODES[typ_name]) > 1 else 1
            out[name] = flat[i] if n == 1 else flat[i:i + n]
            i += n
        return out

    def wait_outputs(self, cond: Callable[[dict[str, Any]], bool], timeout_s: float = 5.0,
                     what: str = "outputs") -> dict[str, Any]:
        """Read data packages until one satisfies ``cond`` (AssertionError after ``timeout_s``)."""
        deadline = time.monotonic() + timeout_s
        while True:
            out = self.next_outputs()
            if cond(out):
                return out
            if time.monotonic() > deadline:
                raise AssertionError(f"{what} not reached within {timeout_s} s: last {out}")


# ---------------------------------------------------------------------------- realtime, 30003
#: The realtime interface's packet ("RealTime 5.10" table of the client interfaces page): an int32
#: message size, then (name, number of doubles) in this order; 152 doubles, 1220 bytes in all.
REALTIME_LAYOUT = (
    ("time", 1), ("q_target", 6), ("qd_target", 6), ("qdd_target", 6), ("i_target", 6),
    ("m_target", 6), ("q_actual", 6), ("qd_actual", 6), ("i_actual", 6), ("i_control", 6),
    ("tool_vector_actual", 6), ("tcp_speed_actual", 6), ("tcp_force", 6), ("tool_vector_target", 6),
    ("tcp_speed_target", 6), ("digital_input_bits", 1), ("motor_temperatures", 6),
    ("controller_timer", 1), ("test_value", 1), ("robot_mode", 1), ("joint_modes", 6),
    ("safety_mode", 1), ("empty_1", 6), ("tool_accelerometer", 3), ("empty_2", 6),
    ("speed_scaling", 1), ("linear_momentum_norm", 1), ("software_only", 1), ("software_only_2", 1),
    ("v_main", 1), ("v_robot", 1), ("i_robot", 1), ("v_actual", 6), ("digital_outputs", 1),
    ("program_state", 1), ("elbow_position", 3), ("elbow_velocity", 3), ("safety_status", 1),
    ("empty_3", 1), ("empty_4", 1), ("empty_5", 1), ("payload_mass", 1), ("payload_cog", 3),
    ("payload_inertia", 6),
)


def recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("connection closed")
        buf += chunk
    return buf


def read_realtime(sock: socket.socket) -> tuple[int, dict[str, Any]]:
    """One realtime packet: (its message size field, name -> value or tuple)."""
    (size,) = struct.unpack(">i", recv_exact(sock, 4))
    body = recv_exact(sock, size - 4)
    flat = struct.unpack(f">{len(body) // 8}d", body)
    out: dict[str, Any] = {}
    i = 0
    for name, n in REALTIME_LAYOUT:
        out[name] = flat[i] if n == 1 else flat[i:i + n]
        i += n
    return size, out


# ---------------------------------------------------------------------- primary/secondary, 30001/2
def read_primary_message(sock: socket.socket) -> tuple[int, bytes]:
    """One primary/secondary message: (message type, the whole message, header included)."""
    size, typ = struct.unpack(">iB", recv_exact(sock, 5))
    return typ, struct.pack(">iB", size, typ) + recv_exact(sock, size - 5)


def parse_version_message(msg: bytes) -> dict[str, Any]:
    """Message type 20, robot message type 3: project name, major, minor, bugfix, build, build date."""
    _size, typ, _ts, _source, robot_msg_type, name_len = struct.unpack(">iBQbbb", msg[:16])
    assert (typ, robot_msg_type) == (20, 3), (typ, robot_msg_type)
    name = msg[16:16 + name_len].decode()
    major, minor, bugfix, build = struct.unpack(">BBii", msg[16 + name_len:26 + name_len])
    return {"project": name, "version": (major, minor, bugfix, build),
            "build_date": msg[26 + name_len:].decode()}


def parse_robot_state(msg: bytes, e_series: bool) -> dict[int, dict[str, Any]]:
    """Message type 16: sub-package type -> its fields (robot mode 0, joint 1, cartesian 4; others
    by size only)."""
    size, typ = struct.unpack(">iB", msg[:5])
    assert typ == 16
    assert size == len(msg)
    out: dict[int, dict[str, Any]] = {}
    i = 5
    while i < len(msg):
        psize, ptype = struct.unpack(">iB", msg[i:i + 5])
        body = msg[i + 5:i + psize]
        if ptype == 0:
            fmt = ">Q???????BBddd" + ("B" if e_series else "")
            v = struct.unpack(fmt, body)
            out[0] = {"size": psize, "timestamp": v[0], "connected": v[1], "enabled": v[2],
                      "power_on": v[3], "emergency_stopped": v[4], "protective_stopped": v[5],
                      "program_running": v[6], "program_paused": v[7], "robot_mode": v[8],
                      "control_mode": v[9], "target_speed_fraction": v[10], "speed_scaling": v[11]}
        elif ptype == 1:
            joints = [struct.unpack(">dddffffB", body[j * 41:(j + 1) * 41]) for j in range(6)]
            out[1] = {"size": psize, "q_actual": tuple(j[0] for j in joints),
                      "q_target": tuple(j[1] for j in joints), "joint_mode": tuple(j[7] for j in joints)}
        elif ptype == 4:
            v = struct.unpack(">12d", body)
            out[4] = {"size": psize, "tcp": v[:6], "tcp_offset": v[6:]}
        else:
            out[ptype] = {"size": psize}
        i += psize
    return out
