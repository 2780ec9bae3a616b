"""The emulator's sockets: RTDE (30004), the primary (30001), secondary (30002) and realtime (30003)
client interfaces, the dashboard (29999) and the fault control channel (30200).

One asyncio loop runs everything: a tick task advances the controller at its rate, streams data
packages to every started RTDE connection, a realtime packet to every 30003 client each tick and a
robot state message to every 30001/30002 client at 10 Hz; the servers feed requests (scripts on
30001-30003, dashboard lines, RTDE input packages) into the controller.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import struct
import sys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from emulators.ursim import client_interfaces as ci
from emulators.ursim import protocol as proto
from emulators.ursim.controller import UrController
from emulators.ursim.dashboard import dashboard_reply

RTDE_PORT = 30004
PRIMARY_PORT = 30001
SECONDARY_PORT = 30002
SCRIPT_PORT = 30003   # the realtime interface: takes scripts, streams realtime packets
DASHBOARD_PORT = 29999
CONTROL_PORT = 30200
_MAX_WRITE_BUFFER = 1 << 20
#: A state stream (30001-30003) client that has this much unsent is not sent the next message (the
#: stream skips, the connection stays: ur-rtde's script client never reads its 30003 socket).
_MAX_STREAM_BACKLOG = 1 << 14
#: Kernel send buffer of a stream connection (bytes; Linux doubles it): about 50 realtime packets.
_STREAM_SNDBUF = 1 << 15
_READ_TIMEOUT_S = 3600.0
#: Recipe ids are one byte on the wire; id 0 means "setup failed".
MAX_RECIPE_ID = 255
#: Below this an output frequency is treated like 0 (the controller's rate): a denormal one would
#: make frequency_hz / freq overflow.
MIN_OUTPUT_FREQUENCY_HZ = 1e-3


@dataclass
class Ports:
    rtde: int = RTDE_PORT
    script: int = SCRIPT_PORT
    dashboard: int = DASHBOARD_PORT
    control: int = CONTROL_PORT
    primary: int = PRIMARY_PORT
    secondary: int = SECONDARY_PORT


class RtdeConnection:
    """One RTDE client: its recipes, whether it streams, at which divider of the controller rate."""

    def __init__(self, sim: Emulator, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.sim = sim
        self.reader = reader
        self.writer = writer
        self.output: proto.Recipe | None = None
        self.every = 1
        self.started = False
        self.inputs: dict[int, proto.Recipe] = {}

    def send(self, msg_type: int, body: bytes = b"") -> None:
        if self.writer.transport.get_write_buffer_size() > _MAX_WRITE_BUFFER:
            self.writer.transport.abort()  # a client that stopped reading
            return
        self.writer.write(proto.pack(msg_type, body))

    def on_tick(self, tick: int) -> None:
        if not self.started or self.output is None or tick % self.every:
            return
        ctl = self.sim.ctl
        flat: list[object] = []
        for name, typ, n in zip(self.output.names, self.output.types, self.output.sizes, strict=True):
            v = ctl.output(name, typ)
            if n == 1:
                flat.append(v)
            else:
                flat.extend(v)
        try:
            body = bytes([self.output.recipe_id]) + self.output.codec.pack(*flat)
        except struct.error as exc:
            self.sim.warn(f"rtde_pack_failed {exc}")
            return
        self.send(proto.DATA_PACKAGE, body)

    async def run(self) -> None:
        try:
            while True:
                header = await self.reader.readexactly(proto.HEADER.size)
                size, msg_type = proto.HEADER.unpack(header)
                if size < proto.HEADER.size:
                    raise proto.ProtocolViolationError(f"message size {size} < 3")
                body = await self.reader.readexactly(size - proto.HEADER.size)
                await self.handle(msg_type, body)
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        except proto.ProtocolViolationError as exc:
            self.sim.warn(f"rtde_protocol_violation {exc}")
        finally:
            self.sim.rtde_conns.discard(self)
            self.sim.release_inputs(self)
            self.writer.close()

    async def _slow(self) -> None:
        if self.sim.ctl.slow_responses_s > 0:
            await asyncio.sleep(self.sim.ctl.slow_responses_s)

    async def handle(self, msg_type: int, body: bytes) -> None:
        ctl = self.sim.ctl
        if msg_type == proto.DATA_PACKAGE:
            if not body:
                raise proto.ProtocolViolationError("empty data package")
            recipe = self.inputs.get(body[0])
            if recipe is None:
                self.sim.warn(f"rtde_unknown_input_recipe {body[0]}")
                return
            ctl.set_inputs(recipe.unpack(body[1:]))
            return
        await self._slow()
        if msg_type == proto.REQUEST_PROTOCOL_VERSION:
            self.send(proto.REQUEST_PROTOCOL_VERSION, b"\x01")
        elif msg_type == proto.GET_URCONTROL_VERSION:
            v = ctl.version
            self.send(proto.GET_URCONTROL_VERSION, struct.pack(">IIII", v.major, v.minor, v.bugfix, v.build))
        elif msg_type == proto.CONTROL_PACKAGE_SETUP_OUTPUTS:
            if len(body) < 8:
                raise proto.ProtocolViolationError("output setup without frequency")
            (freq,) = struct.unpack(">d", body[:8])
            names = proto.split_names(body[8:])
            recipe = proto.Recipe.build(1, names, proto.OUTPUT_TYPES)
            if recipe is None:
                types = [proto.OUTPUT_TYPES.get(n, proto.NOT_FOUND) for n in names]
                self.send(proto.CONTROL_PACKAGE_SETUP_OUTPUTS, b"\x00" + ",".join(types).encode())
                self.sim.warn(f"rtde_outputs_not_found {[n for n in names if n not in proto.OUTPUT_TYPES]}")
                return
            self.output = recipe
            # <= 0, NaN or a denormal (frequency_hz / freq would overflow): the controller's rate
            freq = freq if freq >= MIN_OUTPUT_FREQUENCY_HZ else ctl.frequency_hz
            self.every = max(1, round(ctl.frequency_hz / min(freq, ctl.frequency_hz)))
            self.send(proto.CONTROL_PACKAGE_SETUP_OUTPUTS, b"\x01" + ",".join(recipe.types).encode())
        elif msg_type == proto.CONTROL_PACKAGE_SETUP_INPUTS:
            names = proto.split_names(body)
            rid = len(self.inputs) + 1
            if rid > MAX_RECIPE_ID:
                raise proto.ProtocolViolationError(f"more than {MAX_RECIPE_ID} input recipes")
            in_recipe = proto.Recipe.build(rid, names, proto.INPUT_TYPES)
            in_use = self.sim.inputs_in_use(self, names)
            if in_recipe is None or in_use:
                # RTDE guide: recipe id 0 (set-up failed), NOT_FOUND / IN_USE in place of the type
                types = [proto.IN_USE if n in in_use else proto.INPUT_TYPES.get(n, proto.NOT_FOUND)
                         for n in names]
                self.send(proto.CONTROL_PACKAGE_SETUP_INPUTS, b"\x00" + ",".join(types).encode())
                if in_use:
                    self.sim.warn(f"rtde_inputs_in_use {sorted(in_use)}")
                return
            self.sim.claim_inputs(self, names)
            self.inputs[rid] = in_recipe
            self.send(proto.CONTROL_PACKAGE_SETUP_INPUTS, bytes([rid]) + ",".join(in_recipe.types).encode())
        elif msg_type == proto.CONTROL_PACKAGE_START:
            ok = self.output is not None
            self.send(proto.CONTROL_PACKAGE_START, b"\x01" if ok else b"\x00")
            self.started = ok
        elif msg_type == proto.CONTROL_PACKAGE_PAUSE:
            self.started = False
            self.send(proto.CONTROL_PACKAGE_PAUSE, b"\x01")
        elif msg_type == proto.TEXT_MESSAGE:
            pass
        else:
            raise proto.ProtocolViolationError(f"unknown message type {msg_type}")


_END_LINE = re.compile(r"^end[ \t]*\r?$", re.MULTILINE)


class Emulator:
    """Owns the controller, the servers and the tick task."""

    def __init__(self, ctl: UrController, host: str, ports: Ports, verbose: bool = False) -> None:
        self.ctl = ctl
        self.host = host
        self.ports = ports
        self.verbose = verbose
        self.rtde_conns: set[RtdeConnection] = set()
        #: input variable -> the RTDE connection whose input recipe names it (one writer per variable)
        self.input_owners: dict[str, RtdeConnection] = {}
        self.other_writers: set[asyncio.StreamWriter] = set()
        self.realtime_writers: set[asyncio.StreamWriter] = set()  # 30003 clients
        self.state_writers: set[asyncio.StreamWriter] = set()     # 30001 / 30002 clients
        self.muted_until_s = 0.0
        self._servers: list[asyncio.Server] = []
        self._control_server: asyncio.Server | None = None
        self._reopen_task: asyncio.Task[None] | None = None
        self.outage_until_s = 0.0
        self._stop = asyncio.Event()

    def warn(self, message: str) -> None:
        print(f"ursim: {message}", file=sys.stderr, flush=True)

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        await self._listen_robot_ports()
        self._control_server = await asyncio.start_server(
            self._on_control, self.host, self.ports.control, reuse_address=True)

    async def _listen_robot_ports(self) -> None:
        specs = [
            (self.ports.rtde, self._on_rtde),
            (self.ports.script, self._on_realtime),
            (self.ports.primary, self._on_primary),
            (self.ports.secondary, self._on_primary),
            (self.ports.dashboard, self._on_dashboard),
        ]
        for port, cb in specs:
            self._servers.append(await asyncio.start_server(cb, self.host, port, reuse_address=True))

    def _close_robot_ports(self) -> None:
        for srv in self._servers:
            srv.close()
        self._servers.clear()

    def outage(self, seconds: float) -> int:
        """A network outage: stop listening, abort every client connection, listen again after
        ``seconds``. Clients that reconnect at once (ur-rtde's control interface does) are refused,
        as behind a pulled cable. Returns the number of connections dropped."""
        if seconds > 0:
            self._close_robot_ports()
        n = self.drop_connections()
        if seconds > 0:
            self.outage_until_s = self.ctl.timestamp_s + seconds
            if self._reopen_task is not None:
                self._reopen_task.cancel()
            self._reopen_task = asyncio.get_running_loop().create_task(self._reopen_after(seconds))
        return n

    async def _reopen_after(self, seconds: float) -> None:
        await asyncio.sleep(seconds)
        for _ in range(50):
            try:
                await self._listen_robot_ports()
                break
            except OSError:  # a port still in TIME_WAIT use: retry shortly
                self._close_robot_ports()
                await asyncio.sleep(0.1)
        self.outage_until_s = 0.0
        self._reopen_task = None

    def request_stop(self) -> None:
        self._stop.set()

    async def run_until_stopped(self) -> None:
        tick_task = asyncio.create_task(self._tick_loop())
        await self._stop.wait()
        tick_task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await tick_task
        if self._reopen_task is not None:
            self._reopen_task.cancel()
        servers = [*self._servers, *([self._control_server] if self._control_server else [])]
        self._close_robot_ports()
        if self._control_server is not None:
            self._control_server.close()
        self.drop_connections()
        for srv in servers:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(srv.wait_closed(), 1.0)

    async def _tick_loop(self) -> None:
        loop = asyncio.get_running_loop()
        period = self.ctl.dt_s
        state_every = max(1, round(self.ctl.frequency_hz / ci.STATE_RATE_HZ))
        next_t = loop.time()
        tick = 0
        while True:
            next_t += period
            self.ctl.tick()
            tick += 1
            if self.ctl.timestamp_s >= self.muted_until_s:
                for conn in tuple(self.rtde_conns):
                    conn.on_tick(tick)
                if self.realtime_writers:
                    _broadcast(self.realtime_writers, lambda: ci.realtime_packet(self.ctl))
                if self.state_writers and tick % state_every == 0:
                    _broadcast(self.state_writers,
                               lambda: ci.robot_state_message(self.ctl, not self.ctl.version.is_cb3))
            if self.verbose:
                while self.ctl.events:
                    self.warn(self.ctl.events.popleft())
            delay = next_t - loop.time()
            if delay < -0.25:  # fell far behind (machine busy): resynchronise, do not burst
                next_t = loop.time()
                delay = 0.0
            await asyncio.sleep(max(0.0, delay))

    # ------------------------------------------------------------------ RTDE input ownership
    def inputs_in_use(self, conn: RtdeConnection, names: list[str]) -> set[str]:
        """The input variables among ``names`` that another live connection's recipe already names."""
        return {n for n in names if self.input_owners.get(n, conn) is not conn}

    def claim_inputs(self, conn: RtdeConnection, names: list[str]) -> None:
        for n in names:
            self.input_owners[n] = conn

    def release_inputs(self, conn: RtdeConnection) -> None:
        """A connection ended: the variables it wrote are free for other clients."""
        for n in [n for n, owner in self.input_owners.items() if owner is conn]:
            del self.input_owners[n]

    def drop_connections(self) -> int:
        """Abort every client connection (RTDE, script, dashboard) like a pulled cable."""
        n = 0
        for conn in tuple(self.rtde_conns):
            conn.writer.transport.abort()
            n += 1
        self.rtde_conns.clear()
        self.input_owners.clear()
        for w in tuple(self.other_writers):
            w.transport.abort()
            n += 1
        self.other_writers.clear()
        self.realtime_writers.clear()
        self.state_writers.clear()
        return n

    # ------------------------------------------------------------------ RTDE
    async def _on_rtde(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        _nodelay(writer)
        conn = RtdeConnection(self, reader, writer)
        self.rtde_conns.add(conn)
        await conn.run()

    # ------------------------------------------------------------------ client interfaces 30001-30003
    async def _on_realtime(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Realtime interface (30003): a realtime packet every tick until the client sends a program
        (then it is a script client: no more packets); scripts are accepted."""
        _nodelay(writer)
        _small_send_buffer(writer)
        self.realtime_writers.add(writer)
        try:
            await self._on_script(reader, writer)
        finally:
            self.realtime_writers.discard(writer)

    async def _on_primary(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Primary / secondary interface (30001 / 30002): the version message at once, then robot
        state messages at 10 Hz; scripts are accepted."""
        v = self.ctl.version
        writer.write(ci.version_message(v.major, v.minor, v.bugfix, v.build, self.ctl.timestamp_s))
        self.state_writers.add(writer)
        try:
            await self._on_script(reader, writer)
        finally:
            self.state_writers.discard(writer)

    async def _on_script(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Read URScript from a client interface connection until it closes."""
        self.other_writers.add(writer)
        buf = ""
        try:
            while True:
                data = await reader.read(65536)
                if not data:
                    break
                # A 30003 client that sends a program is a script client (ur-rtde's never reads its
                # socket): no more realtime packets for it. A real controller keeps streaming; here
                # that stream made the procedure's servo loop fault (docs/ursim.md).
                self.realtime_writers.discard(writer)
                buf += data.decode("utf-8", errors="replace")
                buf = self._consume_script(buf)
        except ConnectionError:
            pass
        finally:
            self.other_writers.discard(writer)
            writer.close()

    def _consume_script(self, buf: str) -> str:
        while True:
            stripped = buf.lstrip()
            if not stripped:
                return ""
            if stripped.startswith(("def ", "sec ")):
                m = _END_LINE.search(stripped)
                if m is None:
                    return stripped
                self.ctl.load_program(stripped[: m.end()])
                buf = stripped[m.end():]
            else:
                if "\n" not in stripped:
                    return stripped
                line, buf = stripped.split("\n", 1)
                self.ctl.load_program(line + "\n")  # a bare statement runs as a one-line program

    # ------------------------------------------------------------------ dashboard
    async def _on_dashboard(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        _nodelay(writer)
        self.other_writers.add(writer)
        try:
            writer.write(b"Connected: Universal Robots Dashboard Server\n")
            while True:
                raw = await reader.readline()
                if not raw:
                    break
                if self.ctl.slow_responses_s > 0:
                    await asyncio.sleep(self.ctl.slow_responses_s)
                reply, close = dashboard_reply(self.ctl, raw.decode("utf-8", errors="replace").strip())
                writer.write(reply.encode() + b"\n")
                if close:
                    break
        except ConnectionError:
            pass
        finally:
            self.other_writers.discard(writer)
            writer.close()

    # ------------------------------------------------------------------ fault control channel
    async def _on_control(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                raw = await reader.readline()
                if not raw:
                    break
                writer.write((self.control_command(raw.decode("utf-8", errors="replace")) + "\n").encode())
                await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()

    def control_command(self, line: str) -> str:
        """Execute one fault-channel command line; returns one reply line (``ok ...`` / ``error ...``)."""
        parts = line.strip().split()
        if not parts:
            return "error empty command"
        cmd, args = parts[0].lower(), parts[1:]
        ctl = self.ctl
        try:
            if cmd == "protective_stop":
                ctl.protective_stop("fault_injection")
            elif cmd == "estop":
                ctl.emergency_stop()
            elif cmd == "release":
                ctl.release()
            elif cmd == "stall":
                ctl.stalled = _on_off(args, default=True)
            elif cmd == "drop_connection":
                seconds = float(args[0]) if args else 2.0
                if seconds < 0:
                    return "error drop_connection needs S >= 0"
                return f"ok dropped={self.outage(seconds)}"
            elif cmd == "pause_stream":
                seconds = float(args[0]) if args else 3.0
                self.muted_until_s = ctl.timestamp_s + seconds
            elif cmd == "stop_program":
                ctl.stop_program()
            elif cmd == "slow_responses":
                ms = float(args[0]) if args else 0.0
                if ms < 0:
                    return "error slow_responses needs MS >= 0"
                ctl.slow_responses_s = ms / 1000.0
            elif cmd == "status":
                st = ctl.status()
                st["rtde_connections"] = len(self.rtde_conns)
                st["realtime_clients"] = len(self.realtime_writers)
                st["state_clients"] = len(self.state_writers)
                st["stream_muted"] = ctl.timestamp_s < self.muted_until_s
                st["outage"] = self.outage_until_s > 0
                return "ok " + json.dumps(st, separators=(",", ":"))
            elif cmd == "reset":
                if self._reopen_task is not None:  # end an outage now
                    self._reopen_task.cancel()
                    self._reopen_task = asyncio.get_running_loop().create_task(self._reopen_after(0.0))
                ctl.release()
                ctl.unlock_protective_stop()
                ctl.power_on()
                ctl.brake_release()
                ctl.stalled = False
                ctl.slow_responses_s = 0.0
                ctl.speed_scaling = 1.0   # the speed slider back at 100 %
                self.muted_until_s = 0.0
            elif cmd == "home":
                if args and len(args) != 6:
                    return "error home takes no argument or 6 joint angles (rad)"
                ctl.home(np.array([float(a) for a in args]) if args else None)
            elif cmd == "help":
                return ("ok commands: protective_stop estop release stall [on|off] drop_connection [S] "
                        "pause_stream [S] stop_program slow_responses MS home [Q1..Q6] status reset help")
            else:
                return f"error unknown command {cmd!r} (try help)"
        except (ValueError, IndexError) as exc:
            return f"error {cmd}: {exc}"
        return "ok"


def _broadcast(writers: set[asyncio.StreamWriter], encode: Callable[[], bytes]) -> None:
    """Send a state message to every stream client that keeps up (a full one skips this message);
    the message is encoded once, and only when one of them takes it."""
    message: bytes | None = None
    for w in tuple(writers):
        if w.transport.is_closing():
            writers.discard(w)
        elif w.transport.get_write_buffer_size() <= _MAX_STREAM_BACKLOG:
            message = encode() if message is None else message
            w.write(message)


def _on_off(args: list[str], default: bool) -> bool:
    if not args:
        return default
    word = args[0].lower()
    if word in ("on", "1", "true"):
        return True
    if word in ("off", "0", "false"):
        return False
    raise ValueError(f"expected on|off, got {args[0]!r}")


def _small_send_buffer(writer: asyncio.StreamWriter) -> None:
    """Cap the kernel's send buffer of a stream connection (no autotuning to megabytes): a client
    that never reads (ur-rtde's script client on 30003) then holds little, and is soon skipped."""
    import socket

    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _STREAM_SNDBUF)


def _nodelay(writer: asyncio.StreamWriter) -> None:
    import socket

    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
