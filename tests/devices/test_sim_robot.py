"""The robot interface exercised through the simulated UR3."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.interfaces import (
    DeviceState,
    LifecycleError,
    LimitViolationError,
    MotionLimits,
    RobotMode,
    SafetyStatus,
    SafetyStopError,
)
from drivers.sim.robot import SimRobot, SimRobotConfig, trapezoid_duration_s, trapezoid_fraction
from hil.clock import ManualClock
from hil.config.types import TransformConfig
from hil.geometry.transform import RigidTransform
from hil.kinematics.ur import ur_forward

LIMITS = MotionLimits(workspace_min_mm=(-400.0, -100.0, -50.0), workspace_max_mm=(400.0, 500.0, 500.0),
                      max_speed_mm_s=100.0, max_accel_mm_s2=500.0, max_angular_speed_rad_s=1.0)


def _robot(clock: ManualClock, **kw: object) -> SimRobot:
    return SimRobot("robot", LIMITS, SimRobotConfig(driver="sim", **kw), clock)  # type: ignore[arg-type]


def _shifted(T: RigidTransform, d_mm: tuple[float, float, float]) -> RigidTransform:
    return RigidTransform(T.R, T.t + np.asarray(d_mm))


@pytest.fixture
def robot(clock: ManualClock) -> SimRobot:
    r = _robot(clock)
    r.open()
    return r


def test_lifecycle_refusals(clock: ManualClock) -> None:
    r = _robot(clock)
    with pytest.raises(LifecycleError, match=r"state\(\) needs state active"):
        r.state_now()
    with pytest.raises(LifecycleError, match="move_linear"):
        r.move_linear(RigidTransform.identity(), 10.0, 10.0)
    r.open()
    assert r.state is DeviceState.ACTIVE
    with pytest.raises(LifecycleError, match="open"):
        r.open()
    r.close()
    r.close()
    with pytest.raises(LifecycleError, match="servo"):
        r.servo(RigidTransform.identity(), 0.008)
    with pytest.raises(LifecycleError, match="stop"):
        r.stop()


def test_initial_state(robot: SimRobot, clock: ManualClock) -> None:
    s = robot.state_now()
    np.testing.assert_allclose(s.q_rad, robot.cfg.initial_q_rad)
    assert s.T_robot_from_tcp.is_close(ur_forward(s.q_rad), atol_mm=1e-9, atol_rad=1e-9)
    assert (s.mode, s.safety, s.t_ns, s.tcp_speed_mm_s) == (RobotMode.IDLE, SafetyStatus.NORMAL,
                                                             clock.now_ns(), 0.0)
    assert robot.control_rate_hz == 125.0
    assert robot.is_steady()


@pytest.mark.parametrize(("offset", "speed", "accel", "limit"), [
    ((0.0, 0.0, 400.0), 50.0, 100.0, "workspace"),
    ((0.0, -500.0, 0.0), 50.0, 100.0, "workspace"),
    ((0.0, 0.0, -10.0), 150.0, 100.0, "speed"),
    ((0.0, 0.0, -10.0), 0.0, 100.0, "speed"),
    ((0.0, 0.0, -10.0), 50.0, 900.0, "acceleration"),
    ((0.0, 0.0, -10.0), 50.0, math.nan, "acceleration"),
])
def test_move_refused_by_limits_before_reaching_the_arm(
    robot: SimRobot, clock: ManualClock, offset: tuple[float, float, float], speed: float, accel: float,
    limit: str,
) -> None:
    before = robot.state_now()
    segments = len(robot._segments)
    with pytest.raises(LimitViolationError) as info:
        robot.move_linear(_shifted(before.T_robot_from_tcp, offset), speed, accel)
    assert info.value.limit == limit
    assert len(robot._segments) == segments      # nothing reached the simulated arm
    clock.advance(1.0)
    assert robot.state_now().T_robot_from_tcp.is_close(before.T_robot_from_tcp)


def test_blocking_move_arrives_with_trapezoid_timing(robot: SimRobot, clock: ManualClock) -> None:
    T0 = robot.state_now().T_robot_from_tcp
    target = _shifted(T0, (30.0, 0.0, -40.0))
    t0 = clock.now_ns()
    robot.move_linear(target, 50.0, 200.0)
    expected_s, _ = trapezoid_duration_s(50.0, 50.0, 200.0)
    assert clock.now_ns() - t0 == round(expected_s * 1e9)
    s = robot.state_now()
    assert s.T_robot_from_tcp.is_close(target, atol_mm=1e-6, atol_rad=1e-6)
    assert s.mode is RobotMode.IDLE


def test_non_blocking_move_is_moving_along_a_line(robot: SimRobot, clock: ManualClock) -> None:
    T0 = robot.state_now().T_robot_from_tcp
    target = _shifted(T0, (0.0, 0.0, -60.0))
    robot.move_linear(target, 50.0, 200.0, blocking=False)
    clock.advance(0.6)
    s = robot.state_now()
    assert s.mode is RobotMode.MOVING
    assert 0.0 < s.tcp_speed_mm_s <= 50.0 + 1e-6
    off_line = np.linalg.norm(s.T_robot_from_tcp.t[:2] - T0.t[:2])
    assert off_line < 0.05
    assert not robot.is_steady()


def test_servo_follows_with_first_order_lag(robot: SimRobot, clock: ManualClock) -> None:
    T0 = robot.state_now().T_robot_from_tcp
    target = _shifted(T0, (0.5, 0.0, 0.0))
    robot.servo(target, 0.008)
    tau = robot.cfg.servo_time_constant_s
    clock.advance(tau)
    s = robot.state_now()
    assert s.mode is RobotMode.SERVOING
    moved = s.T_robot_from_tcp.t[0] - T0.t[0]
    assert moved == pytest.approx(0.5 * (1 - math.exp(-1.0)), abs=0.01)
    clock.advance(10 * tau)
    assert robot.state_now().T_robot_from_tcp.t[0] - T0.t[0] == pytest.approx(0.5, abs=1e-3)


def test_servo_step_too_fast_is_refused(robot: SimRobot) -> None:
    T0 = robot.state_now().T_robot_from_tcp
    with pytest.raises(LimitViolationError) as info:
        robot.servo(_shifted(T0, (5.0, 0.0, 0.0)), 0.008)     # 625 mm/s
    assert info.value.limit == "speed"
    assert robot.state_now().mode is RobotMode.IDLE


def test_stop_decelerates_along_the_path(robot: SimRobot, clock: ManualClock) -> None:
    T0 = robot.state_now().T_robot_from_tcp
    robot.move_linear(_shifted(T0, (0.0, 0.0, -80.0)), 50.0, 200.0, blocking=False)
    clock.advance(0.5)                                   # cruising at 50 mm/s
    p = robot.state_now().T_robot_from_tcp.t.copy()
    robot.stop(500.0)                                    # 50^2 / (2 * 500) = 2.5 mm in 0.1 s
    clock.advance(0.05)
    s = robot.state_now()
    assert s.mode is RobotMode.MOVING
    assert s.tcp_speed_mm_s == pytest.approx(25.0, abs=1.0)
    clock.advance(0.1)
    s = robot.state_now()
    assert s.mode is RobotMode.IDLE
    np.testing.assert_allclose(s.T_robot_from_tcp.t, p + np.array([0.0, 0.0, -2.5]), atol=0.02)
    clock.advance(1.0)
    np.testing.assert_allclose(robot.state_now().T_robot_from_tcp.t, s.T_robot_from_tcp.t, atol=1e-9)


def test_stop_while_servoing_holds(robot: SimRobot, clock: ManualClock) -> None:
    T0 = robot.state_now().T_robot_from_tcp
    robot.servo(_shifted(T0, (0.5, 0.0, 0.0)), 0.008)
    clock.advance(0.01)
    p = robot.state_now().T_robot_from_tcp.t.copy()
    robot.stop()
    clock.advance(1.0)
    np.testing.assert_allclose(robot.state_now().T_robot_from_tcp.t, p, atol=1e-9)
    assert robot.state_now().mode is RobotMode.IDLE


def test_unreachable_target_gives_a_protective_stop(clock: ManualClock) -> None:
    wide = MotionLimits(workspace_min_mm=(-900.0, -900.0, -900.0), workspace_max_mm=(900.0, 900.0, 900.0))
    r = SimRobot("robot", wide, SimRobotConfig(driver="sim"), clock)
    r.open()
    T0 = r.state_now().T_robot_from_tcp
    with pytest.raises(SafetyStopError, match="protective stop: no inverse kinematics"):
        r.move_linear(RigidTransform(T0.R, np.array([0.0, 800.0, 200.0])), 100.0, 500.0)
    assert r.state_now().safety is SafetyStatus.PROTECTIVE_STOP
    with pytest.raises(SafetyStopError, match="motion refused"):
        r.move_linear(T0, 10.0, 10.0)
    r.stop()  # always allowed
    r.recover()
    assert r.state_now().safety is SafetyStatus.NORMAL
    r.move_linear(_shifted(T0, (0.0, 0.0, -5.0)), 10.0, 100.0)


def test_joint_speed_limit_gives_a_protective_stop(clock: ManualClock) -> None:
    r = _robot(clock, max_joint_speed_rad_s=0.05)
    r.open()
    T0 = r.state_now().T_robot_from_tcp
    with pytest.raises(SafetyStopError, match="joint speed"):
        r.move_linear(_shifted(T0, (80.0, 0.0, 0.0)), 100.0, 500.0)
    assert r.state_now().safety is SafetyStatus.PROTECTIVE_STOP


def test_tcp_offset_is_reported(clock: ManualClock) -> None:
    off = TransformConfig(translation_mm=(0.0, 0.0, 60.0), rotvec_rad=(0.0, 0.0, 0.0))
    r = _robot(clock, T_flange_from_tcp=off)
    r.open()
    s = r.state_now()
    assert s.T_robot_from_tcp.is_close(ur_forward(s.q_rad) @ off.as_transform(), atol_mm=1e-9)


def test_trapezoid_profile() -> None:
    assert trapezoid_duration_s(100.0, 50.0, 100.0) == (2.5, 0.5)
    d, ta = trapezoid_duration_s(1.0, 50.0, 100.0)           # triangular
    assert (d, ta) == pytest.approx((0.2, 0.1))
    assert trapezoid_fraction(0.0, 2.5, 0.2) == 0.0
    assert trapezoid_fraction(1.25, 2.5, 0.2) == pytest.approx(0.5)
    assert trapezoid_fraction(2.5, 2.5, 0.2) == 1.0
