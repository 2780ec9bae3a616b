"""The supervisor's robot raises what the servo loop met: a servo command the driver rejected
faults the controller at its next read, in-process (the simulated runs) as in the servo process —
never retried silently while the procedure goes on; a stop that cannot be delivered raises the
device's error at every request, the supervisor's retries included."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.interfaces.errors import DeviceFaultError, DisconnectedError
from drivers.interfaces.robot import MotionLimits
from hil.clock import ManualClock
from hil.geometry.transform import RigidTransform
from hil.servo.client import in_process_servo
from hil.servo.limiter import RateLimiter
from hil.servo.link import InProcessLink
from hil.servo.loop import EV_COMMAND_FAILED, EV_STOP_DELIVERED, EV_STOP_FAILED
from tests.controller.fakes import FakeRobot


class RejectingRobot(FakeRobot):
    def _servo(self, T: RigidTransform, period_s: float) -> None:
        raise DeviceFaultError(self.name, "motion command rejected by the controller (test)")


def test_a_rejected_servo_command_is_raised_at_the_next_read_in_process() -> None:
    clock = ManualClock(10**9)
    limits = MotionLimits()
    inner = RejectingRobot(clock, limits)
    inner.open()
    events: list[str] = []
    robot = in_process_servo(inner, limits, RateLimiter(60.0, 400.0, 0.5), clock,
                             lambda k, f: events.append(k))
    robot.open()
    try:
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
    finally:
        robot.close()
        inner.close()


class UnreachableRobot(FakeRobot):
    """Its stop raises while ``down`` (a lost link)."""

    down = True

    def _stop(self, decel_mm_s2: float) -> None:
        if self.down:
            raise DisconnectedError(self.name, "link lost (test)")
        super()._stop(decel_mm_s2)


def test_every_retried_stop_raises_the_link_error_in_process() -> None:
    """In-process nothing steps the loop while ``stop`` waits: a retried request must learn its
    failure from the kick itself (it used to wait the whole ack timeout, then blame the loop)."""
    clock = ManualClock(10**9)
    limits = MotionLimits()
    inner = UnreachableRobot(clock, limits)
    inner.open()
    events: list[str] = []
    robot = in_process_servo(inner, limits, RateLimiter(60.0, 400.0, 0.5), clock,
                             lambda k, f: events.append(k))
    robot.open()
    try:
        for _ in range(3):
            with pytest.raises(DisconnectedError, match="link lost"):
                robot.stop()
            clock.advance(0.05)
        inner.down = False
        robot.stop()
        robot.state_now()   # (takes the loop's newest events)
        assert events == [EV_STOP_FAILED] * 3 + [EV_STOP_DELIVERED]
    finally:
        robot.close()
        inner.close()
