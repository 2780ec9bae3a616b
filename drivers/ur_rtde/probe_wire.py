"""Just enough of UR's wire protocols for a read-only diagnosis, over plain sockets with timeouts
(used by :mod:`drivers.ur_rtde.probe`; the constants are :mod:`drivers.ur_rtde.wire`'s).

RTDE (TCP 30004): request protocol version 2, ask the controller version, set up a small output
recipe, start, read data packages for a window, pause. Dashboard server (TCP 29999): one greeting
line, then one reply line per command line (``robotmode`` -> ``Robotmode: RUNNING``,
``safetystatus``/``safetymode``, ``running`` -> ``Program running: true``, ``is in remote control``
(e-Series 5.6+), ``PolyscopeVersion``).

Nothing here moves the arm, uploads a script or takes control: the probe only reads.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import time
from dataclasses import dataclass

from drivers.ur_rtde import wire
from hil.probe.runner import WireProblem

#: RTDE outputs the probe subscribes to, with their struct codes.
STREAM_OUTPUTS: tuple[tuple[str, str], ...] = (
    ("timestamp", "d"), ("robot_mode", "i"), ("safety_mode", "i"), ("runtime_state", "I"),
)


class WireError(WireProblem):
    """The peer closed, went silent or sent something that is not the protocol."""


@dataclass(frozen=True)
class ControllerVersion:
    major: int
    minor: int
    bugfix: int
    build: int

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.bugfix}.{self.build}"

    @property
    def family(self) -> str:
        """``cb3`` (PolyScope 3.x), ``e_series`` (5.x) or ``other``."""
        return wire.FAMILY_BY_MAJOR.get(self.major, "other")

    @property
    def rtde_rate_hz(self) -> float:
        """The controller's RTDE rate: 125 Hz up to 3.x, 500 Hz from 5.x."""
        return wire.CONTROLLER_RATE_HZ[wire.rate_family(self.major)]


@dataclass(frozen=True)
class StreamSample:
    timestamp_s: float
    robot_mode: int
    safety_mode: int
    runtime_state: int


@dataclass(frozen=True)
class StreamStats:
    """Packages received in a window, and the rate they imply (controller timestamps)."""

    packages: int
    rate_hz: float | None
    last: StreamSample


def resolve(host: str) -> list[str]:
    """IPv4/IPv6 addresses of ``host``. Raises socket.gaierror when it does not resolve."""
    infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    return sorted({str(i[4][0]) for i in infos})


def tcp_connect(host: str, port: int, timeout_s: float) -> float:
    """Open and close one TCP connection; returns the connect time, s. Raises OSError."""
    t0 = time.monotonic()
    with socket.create_connection((host, port), timeout=timeout_s):
        return time.monotonic() - t0


class _Conn:
    def __init__(self, host: str, port: int, timeout_s: float) -> None:
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        self.sock.settimeout(timeout_s)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()

    def recv_exact(self, n: int) -> bytes:
        buf = bytearray()
        while len(buf) < n:
            try:
                chunk = self.sock.recv(n - len(buf))
            except TimeoutError:
                raise WireError(f"silent for {self.sock.gettimeout():g} s") from None
            if not chunk:
                raise WireError("the controller closed the connection")
            buf += chunk
        return bytes(buf)


