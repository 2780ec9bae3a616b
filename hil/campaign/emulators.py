"""The emulators a transport campaign run talks to, as subprocesses on private addresses, and the
clients of their fault channels (line protocols; no driver import: the core stays driver-free).

- ``tools/emulators/ursim`` (UR controller, RTDE + dashboard + fault channel on TCP 30200) on a
  random loopback address 127.x.y.z (Linux routes all of 127/8 to lo), so the fixed UR ports never
  collide with another emulator;
- ``tools/emulators/trackersim`` (Flock of Birds or NDI Aurora) on a pseudo-terminal, with its
  control interface on a Unix socket;
- ``tools/emulators/fakegv`` (two fake GigE Vision cameras serving a shared-memory frame block) on
  127.0.0.1 and 127.0.0.2, with its control interface on a Unix socket; started INSIDE the run's
  private network namespace (:mod:`hil.campaign.gige`), dying with the process that started it.

Starting blocks (bounded, ~1-3 s); :class:`EmulatorError` when an emulator does not come up.

The emulators are the ``emulators`` package of the source checkout's ``tools/`` directory, run as
``python -m emulators.<name>`` with that directory on ``PYTHONPATH``. :func:`emulators_dir` finds
it: ``$HIL_EMULATORS_DIR`` first, then an importable ``emulators`` package, then the ``tools/`` of
the checkout the ``hil`` package runs from (an editable install); a non-editable install has none
and gets :class:`EmulatorsMissingError`, one line saying how to point at a checkout.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.util
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

import configs
from hil.errors import HilError

#: Names the directory that holds the ``emulators`` package (a checkout's ``tools/``).
ENV_EMULATORS_DIR = "HIL_EMULATORS_DIR"
#: The setups and plans the campaign writes its runs from (the ``configs`` package data).
CONFIGS_DIR = Path(configs.__file__).resolve().parent
START_TIMEOUT_S = 20.0
URSIM_PORTS = (30004, 30003, 30002, 30001, 29999, 30200)
URSIM_CONTROL_PORT = 30200


class EmulatorError(HilError):
    """An emulator did not start, or its fault channel refused a command."""


class EmulatorsMissingError(EmulatorError):
    """The emulators package cannot be found here (a non-editable install without a checkout)."""


def _holds_emulators(directory: Path) -> bool:
    return (directory / "emulators" / "__init__.py").is_file()


def _checkout_tools() -> Path | None:
    """``tools/`` of the source checkout the ``hil`` package is loaded from, when it is one (its
    parent directory holds ``pyproject.toml`` and ``tools/emulators``); None for an installed
    package."""
    spec = importlib.util.find_spec("hil")
    if spec is None or spec.origin is None:
        return None
    root = Path(spec.origin).resolve().parent.parent
    if (root / "pyproject.toml").is_file() and _holds_emulators(root / "tools"):
        return root / "tools"
    return None


def emulators_dir() -> Path:
    """The directory holding the ``emulators`` package, to put on the emulators' ``PYTHONPATH``.

    Looked up in order: ``$HIL_EMULATORS_DIR``; the directory of an importable ``emulators``
    package; the ``tools/`` of the source checkout ``hil`` runs from.

    Raises:
        EmulatorsMissingError: none holds it (one line: where it looked and what to do).
    """
    env = os.environ.get(ENV_EMULATORS_DIR)
    if env:
        if not _holds_emulators(Path(env)):
            raise EmulatorsMissingError(f"{ENV_EMULATORS_DIR}={env} holds no emulators package "
                                        "(emulators/__init__.py): point it at a checkout's tools/ directory")
        return Path(env).resolve()
    spec = importlib.util.find_spec("emulators")
    if spec is not None and spec.origin is not None and _holds_emulators(Path(spec.origin).parent.parent):
        return Path(spec.origin).resolve().parent.parent
    found = _checkout_tools()
    if found is None:
        raise EmulatorsMissingError(
            "the device emulators (the emulators package in tools/ of the source checkout) are not "
            f"installed with hil: set {ENV_EMULATORS_DIR} to a checkout's tools/ directory")
    return found


def _env(tools: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tools) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
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


def _spawn(args: list[str], log_path: Path, *, tied_to_parent: bool = False
           ) -> tuple[subprocess.Popen[bytes], str]:
    """Start ``python -m <args>`` (stderr to ``log_path``); return it and its first stdout line
    (empty when none came within ``START_TIMEOUT_S``)."""
    tools = emulators_dir()
    with log_path.open("wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", *args], env=_env(tools), stdout=subprocess.PIPE,
                                stderr=log, cwd=tools,
                                preexec_fn=die_with_parent if tied_to_parent else None)
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
    RTDE port and fault channel answer.

    Raises:
        EmulatorError: it exited or did not answer in time; EmulatorsMissingError: no emulators.
    """
    tools = emulators_dir()
    host = free_loopback_address()
    log_path = log_dir / f"ursim-{host}.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "emulators.ursim", "--host", host, "--controller-version", version,
             "--verbose"],
            env=_env(tools), stdout=log, stderr=subprocess.STDOUT, cwd=tools)
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


def start_trackersim(log_dir: Path, *, seed: int = 0, protocol: str = "fob") -> TrackerSim:
    """Start ``python -m emulators.trackersim --protocol PROTOCOL`` on a pty, static poses (``fob``:
    a standalone bird; ``aurora``: two wired tools on handles 0A and 0B); wait (bounded) for the
    device path on its first stdout line and its control socket.

    Raises:
        EmulatorError: it exited or did not answer within ``START_TIMEOUT_S``.
    """
    log_path = log_dir / "trackersim.log"
    control = _control_socket_path("trackersim")
    extra = ["--tools", "2"] if protocol == "aurora" else []
    proc, line = _spawn(["emulators.trackersim", "--protocol", protocol, *extra, "--motion", "static",
                         "--seed", str(seed), "--control", str(control)], log_path)
    if not line.startswith("/dev/"):
        _stop(proc)
        raise EmulatorError(f"trackersim did not print its device path: {line!r} "
                            f"{log_path.read_text(errors='replace')[-2000:]}")
    sim = TrackerSim(line, control, proc, log_path)
    _await_control("trackersim", proc, sim.command, sim.stop)
    return sim


def die_with_parent() -> None:
    """preexec_fn: the child gets SIGKILL when the process that started it dies (PR_SET_PDEATHSIG),
    so an emulator never outlives a test or campaign process that crashed (no teardown ran). The
    signal follows the *thread* that started the child: start it from a thread that outlives it."""
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
                         "--control", str(control)], log_path, tied_to_parent=True)
    try:
        cameras = json.loads(line)["cameras"]
    except (ValueError, KeyError, TypeError):
        _stop(proc)
        raise EmulatorError(f"fakegv did not name its cameras: {line!r} "
                            f"{log_path.read_text(errors='replace')[-2000:]}") from None
    sim = FakeGv(cameras, control, proc, log_path)
    _await_control("fakegv", proc, sim.command, sim.stop)
    return sim
