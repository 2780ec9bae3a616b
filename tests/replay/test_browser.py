"""The served web viewer loads a replay in headless Chromium (Debian's package, network-quiet
flags, DevTools protocol) and reaches no host but loopback: the page starts no request to any
other host (DevTools ``Network.requestWillBeSent``), logs no console error and throws no uncaught
exception; its guard refused the viewer's own Internet requests inside the page; the canvas
renders the viewer's layout (not a blank or loading screen); the server is ended and reaped."""

from __future__ import annotations

import io
import os
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from hil.replay import write_replay
from hil.replay.serve import ViewerServer
from tests.replay.cdp import HeadlessChromium, chromium_path

#: More distinct colours than the loading screen has (it has a few dozen; the viewer with the
#: recording's plots and points has hundreds).
RENDERED_COLOURS = 300
#: The only hosts the page may ask anything of.
LOOPBACK_HOSTS = {"127.0.0.1"}


def _need_chromium() -> None:
    if chromium_path() is not None:
        return
    if os.geteuid() == 0:  # tools/test installs it where root: its absence is a set-up defect
        pytest.fail("chromium is not installed (tools/test installs Debian's chromium when root)")
    pytest.skip("chromium is not installed and this user cannot install it (not root)")


def _distinct_colours(png: bytes) -> int:
    from PIL import Image

    with Image.open(io.BytesIO(png)) as im:
        return len(im.convert("RGB").getcolors(maxcolors=1 << 20) or [])


def _listening(pid: int) -> set[tuple[str, int]]:
    """The (IPv4 address, port) of every TCP socket ``pid`` listens on (/proc: its socket
    inodes matched with the LISTEN rows of /proc/net/tcp and tcp6)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        target = os.readlink(fd)
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    out: set[tuple[str, int]] = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for row in Path(table).read_text().splitlines()[1:]:
            f = row.split()
            if f[3] == "0A" and f[9] in inodes:   # 0A: LISTEN
                addr, port = f[1].split(":")
                ip = ".".join(str(int(addr[i:i + 2], 16)) for i in (6, 4, 2, 0)) if len(addr) == 8 else addr
                out.add((ip, int(port, 16)))
    return out


@pytest.mark.timeout(400)
def test_served_viewer_renders_the_replay_and_reaches_only_loopback(sim_session: Path,
                                                                    tmp_path: Path) -> None:
    _need_chromium()
    rrd = write_replay(sim_session, tmp_path / "run.rrd").path
    with ViewerServer(rrd, web_port=0, grpc_port=0) as server, HeadlessChromium() as browser:
        assert server.url.startswith(f"http://127.0.0.1:{server.web_port}/")
        # Rerun's child serves the recording only: one listening socket, the gRPC port on
        # loopback; no copy of the unguarded page is reachable anywhere while it is served
        assert server.pid is not None
        assert _listening(server.pid) == {("127.0.0.1", server.grpc_port)}
        page = browser.open(server.url)
        assert page.wait_for("document.querySelector('canvas') !== null", timeout_s=90)
        # the viewer (egui) draws everything, text included, on its canvas: wait until a
        # screenshot shows the rendered layout rather than the plain loading screen
        colours, png = 0, b""
        for _ in range(30):
            page.pump(3.0)
            png = page.screenshot()
            colours = _distinct_colours(png)
            if colours > RENDERED_COLOURS:
                break
        page.pump(5.0)  # the viewer's later requests (analytics of the loaded recording) too
        blocked = page.evaluate("window.__hilBlockedRequests")
    assert server.pid is not None
    with pytest.raises(ProcessLookupError):  # the viewer server is ended and reaped, no orphan
        os.kill(server.pid, 0)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert colours > RENDERED_COLOURS, page.console[-20:]
    assert page.exceptions == []
    assert [level_text for level_text in page.console if level_text[0] == "error"] == []
    # every request the page started went to loopback: to the front (the page, its script and
    # wasm) and to the recording's gRPC port, and to nothing else
    assert page.requests, "the page started no request at all: the monitor saw nothing"
    assert {urlsplit(u).hostname for u in page.requests} == LOOPBACK_HOSTS, page.requests
    assert {urlsplit(u).port for u in page.requests} == {server.web_port, server.grpc_port}
    # the viewer did try the Internet, and the page's guard refused it before any request
    assert isinstance(blocked, list), blocked
    assert blocked, "the viewer asked nothing of the Internet: the guard was not exercised"
    assert all(urlsplit(u).hostname not in LOOPBACK_HOSTS | {"localhost"} for u in blocked), blocked
