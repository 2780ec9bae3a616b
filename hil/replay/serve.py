"""Serve a recording in Rerun's web viewer on loopback (``hil replay --serve``).

:class:`ViewerServer` runs the wheel's ``rerun`` binary as a child bound to 127.0.0.1 holding the
recording in a gRPC server on ``grpc_port`` (``rerun --serve-grpc``: no web server). The browser is
pointed at ``web_port``, where :class:`~hil.replay.webfront.LoopbackFront` (a thread of this
process) serves the web viewer's assets with a guarded page and a Content-Security-Policy, so that
the page can reach no host but 127.0.0.1 (its analytics, web font, release check and examples
manifest are refused inside the browser; docs/replay.md). The assets ship inside the wheel's
binary: :func:`viewer_assets` takes them once per process from a short-lived ``rerun
--serve-web`` on private loopback ports, which it then ends, so no unguarded copy of the page is
served while the recording is. Analytics are off in every child as in this process
(:mod:`hil.replay.rerun_env`: the config file is shared; ``FORCE_RERUN_ANALYTICS`` is not passed
on).

Ports picked here (the asset snapshot's two, ``--grpc-port 0``) are chosen free by binding port 0
and closing it, then handed to the child, which binds them itself: another process may take one
in between. So a picked port that already accepts connections is never handed over (it would be
taken for the child's server), and a child that exits before it is up is started again on fresh
ports, :data:`PORT_ATTEMPTS` times in all. A port the operator named is used as named, once. The
front binds its own port in this process: ``--web-port 0`` takes what the system gives it.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import socket
import subprocess
import time
from pathlib import Path
from types import TracebackType
from urllib.parse import quote

from hil.errors import HilError
from hil.replay.rerun_env import FORCE_ANALYTICS_ENV, disable_rerun_analytics
from hil.replay.webfront import Asset, LoopbackFront, WebFrontError, snapshot_assets

LOOPBACK = "127.0.0.1"
DEFAULT_WEB_PORT = 9090
DEFAULT_GRPC_PORT = 9876


#: How many times a child is started on freshly picked ports before giving up (module doc).
PORT_ATTEMPTS = 3


class ViewerServeError(HilError):
    """The web viewer could not be started (port busy, viewer missing, it exited)."""


class _ChildExitedError(ViewerServeError):
    """The child exited before it was up (it may have lost a picked port to another process)."""


def free_port() -> int:
    """A TCP port free on loopback right now (another process may take it next: module doc)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOOPBACK, 0))
        return int(s.getsockname()[1])


def _picked_port(taken: tuple[int, ...] = ()) -> int:
    """:func:`free_port`, skipping one that already accepts connections or is in ``taken``."""
    for _ in range(100):
        port = free_port()
        if port not in taken and not _accepts(port):
            return port
    raise ViewerServeError(f"no free port on {LOOPBACK}")


def rerun_binary() -> Path:
    """The ``rerun`` executable shipped in the rerun-sdk wheel (package ``rerun_cli``). Run it
    directly: ``python -m rerun_cli`` is a wrapper whose child would outlive a terminated wrapper.

    Raises:
        ViewerServeError: rerun-sdk (its ``rerun_cli`` package or binary) is not installed.
    """
    spec = importlib.util.find_spec("rerun_cli")
    exe = None if spec is None or spec.origin is None else Path(spec.origin).parent / "rerun"
    if exe is None or not exe.is_file():
        raise ViewerServeError("the Rerun viewer binary is missing "
                               "(pip install 'needle-guide-hil[viewer]')")
    return exe


def _accepts(port: int) -> bool:
    try:
        with socket.create_connection((LOOPBACK, port), timeout=0.2):
            return True
    except OSError:
        return False


#: the viewer's assets by the binary they came from (:func:`viewer_assets`; ~43 MB, taken once)
_ASSETS: dict[Path, dict[str, Asset]] = {}


def viewer_assets(timeout_s: float = 30.0) -> dict[str, Asset]:
    """The web viewer's files (the page guarded) from the wheel's ``rerun`` binary: the first call
    starts ``rerun --serve-web`` on two free loopback ports with no recording, snapshots its files
    (:func:`~hil.replay.webfront.snapshot_assets`) and ends it; later calls return the same.
    Blocks for up to ``timeout_s`` (per attempt: module doc) plus the transfer.

    Raises:
        ViewerServeError: the binary is missing, exits (:data:`PORT_ATTEMPTS` times), does not
            come up in time, or serves a page that cannot be guarded.
    """
    exe = rerun_binary()
    cached = _ASSETS.get(exe)
    if cached is not None:
        return cached
    assets: dict[str, Asset] | None = None
    for _ in range(PORT_ATTEMPTS - 1):
        with contextlib.suppress(_ChildExitedError):
            assets = _snapshot_from_child(exe, timeout_s)
            break
    if assets is None:
        assets = _snapshot_from_child(exe, timeout_s)   # the last attempt: its error is raised
    _ASSETS[exe] = assets
    return assets


def _snapshot_from_child(exe: Path, timeout_s: float) -> dict[str, Asset]:
    """One attempt of :func:`viewer_assets` on freshly picked ports; the child is ended."""
    web_port = _picked_port()
    grpc_port = _picked_port((web_port,))
    proc = _spawn([str(exe), "--serve-web", "--bind", LOOPBACK, "--port", str(grpc_port),
                   "--web-viewer-port", str(web_port)])
    try:
        _wait_for(proc, (web_port, grpc_port), timeout_s, "the Rerun web viewer")
        try:
            return snapshot_assets(web_port)
        except WebFrontError as exc:
            raise ViewerServeError(str(exc)) from None
    finally:
        _end(proc)


