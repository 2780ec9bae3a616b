"""A pytest plugin: the run fails when tests leave threads, child processes or sockets behind.

Every thread, subprocess, socket and emulator a test starts must be closed on every path
(fixtures with finalizers). After each test the plugin notes what appeared during it and is still
there, with the test's id; at the end of the session (after a garbage collection and a short
grace for things that are stopping) whatever is left is named with the test that started it and
the session's exit status becomes "tests failed". Sockets are read from ``/proc/self/fd`` and
``/proc/net/{tcp,tcp6,unix}``, so ur-rtde's C++ clients (which hold a TCP connection to the RTDE,
script or dashboard port) are caught even though Python cannot see their threads.

``HIL_LEAKCHECK=0`` turns the check off (for debugging one test interactively; CI never sets it).
"""

from __future__ import annotations

import gc
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

#: How long the session-end check waits for threads and children that are on their way out.
_GRACE_S = 5.0
#: Children that belong to the interpreter, not to a test: multiprocessing's resource tracker is
#: started once, by the first shared-memory block, and ends by itself when this process exits
#: (its pipe closes). Nothing else is allowed.
_INTERPRETER_CHILDREN = ("from multiprocessing.resource_tracker import main",)
#: Threads that belong to a library, not to a test: distributed's offload pool is one
#: module-global single-thread executor, started on first use and kept to the interpreter's exit
#: (it cannot be shut down without breaking every later Dask client in the process).
_LIBRARY_THREADS = ("Dask-Offload",)


def _children() -> dict[int, str]:
    """Live (or unreaped) child processes of this process: pid -> command line."""
    me = os.getpid()
    out: dict[int, str] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid != me:
                continue
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
            state = stat.rsplit(")", 1)[1].split()[0]
        except (OSError, ValueError, IndexError):
            continue
        if any(marker in cmd for marker in _INTERPRETER_CHILDREN):
            continue
        out[int(d.name)] = (cmd or stat.split("(", 1)[1].split(")", 1)[0]) + (
            " (zombie: never waited for)" if state == "Z" else "")
    return out


def _hexaddr(text: str) -> str:
    ip_hex, port_hex = text.split(":")
    port = int(port_hex, 16)
    if len(ip_hex) == 8:
        ip = ".".join(str(b) for b in bytes.fromhex(ip_hex)[::-1])
    else:
        ip = "[" + ip_hex.lower() + "]"
    return f"{ip}:{port}"


def _socket_table() -> dict[str, str]:
    """inode -> description, for TCP (listening or connected) and named Unix sockets."""
    table: dict[str, str] = {}
    for name in ("tcp", "tcp6"):
        try:
            lines = Path(f"/proc/net/{name}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if len(f) < 10:
                continue
            local, remote, st, inode = f[1], f[2], f[3], f[9]
            what = "listening on" if st == "0A" else "connected"
            table[inode] = (f"TCP {what} {_hexaddr(local)}" if st == "0A"
                            else f"TCP {_hexaddr(local)} -> {_hexaddr(remote)}")
    try:
        for line in Path("/proc/net/unix").read_text().splitlines()[1:]:
            f = line.split()
            if len(f) >= 8:
                table[f[6]] = f"Unix socket {f[7]}"
    except OSError:
        pass
    return table


def _sockets() -> dict[str, str]:
    """Open TCP and named Unix sockets of this process: inode -> description."""
    inodes: set[str] = set()
    fd_dir = Path("/proc/self/fd")
    for fd in fd_dir.iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    table = _socket_table()
    return {i: table[i] for i in inodes if i in table}


def _threads() -> dict[int, threading.Thread]:
    main = threading.main_thread()
    return {t.ident: t for t in threading.enumerate()
            if t.ident is not None and t is not main and not t.name.startswith(_LIBRARY_THREADS)}


@dataclass
class _Leaks:
    threads: dict[int, str] = field(default_factory=dict)   # ident -> test id
    children: dict[int, str] = field(default_factory=dict)  # pid -> test id
    sockets: dict[str, str] = field(default_factory=dict)   # inode -> test id
    start_threads: set[int] = field(default_factory=set)
    start_children: set[int] = field(default_factory=set)
    start_sockets: set[str] = field(default_factory=set)


_state = _Leaks()


def _enabled() -> bool:
    return os.environ.get("HIL_LEAKCHECK", "1") != "0"


def pytest_sessionstart(session: pytest.Session) -> None:
    _state.start_threads = set(_threads())
    _state.start_children = set(_children())
    _state.start_sockets = set(_sockets())


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> object:
    threads, children, sockets = set(_threads()), set(_children()), set(_sockets())
    yield
    for ident in set(_threads()) - threads:
        _state.threads.setdefault(ident, item.nodeid)
    for pid in set(_children()) - children:
        _state.children.setdefault(pid, item.nodeid)
    for inode in set(_sockets()) - sockets:
        _state.sockets.setdefault(inode, item.nodeid)


def leftovers() -> list[str]:
    """What is still open that the session did not start with, each named with its test."""
    gc.collect()
    end = time.monotonic() + _GRACE_S
    while True:
        threads = {i: t for i, t in _threads().items() if i not in _state.start_threads}
        children = {p: c for p, c in _children().items() if p not in _state.start_children}
        sockets = {i: s for i, s in _sockets().items() if i not in _state.start_sockets}
        if not (threads or children or sockets) or time.monotonic() > end:
            break
        time.sleep(0.05)
    out = [f"thread {t.name!r} (daemon={t.daemon}) started by {_state.threads.get(i, 'the session')}"
           for i, t in threads.items()]
    out += [f"child process {pid} {cmd!r} started by {_state.children.get(pid, 'the session')}"
            for pid, cmd in children.items()]
    out += [f"{desc} opened by {_state.sockets.get(inode, 'the session')}" for inode, desc in sockets.items()]
    return out


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if not _enabled() or session.config.option.collectonly:
        return
    left = leftovers()
    if not left:
        return
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_sep("=", "left behind by the tests (close them on every path)", red=True)
        for line in left:
            reporter.write_line(line)
    if session.exitstatus == pytest.ExitCode.OK:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
