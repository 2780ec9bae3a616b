"""The frame prefetcher (hil/controller/prefetch.py) on a scripted camera, and through the controller.

The camera's ``grab`` blocks until the test hands it the next item (a pair or an exception), so
every step is ordered by the test; the only waits are on events the worker sets (bounded, to fail
instead of hang) and one short mailbox timeout. The last test runs the controller on the wall
clock (the prefetcher exists only there) for ~0.3 s: it asserts outcomes, never timings. The soak
test (tests/campaign/test_soak.py) shows the stream going on across frame boundaries.
"""

from __future__ import annotations

import queue
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.interfaces.camera import Frame, StereoFrame
from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError, LifecycleError
from drivers.interfaces.lifecycle import DeviceState
from drivers.interfaces.robot import MotionLimits
from hil.clock import MonotonicClock
from hil.controller.config import ProcedureConfig
from hil.controller.controller import Controller
from hil.controller.fsm import Event
from hil.controller.operator_input import OperatorView
from hil.controller.plan_file import load_plan
from hil.controller.planning import RigGeometry
from hil.controller.prefetch import FramePrefetcher, Prefetched, realtime_switch_interval
from hil.errors import VisionError
from hil.geometry.transform import RigidTransform
from hil.session import SessionLog, read_session_log

from .fakes import FakeRobot, StubCamera

WAIT_S = 10.0   # upper bound on an event wait: only reached when the code under test is broken


def _pair(seq: int) -> StereoFrame:
    img = np.zeros((4, 4), np.uint8)
    return StereoFrame(Frame(img, 1000 * seq, seq), Frame(img, 1000 * seq, seq))


class ScriptedCamera(StubCamera):
    """``grab`` returns (or raises) the next item the test puts in :attr:`script`, blocking until
    there is one; it records every call and signals ``called[n]`` when call ``n`` starts."""

    def __init__(self) -> None:
        super().__init__(frame_rate_hz=15.0, image_size=(4, 4))
        self.script: queue.Queue[StereoFrame | Exception] = queue.Queue()
        self.calls = 0
        self.timeouts: list[float] = []
        self.called = [threading.Event() for _ in range(32)]

    def grab(self, timeout_s: float) -> StereoFrame:
        self.require_active("grab")
        self.calls += 1
        self.timeouts.append(timeout_s)
        self.called[self.calls].set()
        item = self.script.get(timeout=WAIT_S)
        self.require_active("grab")   # closed while waiting: a real driver refuses too
        if isinstance(item, Exception):
            raise item
        return item


def _locate(frame: StereoFrame) -> np.ndarray:
    """One marker at (seq, 0, 0) mm: the result names the pair it came from."""
    return np.array([[float(frame.left.seq), 0.0, 0.0]])


@pytest.fixture
def cam() -> ScriptedCamera:
    c = ScriptedCamera()
    c.open()
    return c


@pytest.fixture
def pf(cam: ScriptedCamera) -> Iterator[FramePrefetcher]:
    p = FramePrefetcher(cam, _locate, grab_timeout_s=0.3)
    yield p
    cam.script.put(_pair(999))   # release a blocked grab
    p.stop()
    assert not p.running


def _wait_call(cam: ScriptedCamera, n: int) -> None:
    assert cam.called[n].wait(WAIT_S), f"grab call {n} never started"


def test_results_arrive_in_order_with_their_points(cam: ScriptedCamera, pf: FramePrefetcher) -> None:
    pf.start()
    got: list[Prefetched] = []
    for seq in (1, 2, 3):
        cam.script.put(_pair(seq))
        got.append(pf.take(timeout_s=WAIT_S))
    assert [g.seq for g in got] == [1, 2, 3]
    assert [g.frame.left.seq for g in got] == [1, 2, 3]
    assert [g.points_mm.tolist() for g in got if g.points_mm is not None] == [[[1.0, 0, 0]], [[2.0, 0, 0]],
                                                                             [[3.0, 0, 0]]]
    assert all(g.error is None for g in got)
    assert pf.overwritten == 0
    assert cam.timeouts[0] == 0.3   # the worker grabs with the configured timeout


def test_latest_wins_and_overwrites_are_counted(cam: ScriptedCamera, pf: FramePrefetcher) -> None:
    pf.start()
    for seq in (1, 2, 3):
        cam.script.put(_pair(seq))
    _wait_call(cam, 4)   # the worker posted pair 3 before it started the 4th grab
    assert pf.ready()
    got = pf.take(timeout_s=WAIT_S)
    assert got.frame.left.seq == 3
    assert got.seq == 3
    assert pf.overwritten == 2
    assert pf.produced == 3
    assert not pf.ready()


