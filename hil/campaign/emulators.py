"""The emulators a transport campaign run talks to, as subprocesses on private addresses, and the
clients of their fault channels (line protocols; no driver import: the core stays driver-free).

- ``tools/emulators/ursim`` (UR controller, RTDE + dashboard + fault channel on TCP 30200) on a
  random loopback address 127.x.y.z (Linux routes all of 127/8 to lo), so the fixed UR ports never
  collide with another emulator;
- ``tools/emulators/trackersim`` (Flock of Birds) on a pseudo-terminal, with its control interface
  on a Unix socket;
- ``tools/emulators/fakegv`` (two fake GigE Vision cameras serving a shared-memory frame block) on
  127.0.0.1 and 127.0.0.2, with its control interface on a Unix socket; started INSIDE the run's
  private network namespace (:mod:`hil.campaign.gige`), dying with the process that started it.

Starting blocks (bounded, ~1-3 s); :class:`EmulatorError` when an emulator does not come up.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import random
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hil.errors import HilError

ROOT = Path(__file__).resolve().parents[2]
TOOLS = ROOT / "tools"
START_TIMEOUT_S = 20.0
URSIM_PORTS = (30004, 30003, 29999, 30200)
URSIM_CONTROL_PORT = 30200


class EmulatorError(HilError):
    """An emulator did not start, or its fault channel refused a command."""


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(TOOLS) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()


def line_command(sock: socket.socket, line: str, timeout_s: float = 3.0) -> str:
    """Send one command line on a connected stream socket; return the reply line.

    Raises:
        EmulatorError: no reply within ``timeout_s``, the channel closed, or an ``error`` reply.
    """
    sock.settimeout(timeout_s)
    try:
        sock.sendall(line.strip().encode() + b"\n")
        buf = b""
        while b"\n" not in buf:
            chunk = sock.recv(4096)
            if not chunk:
                raise EmulatorError(f"fault channel closed on {line.strip()!r}")
            buf += chunk
    except OSError as exc:
        raise EmulatorError(f"fault channel: {line.strip()!r}: {exc}") from exc
    reply = buf.split(b"\n", 1)[0].decode("utf-8", errors="replace")
    if not reply.startswith("ok"):
        raise EmulatorError(f"fault channel: {line.strip()!r} -> {reply}")
    return reply


def ursim_command(host: str, line: str) -> str:
    """One command on the UR emulator's fault channel at ``host`` (TCP 30200); the reply line.

    Raises:
        EmulatorError: unreachable, no reply, or an ``error`` reply.
    """
    try:
        sock = socket.create_connection((host, URSIM_CONTROL_PORT), timeout=3.0)
    except OSError as exc:
        raise EmulatorError(f"ursim fault channel {host}:{URSIM_CONTROL_PORT}: {exc}") from exc
    with sock:
        return line_command(sock, line)


def unix_command(what: str, control_path: Path, line: str) -> str:
    """One command line on an emulator's Unix-socket control interface; the reply line.

    Raises:
        EmulatorError: unreachable (naming ``what``), no reply, or an ``error`` reply.
    """
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(3.0)
        try:
            sock.connect(str(control_path))
        except OSError as exc:
            raise EmulatorError(f"{what} control {control_path}: {exc}") from exc
        return line_command(sock, line)


def trackersim_command(control_path: Path, line: str) -> str:
    """One command on the tracker emulator's control socket; the reply line.

    Raises:
        EmulatorError: unreachable, no reply, or an ``error`` reply.
    """
    return unix_command("trackersim", control_path, line)


def fakegv_command(control_path: Path, line: str) -> str:
    """One command on the fake GigE cameras' control socket (``stream_loss 1.0``, ``status``);
    the reply line.

    Raises:
        EmulatorError: unreachable, no reply, or an ``error`` reply.
    """
    return unix_command("fakegv", control_path, line)


def _control_socket_path(what: str) -> Path:
    # a short path: Unix socket paths are limited to ~100 bytes
    return Path("/tmp") / f"hil-{what}-{os.getpid()}-{random.randint(0, 1 << 30)}.sock"


def _spawn(args: list[str], log_path: Path, *, die_with_parent: bool = False
           ) -> tuple[subprocess.Popen[bytes], str]:
    """Start ``python -m <args>`` (stderr to ``log_path``); return it and its first stdout line
    (empty when none came within ``START_TIMEOUT_S``)."""
    with log_path.open("wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", *args], env=_env(), stdout=subprocess.PIPE, stderr=log,
                                cwd=ROOT, preexec_fn=_die_with_parent if die_with_parent else None)
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], START_TIMEOUT_S)
    return proc, proc.stdout.readline().decode(errors="replace").strip() if ready else ""


def _await_control(what: str, proc: subprocess.Popen[bytes], command: Callable[[str], str],
                   stop: Callable[[], None]) -> None:
    """Wait (bounded) until the control interface answers ``status``; else stop and raise."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:
        try:
            command("status")
            return
        except EmulatorError:
            if proc.poll() is not None or time.monotonic() > deadline:
                stop()
                raise EmulatorError(f"{what} control interface did not answer") from None
            time.sleep(0.05)