class RtdeProbe(_Conn):
    """A minimal read-only RTDE client (one connection, closed by :meth:`close`)."""

    def __init__(self, host: str, timeout_s: float) -> None:
        super().__init__(host, wire.RTDE_PORT, timeout_s)

    def _send(self, msg_type: int, body: bytes = b"") -> None:
        self.sock.sendall(wire.HEADER.pack(wire.HEADER.size + len(body), msg_type) + body)

    def _recv(self) -> tuple[int, bytes]:
        size, msg_type = wire.HEADER.unpack(self.recv_exact(wire.HEADER.size))
        if size < wire.HEADER.size:
            raise WireError(f"RTDE message size {size} is below the header size")
        return msg_type, self.recv_exact(size - wire.HEADER.size)

    def _reply(self, expected: int) -> bytes:
        for _ in range(64):  # text messages may come in between
            msg_type, body = self._recv()
            if msg_type == expected:
                return body
            if msg_type not in (wire.TEXT_MESSAGE, wire.DATA_PACKAGE):
                raise WireError(f"expected RTDE message {chr(expected)!r}, got type {msg_type}")
        raise WireError(f"no RTDE {chr(expected)!r} reply among 64 messages")

    def request_protocol_version(self, version: int = wire.PROTOCOL_VERSION) -> bool:
        self._send(wire.REQUEST_PROTOCOL_VERSION, struct.pack(">H", version))
        body = self._reply(wire.REQUEST_PROTOCOL_VERSION)
        return bool(body[:1] == b"\x01")

    def controller_version(self) -> ControllerVersion:
        self._send(wire.GET_CONTROLLER_VERSION)
        body = self._reply(wire.GET_CONTROLLER_VERSION)
        if len(body) < 16:
            raise WireError(f"controller version reply has {len(body)} bytes, expected 16")
        return ControllerVersion(*struct.unpack(">IIII", body[:16]))

    def stream(self, frequency_hz: float, window_s: float, max_packages: int = 2000) -> StreamStats:
        """Subscribe to :data:`STREAM_OUTPUTS`, start, read packages for ``window_s``, pause."""
        names = ",".join(n for n, _ in STREAM_OUTPUTS)
        self._send(wire.SETUP_OUTPUTS, struct.pack(">d", frequency_hz) + names.encode("ascii"))
        body = self._reply(wire.SETUP_OUTPUTS)
        if not body or body[0] == 0 or b"NOT_FOUND" in body:
            raise WireError(f"the controller refused the output recipe ({body[1:].decode(errors='replace')})")
        self._send(wire.START)
        if self._reply(wire.START)[:1] != b"\x01":
            raise WireError("the controller refused to start the RTDE stream")
        codec = struct.Struct(">B" + "".join(c for _, c in STREAM_OUTPUTS))
        samples: list[StreamSample] = []
        deadline = time.monotonic() + window_s
        while time.monotonic() < deadline and len(samples) < max_packages:
            msg_type, data = self._recv()
            if msg_type != wire.DATA_PACKAGE:
                continue
            if len(data) != codec.size:
                raise WireError(f"data package of {len(data)} bytes, expected {codec.size}")
            _rid, ts, rm, sm, rs = codec.unpack(data)
            samples.append(StreamSample(ts, rm, sm, rs))
        with contextlib.suppress(OSError):
            self._send(wire.PAUSE)
        if not samples:
            raise WireError(f"no data package within {window_s:g} s")
        rate: float | None = None
        span = samples[-1].timestamp_s - samples[0].timestamp_s
        if len(samples) >= 3 and span > 0:
            rate = (len(samples) - 1) / span
        return StreamStats(len(samples), rate, samples[-1])


class DashboardProbe(_Conn):
    """A line client for the dashboard server. ``greeting`` is its first line."""

    def __init__(self, host: str, timeout_s: float) -> None:
        super().__init__(host, wire.DASHBOARD_PORT, timeout_s)
        self._buf = bytearray()
        self.greeting = self._line()

    def _line(self) -> str:
        while b"\n" not in self._buf:
            try:
                chunk = self.sock.recv(4096)
            except TimeoutError:
                raise WireError(f"dashboard silent for {self.sock.gettimeout():g} s") from None
            if not chunk:
                raise WireError("the dashboard server closed the connection")
            self._buf += chunk
            if len(self._buf) > 65536:
                raise WireError("dashboard line longer than 64 KiB")
        i = self._buf.index(b"\n")
        line = bytes(self._buf[:i])
        del self._buf[:i + 1]
        return line.decode("utf-8", errors="replace").strip()

    def ask(self, command: str) -> str:
        self.sock.sendall(command.encode("ascii") + b"\n")
        return self._line()
