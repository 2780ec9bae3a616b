"""The OpenIGTLink server: streams TRANSFORM, STRING and POINT messages to every connected
client (3D Slicer's OpenIGTLinkIF, or any OpenIGTLink client). Messages are packed with pyigtl
(optional ``igtl`` extra); the socket side is a small threaded TCP server of our own so that it
binds exactly the configured address, installs no signal handlers, and never prints tracebacks.

Read-only by construction: bytes a client sends are read and discarded (counted, logged once per
client) — nothing a client sends reaches the controller, let alone the robot.

Threads: one accept thread, one per client. :meth:`IgtlServer.publish` never blocks: it packs
the messages and appends them to each client's bounded queue (the oldest are dropped when a
client falls behind).
"""

from __future__ import annotations

import collections
import socket
import socketserver
import threading
from typing import Any

from hil.clock import Clock
from hil.errors import HilError
from hil.igtl.config import IgtlConfig
from hil.igtl.snapshot import IgtlSnapshot
from hil.log import get_logger

_log = get_logger(__name__)

_QUEUE_MESSAGES = 256
_POLL_S = 0.01


class IgtlError(HilError):
    """The OpenIGTLink server cannot start (port in use, address not local, pyigtl missing)."""


def _pyigtl() -> Any:
    try:
        import pyigtl
    except ImportError as exc:
        raise IgtlError(f"OpenIGTLink needs pyigtl (pip install 'needle-guide-hil[igtl]'): {exc}") from None
    return pyigtl


class _Client:
    def __init__(self, peer: str) -> None:
        self.peer = peer
        self.queue: collections.deque[bytes] = collections.deque(maxlen=_QUEUE_MESSAGES)
        self.lock = threading.Lock()
        self.ignored_bytes = 0


class _Handler(socketserver.BaseRequestHandler):
    server: _TcpServer

    def handle(self) -> None:
        owner = self.server.owner
        sock: socket.socket = self.request
        sock.settimeout(_POLL_S)
        client = _Client(f"{self.client_address[0]}:{self.client_address[1]}")
        owner._add_client(client)
        try:
            while not owner._stopping.is_set():
                try:
                    data = sock.recv(65536)
                    if not data:
                        break  # the client closed the connection
                    if client.ignored_bytes == 0:
                        _log.warning("igtl_client_input_ignored", peer=client.peer,
                                     detail="the OpenIGTLink server is read-only")
                    client.ignored_bytes += len(data)
                except TimeoutError:
                    pass
                with client.lock:
                    out = list(client.queue)
                    client.queue.clear()
                for msg in out:
                    sock.sendall(msg)
        except OSError as exc:
            _log.info("igtl_client_lost", peer=client.peer, reason=str(exc))
        finally:
            owner._remove_client(client)


class _TcpServer(socketserver.ThreadingMixIn, socketserver.TCPServer):
    allow_reuse_address = True
    daemon_threads = True

    def __init__(self, address: tuple[str, int], owner: IgtlServer) -> None:
        self.owner = owner
        super().__init__(address, _Handler)