def free_loopback_address() -> str:
    """A random 127.x.y.z on which every UR port is free."""
    for _ in range(50):
        host = f"127.{random.randint(100, 199)}.{random.randint(0, 255)}.{random.randint(1, 254)}"
        with contextlib.ExitStack() as stack:
            try:
                for port in URSIM_PORTS:
                    s = stack.enter_context(socket.socket())
                    s.bind((host, port))
            except OSError:
                continue
            return host
    raise EmulatorError("no free loopback address for the UR emulator")


@dataclass
class Ursim:
    """A running UR controller emulator."""

    host: str
    proc: subprocess.Popen[bytes]
    log_path: Path

    def command(self, line: str) -> str:
        """One fault-channel command (``protective_stop``, ``drop_connection 1.0``, ...)."""
        return ursim_command(self.host, line)

    def stop(self) -> None:
        _stop(self.proc)


def start_ursim(log_dir: Path, version: str = "3.15") -> Ursim:
    """Start ``python -m emulators.ursim`` on a free loopback address; wait (bounded) until its
    RTDE port and fault channel answer."""
    host = free_loopback_address()
    log_path = log_dir / f"ursim-{host}.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "emulators.ursim", "--host", host, "--controller-version", version,
             "--verbose"],
            env=_env(), stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
    sim = Ursim(host, proc, log_path)
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:
        if proc.poll() is not None:
            raise EmulatorError(f"ursim exited with {proc.returncode}: {log_path.read_text()[-2000:]}")
        try:
            with socket.create_connection((host, 30004), timeout=0.5):
                pass
            sim.command("status")
            return sim
        except (OSError, EmulatorError):
            if time.monotonic() > deadline:
                sim.stop()
                raise EmulatorError(f"ursim did not start in {START_TIMEOUT_S} s") from None
            time.sleep(0.05)


@dataclass
class TrackerSim:
    """A running serial tracker emulator: ``port`` is the pty the driver opens."""

    port: str
    control_path: Path
    proc: subprocess.Popen[bytes]
    log_path: Path

    def command(self, line: str) -> str:
        """One control-interface command (``fault garbage,p=1``, ``clear``, ``status``)."""
        return trackersim_command(self.control_path, line)

    def stop(self) -> None:
        _stop(self.proc)
        with contextlib.suppress(FileNotFoundError):
            self.control_path.unlink()


def start_trackersim(log_dir: Path, *, seed: int = 0) -> TrackerSim:
    """Start ``python -m emulators.trackersim --protocol fob`` (a standalone bird, static poses) on
    a pty; wait (bounded) for the device path on its first stdout line and its control socket."""
    log_path = log_dir / "trackersim.log"
    control = _control_socket_path("trackersim")
    proc, line = _spawn(["emulators.trackersim", "--protocol", "fob", "--motion", "static",
                         "--seed", str(seed), "--control", str(control)], log_path)
    if not line.startswith("/dev/"):
        _stop(proc)
        raise EmulatorError(f"trackersim did not print its device path: {line!r} "
                            f"{log_path.read_text(errors='replace')[-2000:]}")
    sim = TrackerSim(line, control, proc, log_path)
    _await_control("trackersim", proc, sim.command, sim.stop)
    return sim


def _die_with_parent() -> None:
    """preexec_fn: the child gets SIGKILL when the process that started it dies (PR_SET_PDEATHSIG)."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # 1 = PR_SET_PDEATHSIG


@dataclass
class FakeGv:
    """Running fake GigE Vision cameras: ``cameras`` as printed on the first stdout line
    (``side``, ``address``, ``serial``, ``device_id``)."""

    cameras: list[dict[str, Any]]
    control_path: Path
    proc: subprocess.Popen[bytes]
    log_path: Path

    def command(self, line: str) -> str:
        """One control-interface command (``stream_loss 1.0``, ``status``, ``help``)."""
        return fakegv_command(self.control_path, line)

    def status(self) -> dict[str, Any]:
        """The emulator's ``status`` object (running, frames filled/served, stream losses)."""
        reply = self.command("status")
        out: dict[str, Any] = json.loads(reply.removeprefix("ok").strip())
        return out

    def stop(self) -> None:
        _stop(self.proc)
        with contextlib.suppress(FileNotFoundError):
            self.control_path.unlink()


def start_fakegv(log_dir: Path, shm_name: str, *, left: str = "127.0.0.1",
                 right: str = "127.0.0.2") -> FakeGv:
    """Start ``python -m emulators.fakegv --shm NAME --right-address RIGHT --control PATH`` (it dies
    with this process); wait (bounded) for its first stdout line and its control socket.
    Both addresses must be on a local interface (a private network namespace for 127.0.0.2).

    Raises:
        EmulatorError: it exited or did not answer within ``START_TIMEOUT_S``.
    """
    log_path = log_dir / "fakegv.log"
    control = _control_socket_path("fakegv")
    proc, line = _spawn(["emulators.fakegv", "--shm", shm_name, "--address", left, "--right-address", right,
                         "--control", str(control)], log_path, die_with_parent=True)
    try:
        cameras = json.loads(line)["cameras"]
    except (ValueError, KeyError, TypeError):
        _stop(proc)
        raise EmulatorError(f"fakegv did not name its cameras: {line!r} "
                            f"{log_path.read_text(errors='replace')[-2000:]}") from None
    sim = FakeGv(cameras, control, proc, log_path)
    _await_control("fakegv", proc, sim.command, sim.stop)
    return sim
