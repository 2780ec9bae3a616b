"""The console on a wall-clock simulated setup with perception in its own process: the controller
thread shows the markers the process located (waiting with the console's wake, so an input is never
held behind a camera), and closing the session ends the processes."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.console.session import ConsoleSession, open_console_session
from hil.perception.camera import PerceptionCamera

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def session(tmp_path: Path) -> Iterator[ConsoleSession]:
    text = (ROOT / "configs" / "sim.toml").read_text()
    text = text.replace("real_time = false", "real_time = true", 1)
    text = text.replace('stereo = "calibration/sim_stereo.json"',
                        f'stereo = "{ROOT / "configs" / "calibration" / "sim_stereo.json"}"', 1)
    cfg = tmp_path / "rt.toml"
    cfg.write_text(text + '\n[perception]\nprocess = "on"\n')
    s = open_console_session(cfg, plan=ROOT / "configs" / "plans" / "sim_plan.json",
                             session_dir=tmp_path / "sessions")
    try:
        yield s
    finally:
        s.close()


def test_the_console_shows_markers_located_in_the_perception_process(session: ConsoleSession) -> None:
    camera = session.devices.camera
    assert isinstance(camera, PerceptionCamera)
    feed = camera.perception_feed
    pid = feed.pid
    assert pid is not None
    deadline = time.monotonic() + 60.0
    while True:
        v = session.runner.latest()
        if v is not None and v.located_counts is not None and v.located_counts[2] > 0:
            break
        assert v is None or not v.error, v.error
        assert time.monotonic() < deadline, "no located markers shown"
        time.sleep(0.05)
    result = session.close()
    assert session.runner.ended
    assert result["error"] is None
    assert feed.exitcode == 0   # ended and reaped