def _spawn(cmd: list[str]) -> subprocess.Popen[bytes]:
    """Start a ``rerun`` child with analytics off (module doc), its output discarded.

    Raises:
        ViewerServeError: it cannot be started.
    """
    disable_rerun_analytics()
    env = {k: v for k, v in os.environ.items() if k != FORCE_ANALYTICS_ENV}
    try:
        return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, env=env)
    except OSError as exc:
        raise ViewerServeError(f"cannot start the Rerun viewer: {exc.strerror or exc}") from None


def _wait_for(proc: subprocess.Popen[bytes], ports: tuple[int, ...], timeout_s: float, what: str) -> None:
    """Until every port accepts a connection.

    Raises:
        ViewerServeError: ``proc`` exited, or ``timeout_s`` passed (the caller ends ``proc``).
    """
    deadline = time.monotonic() + timeout_s
    while not all(_accepts(p) for p in ports):
        code = proc.poll()
        if code is not None:
            raise _ChildExitedError(f"{what} exited with code {code} (is rerun-sdk installed? "
                               f"is a port of {', '.join(map(str, ports))} taken?)")
        if time.monotonic() > deadline:
            raise ViewerServeError(f"{what} not up after {timeout_s:g} s (is rerun-sdk installed?)")
        time.sleep(0.05)  # polling a port's readiness, not a synchronisation by sleeping


class ViewerServer:
    """The web viewer serving ``rrd`` on loopback. Start with :meth:`start` (or ``with``), stop
    with :meth:`close` (idempotent; terminates the viewer, then kills it after ``2 s``; then stops
    and joins the front's threads).

    Args:
        rrd: the recording to serve.
        web_port / grpc_port: loopback ports (0: pick a free one; module doc). Read
            :attr:`web_port`, :attr:`grpc_port` and :attr:`url` after :meth:`start`.
    """

    def __init__(self, rrd: str | Path, web_port: int = DEFAULT_WEB_PORT,
                 grpc_port: int = DEFAULT_GRPC_PORT) -> None:
        self.rrd = Path(rrd)
        self.web_port = web_port
        self.grpc_port = grpc_port
        self._pick_grpc = grpc_port == 0
        self._proc: subprocess.Popen[bytes] | None = None
        self._front: LoopbackFront | None = None
        self.pid: int | None = None

    @property
    def grpc_url(self) -> str:
        return f"rerun+http://{LOOPBACK}:{self.grpc_port}/proxy"

    @property
    def url(self) -> str:
        """The address to open in a browser: the web viewer connected to the recording."""
        return f"http://{LOOPBACK}:{self.web_port}/?url={quote(self.grpc_url, safe='')}"

    def start(self, timeout_s: float = 30.0) -> ViewerServer:
        """Take the viewer's assets (:func:`viewer_assets`, once per process), start the gRPC
        server with the recording, wait (up to ``timeout_s`` per attempt) until it accepts
        connections, then start the front on ``web_port``.

        Raises:
            ViewerServeError: a named port is busy, the viewer exited (on a picked port:
                :data:`PORT_ATTEMPTS` times), or it did not come up in time.
        """
        for port in (self.web_port, self.grpc_port):
            if port and _accepts(port):
                raise ViewerServeError(f"{LOOPBACK}:{port} is already in use")
        assets = viewer_assets(timeout_s)
        try:
            self._start_grpc(timeout_s)
            self._front = LoopbackFront(self.web_port, assets, self.grpc_port).start()
            self.web_port = self._front.port
        except WebFrontError as exc:
            self.close()
            raise ViewerServeError(str(exc)) from None
        except ViewerServeError:
            self.close()
            raise
        return self

    def _start_grpc(self, timeout_s: float) -> None:
        """The gRPC child, up; on a picked port started again when it exits (module doc)."""
        attempts = PORT_ATTEMPTS if self._pick_grpc else 1
        for attempt in range(1, attempts + 1):
            if self._pick_grpc:
                self.grpc_port = _picked_port((self.web_port,))
            self._proc = _spawn([str(rerun_binary()), "--serve-grpc", "--bind", LOOPBACK,
                                 "--port", str(self.grpc_port), str(self.rrd)])
            self.pid = self._proc.pid
            try:
                _wait_for(self._proc, (self.grpc_port,), timeout_s, "the Rerun gRPC server")
                return
            except _ChildExitedError:
                proc, self._proc = self._proc, None
                _end(proc)
                if attempt == attempts:
                    raise

    def wait(self) -> int:
        """Block until the viewer exits (Ctrl-C raises KeyboardInterrupt here); its exit code."""
        if self._proc is None:
            return 0
        return self._proc.wait()

    def close(self) -> None:
        proc, self._proc = self._proc, None
        front, self._front = self._front, None
        try:
            if proc is not None:
                _end(proc)
        finally:
            if front is not None:  # after the viewer: a relay from it then ends at once
                front.close()

    def __enter__(self) -> ViewerServer:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _end(proc: subprocess.Popen[bytes]) -> None:
    """Terminate ``proc``, kill it after 2 s, reap it."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            proc.kill()
    proc.wait()