def test_a_grab_error_is_raised_in_the_caller_as_is(cam: ScriptedCamera, pf: FramePrefetcher) -> None:
    pf.start()
    err = DisconnectedError("camera", "stream gone (GigE heartbeat)")
    cam.script.put(err)
    with pytest.raises(DisconnectedError) as info:
        pf.take(timeout_s=WAIT_S)
    assert info.value is err
    assert (info.value.device, info.value.message) == ("camera", "stream gone (GigE heartbeat)")
    assert str(info.value) == "camera: stream gone (GigE heartbeat)"
    # the worker grabs again only after the error was taken; then pairs flow again
    _wait_call(cam, 2)
    cam.script.put(_pair(7))
    assert pf.take(timeout_s=WAIT_S).frame.left.seq == 7


def test_an_error_waits_to_be_taken_before_the_next_grab(cam: ScriptedCamera, pf: FramePrefetcher) -> None:
    pf.start()
    cam.script.put(DeviceTimeoutError("camera", "no stereo pair within 0.3 s"))
    cam.script.put(_pair(1))   # would be grabbed at once if the worker did not wait
    _wait_call(cam, 1)
    assert not cam.called[2].wait(0.05)   # still waiting for the error to be taken
    assert cam.calls == 1
    with pytest.raises(DeviceTimeoutError, match=r"^camera: no stereo pair within 0.3 s$"):
        pf.take(timeout_s=WAIT_S)
    assert pf.take(timeout_s=WAIT_S).frame.left.seq == 1


def test_nothing_within_the_timeout_is_a_device_timeout_naming_the_camera(
        cam: ScriptedCamera, pf: FramePrefetcher) -> None:
    pf.start()
    _wait_call(cam, 1)   # the worker waits in grab; nothing comes
    with pytest.raises(DeviceTimeoutError) as info:
        pf.take(timeout_s=0.02)
    assert info.value.device == "camera"
    assert info.value.message == "no stereo pair within 0.02 s"


def test_an_operator_input_ends_the_wait_without_a_pair(cam: ScriptedCamera, pf: FramePrefetcher) -> None:
    """The supervisor never waits out a frame for an operator: take() returns None as soon as the
    wake condition holds, and the pair that then arrives is taken by the next call."""
    pf.start()
    _wait_call(cam, 1)   # the worker waits in grab; no pair yet
    waiting = threading.Event()
    threading.Timer(0.01, waiting.set).start()
    assert pf.take(timeout_s=WAIT_S, wake=waiting.is_set) is None
    cam.script.put(_pair(1))
    got = pf.take(timeout_s=WAIT_S)
    assert got is not None
    assert got.frame.left.seq == 1


def test_a_ready_pair_is_taken_even_with_an_input_waiting(cam: ScriptedCamera, pf: FramePrefetcher) -> None:
    pf.start()
    cam.script.put(_pair(1))
    _wait_call(cam, 2)   # the pair was posted and the worker waits for the next
    got = pf.take(timeout_s=WAIT_S, wake=lambda: True)
    assert got is not None
    assert got.frame.left.seq == 1


def test_a_locate_error_travels_with_its_frame(cam: ScriptedCamera) -> None:
    boom = VisionError("left image 4x4 does not fit the calibration (1920x1080)")

    def bad_locate(frame: StereoFrame) -> np.ndarray:
        raise boom

    pf = FramePrefetcher(cam, bad_locate, grab_timeout_s=0.3)
    pf.start()
    try:
        cam.script.put(_pair(1))
        got = pf.take(timeout_s=WAIT_S)
    finally:
        cam.script.put(_pair(2))
        pf.stop()
    assert got.frame.left.seq == 1
    assert got.points_mm is None
    assert got.error is boom


def test_stop_joins_the_worker_blocked_in_grab(cam: ScriptedCamera, pf: FramePrefetcher) -> None:
    pf.start()
    _wait_call(cam, 1)
    assert pf.running
    cam.script.put(_pair(1))   # the grab in progress returns...
    pf.stop()                  # ...and the worker ends without posting or grabbing again
    assert not pf.running
    assert cam.calls == 1
    assert not pf.ready()
    pf.stop()   # idempotent


