"""Ports the viewer server picks itself (``--grpc-port 0``, the asset snapshot's two): a port that
already accepts connections is never handed to the child, and a child that loses its picked port
to another process (it exits before it is up) is started again on a fresh one; a port the
operator named is tried once."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.replay import serve
from hil.replay.serve import ViewerServeError, ViewerServer


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A loopback port bound by this process without listening: a child cannot bind it, and
    nothing accepts connections on it (so the readiness poll cannot mistake it for the child)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        yield int(s.getsockname()[1])


@pytest.fixture
def listening_port() -> Iterator[int]:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield int(s.getsockname()[1])


def _first_then_free(monkeypatch: pytest.MonkeyPatch, first: list[int]) -> None:
    """``free_port`` answers ``first`` in order, then free ports as before."""
    real = serve.free_port
    queue = list(first)
    monkeypatch.setattr(serve, "free_port", lambda: queue.pop(0) if queue else real())


def test_a_picked_port_that_accepts_connections_is_skipped(monkeypatch: pytest.MonkeyPatch,
                                                           listening_port: int) -> None:
    _first_then_free(monkeypatch, [listening_port, listening_port])
    port = serve._picked_port()
    assert port != listening_port
    assert not serve._accepts(port)


def _tiny_recording(path: Path) -> Path:
    from hil.replay.rerun_env import import_rerun

    rr = import_rerun()
    rec = rr.RecordingStream("needle_guide_hil_test")
    rec.save(str(path))
    rec.log("series/x", rr.Scalars(1.0))
    rec.flush()
    rec.disconnect()
    return path


@pytest.mark.timeout(300)
def test_a_child_that_lost_its_picked_port_is_started_again(monkeypatch: pytest.MonkeyPatch,
                                                            tmp_path: Path, taken_port: int) -> None:
    rrd = _tiny_recording(tmp_path / "tiny.rrd")
    serve.viewer_assets()   # taken now (once per process), so the ports below are the gRPC child's
    spawned: list[list[str]] = []
    real_spawn = serve._spawn

    def spawn(cmd: list[str]) -> object:
        spawned.append(cmd)
        return real_spawn(cmd)

    monkeypatch.setattr(serve, "_spawn", spawn)
    _first_then_free(monkeypatch, [taken_port])   # another process took it after we picked it
    server = ViewerServer(rrd, web_port=0, grpc_port=0)
    try:
        server.start()
        assert [c[c.index("--port") + 1] for c in spawned] == [str(taken_port), str(server.grpc_port)]
        assert server.grpc_port != taken_port
        assert serve._accepts(server.grpc_port)
        assert server.web_port != 0   # the front bound what the system gave it
        assert server.url.startswith(f"http://127.0.0.1:{server.web_port}/?url=")
    finally:
        server.close()
    assert not serve._accepts(server.grpc_port)


@pytest.mark.timeout(300)
def test_a_named_port_is_tried_once(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                    taken_port: int) -> None:
    rrd = _tiny_recording(tmp_path / "tiny.rrd")
    serve.viewer_assets()
    spawned: list[list[str]] = []
    real_spawn = serve._spawn
    monkeypatch.setattr(serve, "_spawn", lambda cmd: spawned.append(cmd) or real_spawn(cmd))
    with pytest.raises(ViewerServeError, match=f"exited with code .* is a port of {taken_port} taken"):
        ViewerServer(rrd, web_port=0, grpc_port=taken_port).start()
    assert len(spawned) == 1