class IgtlServer:
    """OpenIGTLink streaming server.

    Args:
        cfg: address, port and rates.
        clock: the controller clock; rates are counted on it (faster-than-real-time sessions
            stream at the simulated rate).

    :meth:`start` binds and serves in background threads; :meth:`publish` queues a snapshot
    (rate-limited); :meth:`close` stops everything (idempotent). Also a context manager.
    """

    def __init__(self, cfg: IgtlConfig, clock: Clock) -> None:
        self.cfg = cfg
        self.clock = clock
        self._pyigtl = _pyigtl()
        self._tcp: _TcpServer | None = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._clients: list[_Client] = []
        self._clients_lock = threading.Lock()
        self._last_tf_ns: int | None = None
        self._last_status_ns: int | None = None
        self.messages_sent = 0
        self.ignored_bytes = 0  # bytes clients sent (discarded: the server is read-only)

    # -------------------------------------------------------------- lifecycle
    def start(self) -> None:
        """Bind ``cfg.host:cfg.port`` and serve.

        Raises:
            IgtlError: the address cannot be bound (names host, port and the reason).
        """
        if self._tcp is not None:
            return
        try:
            self._tcp = _TcpServer((self.cfg.host, self.cfg.port), self)
        except OSError as exc:
            raise IgtlError(f"OpenIGTLink server cannot listen on {self.cfg.host}:{self.cfg.port}: "
                            f"{exc.strerror or exc}") from None
        self._thread = threading.Thread(target=self._tcp.serve_forever, kwargs={"poll_interval": 0.05},
                                        name="igtl-server", daemon=True)
        self._thread.start()
        host, port = self.address
        _log.info("igtl_server_started", host=host, port=port)

    @property
    def address(self) -> tuple[str, int]:
        """The bound (host, port) — the real port when ``cfg.port`` is 0."""
        if self._tcp is None:
            return self.cfg.host, self.cfg.port
        host, port = self._tcp.server_address[:2]
        return str(host), int(port)

    def ignored_bytes_now(self) -> int:
        """Bytes received from clients so far (all discarded), connected or gone."""
        with self._clients_lock:
            return self.ignored_bytes + sum(c.ignored_bytes for c in self._clients)

    @property
    def clients(self) -> int:
        with self._clients_lock:
            return len(self._clients)

    def close(self) -> None:
        """Disconnect the clients and stop serving (idempotent, returns within ~0.2 s)."""
        if self._tcp is None:
            return
        self._stopping.set()
        self._tcp.shutdown()
        self._tcp.server_close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._tcp = None
        _log.info("igtl_server_stopped")

    def __enter__(self) -> IgtlServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _add_client(self, c: _Client) -> None:
        with self._clients_lock:
            self._clients.append(c)
        _log.info("igtl_client_connected", peer=c.peer)

    def _remove_client(self, c: _Client) -> None:
        with self._clients_lock:
            if c in self._clients:
                self._clients.remove(c)
        self.ignored_bytes += c.ignored_bytes
        _log.info("igtl_client_disconnected", peer=c.peer, ignored_bytes=c.ignored_bytes)

    # -------------------------------------------------------------- streaming
    def _due(self, last_ns: int | None, now_ns: int, rate_hz: float) -> bool:
        return last_ns is None or (now_ns - last_ns) * 1e-9 >= 1.0 / rate_hz - 1e-9

    def publish(self, snap: IgtlSnapshot, now_ns: int | None = None, *, force: bool = False) -> int:
        """Queue the snapshot's messages for every client, rate-limited on the controller clock
        (transforms at ``rate_hz``, status and points at ``status_rate_hz``; ``force`` ignores
        the rates). Never blocks. Returns the number of messages queued per client (0 when no
        client is connected or nothing is due)."""
        now = self.clock.now_ns() if now_ns is None else now_ns
        with self._clients_lock:
            clients = list(self._clients)
        if not clients:
            return 0
        ig = self._pyigtl
        msgs: list[Any] = []
        if force or self._due(self._last_tf_ns, now, self.cfg.rate_hz):
            self._last_tf_ns = now
            msgs += [ig.TransformMessage(m, device_name=name) for name, m in snap.transforms.items()]
        if force or self._due(self._last_status_ns, now, self.cfg.status_rate_hz):
            self._last_status_ns = now
            msgs.append(ig.StringMessage(snap.status, device_name="Status"))
            if snap.deformation:
                msgs.append(ig.StringMessage(snap.deformation, device_name="Deformation"))
            if snap.points:
                msgs.append(ig.PointMessage(positions=[p.tolist() for p in snap.points.values()],
                                            names=list(snap.points), device_name="Plan"))
        packed = [m.pack() for m in msgs]
        for c in clients:
            with c.lock:
                c.queue.extend(packed)
        self.messages_sent += len(packed)
        return len(packed)
