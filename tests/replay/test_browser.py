"""The served web viewer loads a replay in headless Chromium (Debian's package, network-quiet
flags, DevTools protocol): no uncaught exception, no console error but the one the viewer's page
makes offline (its Google Fonts stylesheet cannot be fetched: no network), and the canvas renders
the recording (the viewer's Rerun entities are drawn: the canvas is not blank)."""

from __future__ import annotations

import io
import os
from pathlib import Path

import pytest

from hil.replay import write_replay
from hil.replay.serve import ViewerServer
from tests.replay.cdp import HeadlessChromium, chromium_path

#: The only console error allowed: the page's web-font stylesheet, unreachable without network.
OFFLINE_FONT = "https://fonts.googleapis.com/css2"
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
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert colours > RENDERED_COLOURS, page.console[-20:]
    assert page.exceptions == []
    errors = [text for level, text in page.console if level == "error"]
    assert all(OFFLINE_FONT in text for text in errors), errors
