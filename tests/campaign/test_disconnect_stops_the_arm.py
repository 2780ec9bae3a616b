"""Campaign finding robot_disconnect@approach, driver side: a UR program stops when its RTDE /
script link drops, so the simulated arm behind an injected disconnect must come to rest during
the outage instead of finishing its move (it kept going at 50 mm/s for the whole second)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.faults import FaultyRobot
from drivers.interfaces import DisconnectedError, MotionLimits
from drivers.sim.robot import SimRobot, SimRobotConfig
from hil.clock import ManualClock
from hil.config import FaultKind, FaultSpec
from hil.geometry.transform import RigidTransform

LIMITS = MotionLimits(workspace_min_mm=(-400.0, -100.0, -50.0), workspace_max_mm=(400.0, 500.0, 500.0),
                      max_speed_mm_s=100.0, max_accel_mm_s2=500.0, max_angular_speed_rad_s=1.0)


def _sim(clock: ManualClock) -> SimRobot:
    return SimRobot("robot", LIMITS, SimRobotConfig(driver="sim"), clock)


def _start_move(robot: FaultyRobot | SimRobot, clock: ManualClock) -> RigidTransform:
    T0 = robot.state_now().T_robot_from_tcp
    target = RigidTransform(T0.R, T0.t + np.array([0.0, 0.0, -60.0]))
    robot.move_linear(target, 50.0, 500.0, blocking=False)  # 1.3 s at 50 mm/s
    clock.advance(0.3)
    assert robot.state_now().tcp_speed_mm_s == pytest.approx(50.0, abs=0.5)
    return target


def test_an_injected_disconnect_stops_the_arm_from_the_onset() -> None:
    clock = ManualClock(10**9)
    sim = _sim(clock)
    drop = FaultSpec(kind=FaultKind.ROBOT_DISCONNECT, start_s=0.35, duration_s=1.0)
    robot = FaultyRobot(sim, [drop], clock)
    robot.open()
    _start_move(robot, clock)
    clock.advance(0.09)  # the link dropped 0.35 s after open; a controller tick later it notices
    with pytest.raises(DisconnectedError):
        robot.state_now()
    # decelerating from 50 mm/s at 500 mm/s^2 from the onset: at rest 0.1 s after it, 2.5 mm on
    t_onset = 10**9 + 350_000_000
    p_onset = sim.T_robot_from_tcp_at(t_onset).t
    assert sim.T_robot_from_tcp_at(t_onset + 50_000_000).t[2] < p_onset[2]  # still braking
    clock.advance(0.5)
    p_rest = sim.T_robot_from_tcp_at(clock.now_ns()).t
    assert float(np.linalg.norm(p_rest - p_onset)) == pytest.approx(2.5, abs=0.05)
    clock.advance(0.5)  # the link is back: the arm is at rest where it stopped
    st = robot.state_now()
    assert st.tcp_speed_mm_s < 1e-6
    assert np.allclose(st.T_robot_from_tcp.t, p_rest)


def test_without_a_disconnect_the_move_runs_to_its_target() -> None:
    clock = ManualClock(10**9)
    robot = FaultyRobot(_sim(clock), [], clock)
    robot.open()
    target = _start_move(robot, clock)
    clock.advance(2.0)
    assert np.allclose(robot.state_now().T_robot_from_tcp.t, target.t, atol=1e-6)


def test_connection_lost_holds_a_servo_follow_and_is_idempotent() -> None:
    clock = ManualClock(10**9)
    sim = _sim(clock)
    sim.open()
    T0 = sim.state_now().T_robot_from_tcp
    sim.servo(RigidTransform(T0.R, T0.t + np.array([0.0, 0.0, -0.3])), 0.008)
    clock.advance(0.01)
    sim.connection_lost()
    p = sim.state_now().T_robot_from_tcp.t
    sim.connection_lost()
    clock.advance(0.5)
    assert np.allclose(sim.state_now().T_robot_from_tcp.t, p)
    assert sim.state_now().tcp_speed_mm_s < 1e-6
