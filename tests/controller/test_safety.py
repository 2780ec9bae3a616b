"""Safety layer refusals (nothing is sent) and watchdogs."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from drivers.interfaces.robot import MotionLimits, RobotState, SafetyStatus
from hil.clock import ManualClock
from hil.geometry.transform import RigidTransform
from hil.safety import SafetyLayer, SafetyViolationError, Watchdog, WatchdogSet
from tests.controller.fakes import FakeRobot

LIMITS = MotionLimits(workspace_min_mm=(-200.0, -200.0, 0.0), workspace_max_mm=(200.0, 200.0, 400.0),
                      max_speed_mm_s=50.0, max_accel_mm_s2=200.0, max_angular_speed_rad_s=0.5)


def _layer() -> tuple[SafetyLayer, FakeRobot, ManualClock, list[tuple[str, dict[str, Any]]]]:
    clock = ManualClock(10**9)
    robot = FakeRobot(clock)
    robot.open()
    log: list[tuple[str, dict[str, Any]]] = []
    layer = SafetyLayer(robot, LIMITS, clock, robot_state_max_age_s=0.05,
                        log=lambda e, f: log.append((e, f)))
    return layer, robot, clock, log


def _at(x: float, y: float = 0.0, z: float = 300.0) -> RigidTransform:
    return RigidTransform.from_translation((x, y, z))


class TestRefusals:
    @pytest.mark.parametrize(("target", "speed", "accel", "check"), [
        (_at(250.0), 10.0, 100.0, "workspace"),
        (_at(0.0, 0.0, -1.0), 10.0, 100.0, "workspace"),
        (_at(10.0), 60.0, 100.0, "speed"),
        (_at(10.0), 0.0, 100.0, "speed"),
        (_at(10.0), float("nan"), 100.0, "speed"),
        (_at(10.0), 10.0, 300.0, "acceleration"),
    ])
    def test_move_linear_refusal_is_never_sent(self, target: RigidTransform, speed: float, accel: float,
                                               check: str) -> None:
        layer, robot, _, log = _layer()
        with pytest.raises(SafetyViolationError) as ei:
            layer.move_linear(target, speed, accel)
        assert ei.value.check == check
        assert robot.calls == []
        assert log[-1][0] == "command_refused"
        assert log[-1][1]["check"] == check
        assert (layer.commands_sent, layer.commands_refused) == (0, 1)

    def test_servo_speed_refusal(self) -> None:
        layer, robot, _, _ = _layer()
        with pytest.raises(SafetyViolationError, match="speed"):
            layer.servo(_at(1.0), 0.01)  # 100 mm/s
        assert robot.calls == []

    def test_servo_acceleration_refusal_from_rest(self) -> None:
        layer, robot, _, _ = _layer()
        with pytest.raises(SafetyViolationError) as ei:
            layer.servo(_at(0.4), 0.01)  # 40 mm/s from rest in 10 ms = 4000 mm/s^2
        assert ei.value.check == "acceleration"
        assert robot.calls == []

    def test_servo_angular_speed_refusal(self) -> None:
        layer, robot, _, _ = _layer()
        T = RigidTransform.from_rotvec((0.0, 0.0, 0.01), (0.0, 0.0, 300.0))
        with pytest.raises(SafetyViolationError) as ei:
            layer.servo(T, 0.01)  # 1 rad/s
        assert ei.value.check == "angular_speed"
        assert robot.calls == []

    def test_servo_within_limits_is_sent_and_ramps(self) -> None:
        layer, robot, clock, log = _layer()
        x = 0.0
        v = 0.0
        for _ in range(20):
            v = min(v + 1.5, 40.0)  # 150 mm/s^2 at 100 Hz
            x += v * 0.01
            clock.advance(0.01)
            layer.servo(_at(x), 0.01)
        assert len(robot.calls) == 20
        assert log[-1][0] == "command_sent"

    def test_stale_robot_state_refuses(self) -> None:
        layer, robot, _, _ = _layer()
        robot.state_delay_ns = 60_000_000
        with pytest.raises(SafetyViolationError) as ei:
            layer.move_linear(_at(10.0), 10.0, 100.0)
        assert ei.value.check == "state_age"
        assert robot.calls == []

    def test_protective_stop_refuses(self) -> None:
        layer, robot, _, _ = _layer()
        robot.safety_status = SafetyStatus.PROTECTIVE_STOP
        with pytest.raises(SafetyViolationError) as ei:
            layer.servo(_at(0.01), 0.01)
        assert ei.value.check == "robot_safety"
        assert robot.calls == []

    def test_nonpositive_period_refuses(self) -> None:
        layer, robot, _, _ = _layer()
        with pytest.raises(SafetyViolationError) as ei:
            layer.servo(_at(0.0), 0.0)
        assert ei.value.check == "period"
        assert robot.calls == []

    def test_stop_is_never_refused_and_restarts_the_stream_from_rest(self) -> None:
        layer, robot, _, _ = _layer()
        robot.safety_status = SafetyStatus.PROTECTIVE_STOP
        layer.stop("test")
        assert robot.calls == [("stop", None)]
        robot.safety_status = SafetyStatus.NORMAL
        layer.servo(_at(0.01), 0.01)  # 1 mm/s from rest: fine
        with pytest.raises(SafetyViolationError, match="acceleration"):
            layer.servo(_at(0.4), 0.01)


class TestWatchdogs:
    def test_unarmed_watchdog_is_silent(self) -> None:
        assert Watchdog("camera", 0.1).check(10**12) is None

    def test_no_data_after_arming(self) -> None:
        w = Watchdog("camera", 0.1)
        w.arm(0)
        assert w.check(100_000_000) is None
        assert w.check(100_000_001) == "watchdog: no camera data for 0.100 s > 0.100 s"

    def test_stale_data(self) -> None:
        w = Watchdog("robot", 0.05)
        w.feed(1_000_000_000, 1_000_000_000)
        assert w.check(1_050_000_000) is None
        assert w.check(1_060_000_000) == "watchdog: robot data 0.060 s old > 0.050 s"
        assert w.age_s(1_060_000_000) == pytest.approx(0.06)

    def test_data_time_not_arrival_time_counts(self) -> None:
        """A frame delivered now but exposed long ago is stale."""
        w = Watchdog("camera", 0.2)
        w.feed(0, 500_000_000)
        assert w.check(500_000_000) == "watchdog: camera data 0.500 s old > 0.200 s"
        assert not w.is_fresh(0, 500_000_000)

    def test_older_data_does_not_refresh(self) -> None:
        w = Watchdog("tracker", 0.2)
        w.feed(1_000_000_000, 1_000_000_000)
        w.feed(900_000_000, 1_000_000_000)
        assert w.last_t_ns == 1_000_000_000

    def test_set_reports_each_violation(self) -> None:
        s = WatchdogSet({"camera": 0.1, "robot": 0.05, "tracker": 0.2})
        s.arm(0)
        s["camera"].feed(0, 0)
        s["robot"].feed(0, 0)
        s["tracker"].feed(0, 0)
        assert s.check(150_000_000) == ["watchdog: camera data 0.150 s old > 0.100 s",
                                        "watchdog: robot data 0.150 s old > 0.050 s"]

    def test_bad_age_is_refused(self) -> None:
        with pytest.raises(ValueError, match="max_age_s must be > 0"):
            Watchdog("camera", 0.0)


class _TrackingFake(FakeRobot):
    """A fake robot that takes tracking setpoints (the servo loop's client) and counts state reads."""

    def __init__(self, clock: ManualClock) -> None:
        super().__init__(clock)
        self.reads = 0
        self.setpoints: list[RigidTransform] = []

    def _state_now(self) -> RobotState:
        self.reads += 1
        return super()._state_now()

    def start_tracking(self) -> int:
        return 1

    def hold(self) -> None:
        self.calls.append(("hold", None))

    def move_profile_done(self) -> bool:
        return True

    def track(self, T_robot_from_tcp: RigidTransform, v_mm_s: Any, w_rad_s: Any, *, t_ref_ns: int,
              valid_until_ns: int, exposure_t_ns: int, frame_seq: int, speed_scale: float,
              max_horizon_s: float, lead_s: float) -> None:
        self.setpoints.append(T_robot_from_tcp)


class TestTrack:
    """``track`` checks the state it is given like one it reads, and reads none then."""

    @staticmethod
    def _track(layer: SafetyLayer, state: RobotState | None) -> None:
        z = np.zeros(3)
        layer.track(_at(5.0), z, z, t_ref_ns=0, valid_until_ns=10**12, exposure_t_ns=0, frame_seq=1,
                    speed_scale=1.0, max_horizon_s=0.0, lead_s=0.0, state=state)

    def _layer(self) -> tuple[SafetyLayer, _TrackingFake, ManualClock]:
        clock = ManualClock(10**9)
        robot = _TrackingFake(clock)
        robot.open()
        return SafetyLayer(robot, LIMITS, clock, robot_state_max_age_s=0.05), robot, clock

    def test_given_state_is_used_without_a_read(self) -> None:
        layer, robot, clock = self._layer()
        st = robot.state_now()
        clock.advance(0.049)
        self._track(layer, st)
        assert robot.reads == 1
        assert [T.t.tolist() for T in robot.setpoints] == [[5.0, 0.0, 300.0]]
        assert layer.commands_sent == 1

    def test_without_a_state_it_reads_one(self) -> None:
        layer, robot, _ = self._layer()
        self._track(layer, None)
        assert robot.reads == 1
        assert len(robot.setpoints) == 1

    def test_given_stale_state_refuses(self) -> None:
        layer, robot, clock = self._layer()
        st = robot.state_now()
        clock.advance(0.051)
        with pytest.raises(SafetyViolationError) as ei:
            self._track(layer, st)
        assert ei.value.check == "state_age"
        assert robot.setpoints == []
        assert robot.reads == 1

    def test_given_state_in_protective_stop_refuses(self) -> None:
        layer, robot, _ = self._layer()
        robot.safety_status = SafetyStatus.PROTECTIVE_STOP
        with pytest.raises(SafetyViolationError) as ei:
            self._track(layer, robot.state_now())
        assert ei.value.check == "robot_safety"
        assert robot.setpoints == []

    def test_robot_without_a_servo_loop_is_a_type_error(self) -> None:
        layer, _, _, _ = _layer()
        with pytest.raises(TypeError, match="FakeRobot has no servo loop"):
            self._track(layer, None)
        with pytest.raises(TypeError, match="FakeRobot has no servo loop"):
            layer.hold("test")


def test_move_profile_done_asks_the_servo_loop_and_is_true_without_one() -> None:
    """The arrival check's ``move_profile_done`` is part of the servo client's declared interface
    (``TrackingRobot``), not probed by name: a robot without a servo loop is always done."""
    layer, _, _, _ = _layer()
    assert layer.move_profile_done() is True    # a plain robot runs its own moves

    class _Streaming(_TrackingFake):
        done = False

        def move_profile_done(self) -> bool:
            return self.done

    clock = ManualClock(10**9)
    robot = _Streaming(clock)
    robot.open()
    tracking = SafetyLayer(robot, LIMITS, clock, robot_state_max_age_s=0.05)
    assert tracking.move_profile_done() is False
    robot.done = True
    assert tracking.move_profile_done() is True
