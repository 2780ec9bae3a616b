"""Every listener the project opens binds loopback unless configured otherwise, and none accepts a
command that moves the robot unless the setup enables it.

Listeners: the OpenIGTLink server (hil.igtl), the UR controller emulator (tools/ursim: RTDE,
primary, secondary, realtime/script, dashboard and fault-control ports), the fake GigE Vision
camera (tools/fakegv) and the tracker emulator's control socket (tools/trackersim: a Unix socket,
no network at all).
"""

from __future__ import annotations

import ast
import asyncio
import socket
import sys
import time
from pathlib import Path

import pytest

from hil.clock import ManualClock
from hil.igtl import IgtlConfig
from hil.igtl.server import IgtlServer

ROOT = Path(__file__).resolve().parents[2]
TOOLS = ROOT / "tools"
if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))


def _is_loopback(host: str) -> bool:
    return host == "::1" or host.startswith("127.")


# ----------------------------------------------------------------------------- OpenIGTLink
def test_igtl_is_off_and_loopback_by_default() -> None:
    cfg = IgtlConfig()
    assert cfg.enabled is False
    assert cfg.host == "127.0.0.1"


def test_igtl_refuses_a_host_name_it_would_resolve() -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="not an IPv4 address"):
        IgtlConfig(host="example.org")


def test_igtl_server_binds_loopback_and_ignores_everything_a_client_sends() -> None:
    srv = IgtlServer(IgtlConfig(enabled=True, port=0), ManualClock())
    srv.start()
    try:
        host, port = srv.address
        assert _is_loopback(host)
        # not reachable on any other local address
        with socket.create_connection((host, port), timeout=2.0) as c:
            # an OpenIGTLink TRANSFORM "move here" message, then garbage: both are discarded
            import pyigtl

            msg = pyigtl.TransformMessage(
                [[1, 0, 0, 100], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], device_name="RobotTarget"
            )
            payload = msg.pack() + b"\x00\xff" * 64
            c.sendall(payload)
            end = time.monotonic() + 5.0
            while srv.ignored_bytes_now() < len(payload):
                assert time.monotonic() < end, "server did not read the client's bytes"
                time.sleep(0.01)
        assert srv.ignored_bytes_now() == len(payload)
    finally:
        srv.close()


def test_igtl_package_cannot_reach_a_robot() -> None:
    """Read-only by construction: the socket side of hil/igtl (server.py, config.py) imports neither
    the robot interface, the controller nor a driver (snapshot.py reads a Controller, for typing)."""
    forbidden = ("drivers", "hil.safety", "hil.controller")
    for path in (ROOT / "hil" / "igtl" / "server.py", ROOT / "hil" / "igtl" / "config.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            for name in names:
                assert not name.startswith(forbidden), f"{path.name} imports {name}"


# ----------------------------------------------------------------------------- UR emulator
def test_ursim_listens_on_loopback_by_default() -> None:
    from emulators.ursim.__main__ import build_parser

    assert build_parser().parse_args([]).host == "127.0.0.1"


def test_ursim_sockets_are_bound_to_the_given_loopback_address() -> None:
    from emulators.ursim.controller import ControllerVersion, UrController
    from emulators.ursim.server import Emulator, Ports

    async def run() -> list[tuple[str, int]]:
        emu = Emulator(UrController(ControllerVersion.parse("3.15")), "127.0.0.1",
                   Ports(rtde=0, script=0, dashboard=0, control=0, primary=0, secondary=0))
        await emu.start()
        servers = [*emu._servers, emu._control_server]
        addrs = [s.getsockname()[:2] for srv in servers if srv is not None for s in srv.sockets]
        for srv in servers:
            if srv is not None:
                srv.close()
                await srv.wait_closed()
        return addrs

    addrs = asyncio.run(run())
    assert len(addrs) == 6
    assert all(_is_loopback(h) for h, _ in addrs), addrs


# ----------------------------------------------------------------------------- fake GigE camera
def test_fakegv_defaults_to_loopback() -> None:
    from emulators.fakegv.__main__ import parser

    args = parser().parse_args(["--render"])
    assert args.address == "127.0.0.1"
    assert args.right_address is None


# ----------------------------------------------------------------------------- tracker emulator
def test_emulator_control_channels_are_unix_sockets_not_network_ports(tmp_path: Path) -> None:
    """trackersim's and fakegv's control interfaces are served by emulators.control: a Unix
    socket, reachable only through the file system, never a network port."""
    import socket
    import threading

    from emulators.control import serve_control_lines
    from emulators.fakegv import __main__ as fm
    from emulators.trackersim import __main__ as tm

    assert tm.serve_control_lines is serve_control_lines
    assert fm.serve_control_lines is serve_control_lines
    stop = threading.Event()
    srv = serve_control_lines(tmp_path / "ctl", lambda line: "ok " + line.strip(), stop)
    try:
        assert srv.family == socket.AF_UNIX
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as c:
            c.settimeout(5.0)
            c.connect(str(tmp_path / "ctl"))
            c.sendall(b"status\n")
            assert c.recv(100) == b"ok status\n"
    finally:
        stop.set()
        srv.close()


# ----------------------------------------------------------------------------- the whole tree
def test_no_code_binds_every_interface_by_default() -> None:
    """No Python source in hil/, drivers/, plugins/ or tools/ uses 0.0.0.0 / '' as a default bind
    address (0.0.0.0 may appear only in documentation strings of an opt-in setting)."""
    offenders = []
    for top in ("hil", "drivers", "plugins", "tools"):
        for path in (ROOT / top).rglob("*.py"):
            tree = ast.parse(path.read_text())
            for node in ast.walk(tree):
                if isinstance(node, ast.Constant) and node.value in ("0.0.0.0", "::"):
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert offenders == []