def test_closing_the_camera_ends_the_worker_quietly_and_it_never_grabs_again(
        cam: ScriptedCamera, pf: FramePrefetcher) -> None:
    pf.start()
    cam.script.put(_pair(1))
    assert pf.take(timeout_s=WAIT_S).frame.left.seq == 1
    _wait_call(cam, 2)
    cam.close()
    cam.script.put(_pair(2))   # the blocked grab wakes up on a closed camera: LifecycleError
    assert pf.wait_ended(WAIT_S)
    assert cam.calls == 2   # no grab after the close
    assert not pf.ready()   # the LifecycleError was not delivered as a fault
    # once the worker has ended a take is a direct grab: the closed camera's own error
    with pytest.raises(LifecycleError, match="needs state active"):
        pf.take(timeout_s=0.01)
    assert cam.calls == 2


def test_stop_before_start_and_a_closed_camera_never_grab() -> None:
    cam = ScriptedCamera()
    cam.open()
    cam.close()
    pf = FramePrefetcher(cam, _locate, grab_timeout_s=0.3)
    pf.start()
    pf.stop()
    assert not pf.running
    assert cam.calls == 0


def test_bad_grab_timeout_is_refused(cam: ScriptedCamera) -> None:
    with pytest.raises(ValueError, match="grab timeout"):
        FramePrefetcher(cam, _locate, grab_timeout_s=0.0)


def test_realtime_switch_interval_is_set_and_restored() -> None:
    before = sys.getswitchinterval()
    with realtime_switch_interval(0.0005):
        assert sys.getswitchinterval() == pytest.approx(0.0005)
        with realtime_switch_interval(0.01):   # never raised above the current value
            assert sys.getswitchinterval() == pytest.approx(0.0005)
        assert sys.getswitchinterval() == pytest.approx(0.0005)
    assert sys.getswitchinterval() == before


# ---------------------------------------------------------------------- through the controller, in real time
class _FailingCamera(StubCamera):
    """30 Hz pairs on the wall clock (a grab waits one frame period), ``ok`` of them, then every
    grab raises ``DisconnectedError``; counts the grabs made after ``close``."""

    def __init__(self, clock: MonotonicClock, ok: int) -> None:
        super().__init__(frame_rate_hz=30.0, image_size=(4, 4))
        self.clock, self.ok, self.seq, self.grabs_after_close = clock, ok, 0, 0

    def grab(self, timeout_s: float) -> StereoFrame:
        if self.state is DeviceState.CLOSED:
            self.grabs_after_close += 1
        self.require_active("grab")
        self.clock.sleep(1 / 30)
        self.seq += 1
        if self.seq > self.ok:
            raise DisconnectedError("camera", "stream gone (test)")
        img = np.zeros((4, 4), np.uint8)
        t_ns = self.clock.now_ns() - 10_000_000   # exposed 10 ms ago
        return StereoFrame(Frame(img, t_ns, self.seq), Frame(img, t_ns, self.seq))


class _Ticks:
    """No command; the run ends after ``n`` ticks."""

    def __init__(self, n: int) -> None:
        self.n = n

    def poll(self, view: OperatorView) -> Event | None:
        self.n -= 1
        return None

    def finished(self, view: OperatorView) -> bool:
        return self.n <= 0


@pytest.mark.parametrize("prefetch", [False, True])
def test_a_camera_fault_reaches_the_controller_the_same_with_and_without_prefetch(
        tmp_path: Path, prefetch: bool) -> None:
    """Real time (MonotonicClock, ~0.3 s): the same fault reason either way, and after ``run``
    no prefetch thread is left and the closed camera is never grabbed."""
    clock = MonotonicClock()
    cam = _FailingCamera(clock, ok=3)
    robot = FakeRobot(clock)  # type: ignore[arg-type]  # any Clock does
    cam.open()
    robot.open()
    log = SessionLog(tmp_path / "s.jsonl", clock)
    ctl = Controller(camera=cam, robot=robot, tracker=None, clock=clock, locate=_locate,
                     plan=load_plan("configs/plans/sim_plan.json"),
                     rig=RigGeometry(RigidTransform.identity(), np.zeros((3, 3)), RigidTransform.identity()),
                     procedure=ProcedureConfig(camera_prefetch=prefetch), limits=MotionLimits(),
                     watchdog_ages_s={"camera": 0.25, "robot": 0.05}, session=log, operator=_Ticks(6))
    ctl.run()
    assert not any(t.name == "frame_prefetch" for t in threading.enumerate())
    cam.close()
    log.close()
    assert ctl.faults == ["camera: stream gone (test)"]
    assert ctl.frames >= 2   # the pairs before the fault were taken
    assert cam.grabs_after_close == 0
    stopped = [r for r in read_session_log(log.path) if r["event"] == "frame_prefetch_stopped"]
    assert len(stopped) == (1 if prefetch else 0)
