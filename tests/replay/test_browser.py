"""The served web viewer loads a replay in headless Chromium (Debian's package, network-quiet
flags, DevTools protocol): no uncaught exception, no console error but the viewer page's own
Internet fetches failing offline (:data:`OFFLINE_FETCHES`), the canvas renders the viewer's
layout (not a blank or loading screen), and the server is ended and reaped."""

from __future__ import annotations

import io
import os
from pathlib import Path

import pytest

from hil.replay import write_replay
from hil.replay.serve import ViewerServer
from tests.replay.cdp import HeadlessChromium, chromium_path

#: The only console errors allowed: what the web viewer's page asks of the Internet, refused
#: on this machine (the browser resolves no host but loopback and proxies the rest to nowhere,
#: tests/replay/cdp.py: no packet leaves it):
#: its web-font stylesheet, the welcome screen's examples manifest (shown until the
#: recording arrives), its check for a newer release (GitHub) and Rerun's web analytics
#: (``tel.rerun.io``: the web viewer has no opt-out).
#: A known defect, docs/replay.md; a new outbound request fails this test.
OFFLINE_FETCHES = ("https://fonts.googleapis.com/css2",
                   "https://app.rerun.io/version/0.41.0/examples_manifest.json",
                   "https://api.github.com/repos/rerun-io/rerun/releases/latest",
                   "https://tel.rerun.io/")
#: More distinct colours than the loading screen has (it has a few dozen; the viewer with the
#: recording's plots and points has hundreds).
RENDERED_COLOURS = 300


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


@pytest.mark.timeout(400)
def test_served_viewer_renders_the_replay(sim_session: Path, tmp_path: Path) -> None:
    _need_chromium()
    rrd = write_replay(sim_session, tmp_path / "run.rrd").path
    with ViewerServer(rrd, web_port=0, grpc_port=0) as server, HeadlessChromium() as browser:
        assert server.url.startswith("http://127.0.0.1:")
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
    assert server.pid is not None
    with pytest.raises(ProcessLookupError):  # the viewer server is ended and reaped, no orphan
        os.kill(server.pid, 0)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert colours > RENDERED_COLOURS, page.console[-20:]
    assert page.exceptions == []
    errors = [text for level, text in page.console if level == "error"]
    network = [t for t in errors if not t.startswith("TypeError: Failed to fetch")]
    assert all(("ERR_NAME_NOT_RESOLVED" in text or "ERR_PROXY_CONNECTION_FAILED" in text)
               and any(url in text for url in OFFLINE_FETCHES)
               for text in network), errors
    assert len(errors) - len(network) <= len(network)  # a failed fetch's own error, no other
