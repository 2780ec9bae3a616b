"""The controller's pipeline with a perception feed: it takes located pairs from the feed and never
grabs the camera, priming skips what was published before it, the feed's located markers are the
ones perceived, and a locate error travels with its pair."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.interfaces.camera import Frame, StereoFrame
from drivers.interfaces.robot import RobotMode, RobotState, SafetyStatus
from hil.clock import MonotonicClock
from hil.controller.located import LocatedMarkers
from hil.controller.metrics import RunMetrics
from hil.controller.pipeline import DevicePipeline
from hil.controller.prefetch import Prefetched
from hil.geometry.transform import RigidTransform
from hil.perception.process import PerceptionLocateError
from hil.safety.watchdog import WatchdogSet
from hil.session.log import SessionLog

_IMG = np.zeros((0, 0), dtype=np.uint8)


def _pair(k: int, t_ns: int) -> StereoFrame:
    return StereoFrame(Frame(_IMG, t_ns, k), Frame(_IMG, t_ns, k))


class FakeFeed:
    """Hands out the queued results in order (what the perception process would publish)."""

    def __init__(self, items: list[Prefetched]) -> None:
        self.items = items
        self.produced = 0
        self.overwritten = 0
        self.takes: list[float] = []

    def ready(self) -> bool:
        return bool(self.items)

    def take(self, timeout_s: float, wake: Callable[[], bool] | None = None) -> Prefetched | None:
        self.takes.append(timeout_s)
        self.produced += 1
        return self.items.pop(0)

    def stop(self, timeout_s: float | None = None) -> None:
        """Nothing to stop."""


class FeedCamera:
    """A camera whose pairs come from a feed: grabbing it is a test failure."""

    name = "camera"
    frame_rate_hz = 15.0

    def __init__(self, feed: FakeFeed) -> None:
        self.perception_feed = feed

    def grab(self, timeout_s: float) -> StereoFrame:
        raise AssertionError("the pipeline grabbed the camera")


class StillRobot:
    def __init__(self, st: RobotState) -> None:
        self.st = st

    def state_now(self) -> RobotState:
        return self.st


class Est:
    """What ``DevicePipeline.read`` writes into the estimate."""

    def __init__(self) -> None:
        self.last_frame: StereoFrame | None = None
        self.states: list[RobotState] = []

    def record_robot_state(self, st: RobotState) -> None:
        self.states.append(st)


@pytest.fixture
def make(tmp_path: Path) -> Iterator[Callable[[FakeFeed], DevicePipeline]]:
    """Pipelines on a feed camera, a still robot and a session log (closed at the end)."""
    sessions: list[SessionLog] = []

    def build(feed: FakeFeed) -> DevicePipeline:
        clock = MonotonicClock()
        cam: Any = FeedCamera(feed)
        st = RobotState(RigidTransform.identity(), np.zeros(6), RobotMode.IDLE, SafetyStatus.NORMAL,
                        clock.now_ns())
        robot: Any = StillRobot(st)
        wd = WatchdogSet({"camera": 10.0, "robot": 10.0, "tracker": 10.0})
        sessions.append(SessionLog(tmp_path / f"s{len(sessions)}.jsonl", clock, {}))
        return DevicePipeline(cam, robot, None, clock, _never_locate, wd, sessions[-1], RunMetrics())

    yield build
    for s in sessions:
        s.close()


def _never_locate(frame: StereoFrame) -> np.ndarray[Any, Any]:
    raise AssertionError("the pipeline located a pair the perception process had located")


def _located(frame: StereoFrame, n: int) -> Prefetched:
    pts = np.arange(3.0 * n).reshape(n, 3)
    return Prefetched(frame, LocatedMarkers.of(frame, pts, pts[:, :2], pts[:, :2]), None, frame.left.seq)


def test_the_pipeline_takes_located_pairs_from_the_feed_and_never_grabs(
        make: Callable[[FakeFeed], DevicePipeline], tmp_path: Path) -> None:
    now = MonotonicClock().now_ns()
    stale, fresh, nxt = _pair(1, now - 10**9), _pair(2, now), _pair(3, now)
    feed = FakeFeed([_located(stale, 1), _located(fresh, 2), _located(nxt, 4)])
    p = make(feed)
    assert p.feed is feed
    p.prime()
    assert len(feed.items) == 1   # skipped the stale, primed on the fresh
    assert feed.items[0].frame is nxt
    est: Any = Est()
    with p.prefetching(enabled=False):           # the feed is the prefetcher, enabled or not
        assert p.prefetch is feed
        st = p.read(est)
        assert st is not None
        assert est.last_frame is nxt
        pts = p.located(nxt)
    assert np.array_equal(pts, np.arange(12.0).reshape(4, 3))
    assert p.last_located is not None
    assert p.last_located.counts == (4, 4, 4)
    assert p.prefetch is None
    lines = (tmp_path / "s0.jsonl").read_text().splitlines()
    stopped = [line for line in lines if "frame_prefetch_stopped" in line]
    assert len(stopped) == 1
    assert '"process":true' in stopped[0].replace(" ", "")


def test_a_locate_error_travels_with_its_pair(make: Callable[[FakeFeed], DevicePipeline]) -> None:
    frame = _pair(5, MonotonicClock().now_ns())
    err = PerceptionLocateError("VisionError: no markers")
    feed = FakeFeed([Prefetched(frame, None, err, 5)])
    p = make(feed)
    est: Any = Est()
    assert p.read(est) is not None
    with pytest.raises(PerceptionLocateError, match="VisionError: no markers"):
        p.located(frame)
