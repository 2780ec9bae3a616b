"""The supervisor's robot raises what the servo loop met: a servo command the driver rejected
faults the controller at its next read, in-process (the simulated runs) as in the servo process —
never retried silently while the procedure goes on; a stop that cannot be delivered raises the
device's error at every request, the supervisor's retries included."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from drivers.interfaces.errors import DeviceFaultError, DisconnectedError
from drivers.interfaces.robot import MotionLimits
from hil.clock import ManualClock
from hil.geometry.transform import RigidTransform
from hil.servo.client import ServoRobot, in_process_servo
from hil.servo.limiter import RateLimiter
from hil.servo.link import InProcessLink
from hil.servo.loop import EV_COMMAND_FAILED, EV_MOVE_DONE, EV_MOVE_STARTED, EV_STOP_DELIVERED, EV_STOP_FAILED
from tests.controller.fakes import DroppingRobot, FakeRobot


class RejectingRobot(FakeRobot):
    def _servo(self, T: RigidTransform, period_s: float) -> None:
        raise DeviceFaultError(self.name, "motion command rejected by the controller (test)")


Rig = tuple[ManualClock, FakeRobot, ServoRobot, list[str]]


@contextmanager
def _in_process(inner_type: type[FakeRobot]) -> Iterator[Rig]:
    """``inner_type`` behind an in-process servo loop on a manual clock, with the events it
    reported; both robots closed on every path."""
    clock = ManualClock(10**9)
    limits = MotionLimits()
    inner = inner_type(clock, limits)
    inner.open()
    events: list[str] = []
    robot = in_process_servo(inner, limits, RateLimiter(60.0, 400.0, 0.5), clock,
                             lambda k, f: events.append(k))
    robot.open()
    try:
        yield clock, inner, robot, events
    finally:
        robot.close()
        inner.close()


def test_a_rejected_servo_command_is_raised_at_the_next_read_in_process() -> None:
    with _in_process(RejectingRobot) as (clock, inner, robot, events):
        now = clock.now_ns()
        robot.track(inner.pose, np.zeros(3), np.zeros(3), t_ref_ns=now, valid_until_ns=now + 10**9,
                    exposure_t_ns=now, frame_seq=1, speed_scale=1.0, max_horizon_s=0.0, lead_s=0.0)
        link = robot.link
        assert isinstance(link, InProcessLink)
        link.step(clock.now_ns())
        with pytest.raises(DeviceFaultError, match="motion command rejected by the controller"):
            robot.state_now()
        assert events == [EV_COMMAND_FAILED]   # the loop's event reached the session log too
        assert robot.state_now().safety.value == "normal"   # raised once; the state reads again


def test_every_retried_stop_raises_the_link_error_in_process() -> None:
    """In-process nothing steps the loop while ``stop`` waits: a retried request must learn its
    failure from the kick itself (it used to wait the whole ack timeout, then blame the loop)."""
    with _in_process(DroppingRobot) as (clock, inner, robot, events):
        assert isinstance(inner, DroppingRobot)
        inner.down = True
        for _ in range(3):
            with pytest.raises(DisconnectedError, match="link lost"):
                robot.stop()
            clock.advance(0.05)
        inner.down = False
        robot.stop()
        robot.state_now()   # (takes the loop's newest events)
        assert events == [EV_STOP_FAILED] * 3 + [EV_STOP_DELIVERED]


def test_a_blocking_move_in_process_steps_the_loop_on_its_clock_until_the_arm_is_there() -> None:
    with _in_process(FakeRobot) as (clock, inner, robot, events):
        start = inner.pose
        target = RigidTransform(start.R, start.t + np.array([0.0, 25.0, 0.0]))   # 0.5 s + 0.25 s at 50, 200
        t0 = clock.now_ns()
        robot.move_linear(target, 50.0, 200.0)
        assert np.allclose(inner.pose.t, target.t, atol=1e-9)
        assert (clock.now_ns() - t0) * 1e-9 == pytest.approx(0.75, abs=2 / robot.control_rate_hz)
        assert [c for c, _ in inner.calls].count("servo") >= 0.75 * robot.control_rate_hz
        assert "move_linear" not in [c for c, _ in inner.calls]   # streamed, never a moveL
        assert events == [EV_MOVE_STARTED, EV_MOVE_DONE]


def test_a_move_the_loop_refuses_raises_at_the_wait() -> None:
    with _in_process(RejectingRobot) as (_, inner, robot, _events):
        target = RigidTransform(inner.pose.R, inner.pose.t + np.array([0.0, 25.0, 0.0]))
        with pytest.raises(DeviceFaultError, match="motion command rejected"):
            robot.move_linear(target, 50.0, 200.0)
