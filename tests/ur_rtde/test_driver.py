"""The UR driver through the real ur-rtde library, over real sockets, against tools/emulators/ursim."""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest

from drivers.interfaces.errors import (
    DeviceFaultError,
    DeviceTimeoutError,
    DisconnectedError,
    LimitViolationError,
    ProtocolError,
    SafetyStopError,
)
from drivers.interfaces.robot import MotionLimits, RobotMode, SafetyStatus
from drivers.ur_rtde.config import UrRtdeRobotConfig
from drivers.ur_rtde.robot import UrRtdeRobot
from hil.clock import MonotonicClock
from hil.geometry.transform import RigidTransform
from hil.kinematics import ur_forward
from tests.ur_rtde.conftest import Ursim, free_loopback_address, make_robot, wait_for

pytestmark = pytest.mark.emulator

HOME_Q = np.array([0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0])


def shifted(T: RigidTransform, d_mm: list[float]) -> RigidTransform:
    return RigidTransform(T.R, T.t + np.asarray(d_mm, dtype=np.float64))


def test_connect_and_read_state(robot: UrRtdeRobot, ursim: Ursim) -> None:
    s = robot.state_now()
    assert s.safety is SafetyStatus.NORMAL
    assert s.mode is RobotMode.IDLE
    np.testing.assert_allclose(s.q_rad, HOME_Q, atol=1e-12)
    assert s.T_robot_from_tcp.is_close(ur_forward(HOME_Q, "ur3"), atol_mm=1e-9, atol_rad=1e-9)
    assert robot.control_rate_hz == 125.0
    assert ursim.control.status()["runtime_state"] == "PLAYING"


def test_move_linear_50_mm_and_read_the_pose_back(robot: UrRtdeRobot, ursim: Ursim) -> None:
    start = robot.state_now().T_robot_from_tcp
    target = shifted(start, [0.0, 0.0, 50.0])
    robot.move_linear(target, 100.0, 500.0)
    s = robot.state_now()
    assert s.T_robot_from_tcp.is_close(target, atol_mm=1e-6, atol_rad=1e-9)
    assert s.tcp_speed_mm_s < 1e-6
    emulated = ursim.control.status()["tcp_pose"]
    np.testing.assert_allclose(np.array(emulated[:3]) * 1000.0, target.t, atol=1e-5)


def test_limits_are_checked_before_anything_is_sent(robot: UrRtdeRobot, ursim: Ursim) -> None:
    start = robot.state_now().T_robot_from_tcp
    with pytest.raises(LimitViolationError, match="workspace"):
        robot.move_linear(shifted(start, [0.0, 0.0, 900.0]), 100.0, 500.0)
    with pytest.raises(LimitViolationError, match="speed"):
        robot.move_linear(shifted(start, [0.0, 0.0, 10.0]), 5000.0, 500.0)
    assert ursim.control.status()["motion"] is None


def test_tool_offset_is_applied_on_the_host(ursim: Ursim) -> None:
    r = make_robot(ursim, T_flange_from_tcp={"translation_mm": (0.0, 0.0, 100.0)})
    r.open()
    try:
        s = r.state_now()
        flange = ur_forward(HOME_Q, "ur3")
        assert s.T_robot_from_tcp.is_close(flange @ RigidTransform.from_translation([0, 0, 100.0]),
                                           atol_mm=1e-9, atol_rad=1e-9)
        r.move_linear(shifted(s.T_robot_from_tcp, [20.0, 0.0, 0.0]), 100.0, 500.0)
        np.testing.assert_allclose(np.array(ursim.control.status()["tcp_pose"][:3]) * 1000.0,
                                   flange.t + np.array([20.0, 0.0, 0.0]), atol=1e-5)
    finally:
        r.close()


def test_servo_a_trajectory(robot: UrRtdeRobot) -> None:
    start = robot.state_now().T_robot_from_tcp
    period_s = 1.0 / robot.control_rate_hz
    n = 100
    modes = set()
    for i in range(1, n + 1):  # 20 mm along x in 0.8 s (25 mm/s), one target per RTDE period
        robot.servo(shifted(start, [20.0 * i / n, 0.0, 0.0]), period_s)
        modes.add(robot.state_now().mode)
        time.sleep(period_s)
    assert RobotMode.SERVOING in modes
    last = shifted(start, [20.0, 0.0, 0.0])
    wait_for(lambda: robot.state_now().T_robot_from_tcp.is_close(last, atol_mm=0.01, atol_rad=1e-6),
             what="servo settles on the last target")
    robot.stop()
    wait_for(lambda: robot.state_now().mode is RobotMode.IDLE, what="idle after stop")


def test_stop_decelerates_a_running_move(robot: UrRtdeRobot) -> None:
    start = robot.state_now().T_robot_from_tcp
    target = shifted(start, [0.0, 0.0, 150.0])
    robot.move_linear(target, 50.0, 1000.0, blocking=False)
    wait_for(lambda: robot.state_now().T_robot_from_tcp.t[2] - start.t[2] > 20.0, what="cruising")
    z_at_stop = robot.state_now().T_robot_from_tcp.t[2]
    robot.stop(decel_mm_s2=250.0)
    wait_for(lambda: robot.state_now().tcp_speed_mm_s < 1e-6, what="at rest")
    overshoot = robot.state_now().T_robot_from_tcp.t[2] - z_at_stop
    # v^2 / (2 a) = 50^2 / 500 = 5 mm of braking, plus 50 mm/s x the command latency (loaded machine:
    # up to ~0.1 s); an abrupt stop would give well under 4 mm on an idle machine
    assert 4.0 < overshoot < 12.0
    assert robot.state_now().T_robot_from_tcp.t[2] < target.t[2] - 50.0


def test_protective_stop_mid_move_raises_and_recovers(robot: UrRtdeRobot, ursim: Ursim) -> None:
    start = robot.state_now().T_robot_from_tcp
    timer = threading.Timer(0.3, ursim.control.protective_stop)
    timer.start()
    try:
        with pytest.raises(SafetyStopError, match="protective_stop"):
            robot.move_linear(shifted(start, [0.0, 100.0, 0.0]), 50.0, 500.0)
    finally:
        timer.cancel()
    s = robot.state_now()
    assert s.safety is SafetyStatus.PROTECTIVE_STOP
    assert s.mode is RobotMode.STOPPED
    assert 0.0 < s.T_robot_from_tcp.t[1] - start.t[1] < 100.0
    with pytest.raises(SafetyStopError, match="motion refused"):
        robot.move_linear(start, 50.0, 500.0)
    robot.recover()
    assert robot.state_now().safety is SafetyStatus.NORMAL
    robot.move_linear(start, 100.0, 500.0)
    assert robot.state_now().T_robot_from_tcp.is_close(start, atol_mm=1e-6, atol_rad=1e-9)


def test_program_stopped_mid_move_is_a_device_fault_not_a_safety_stop(
    robot: UrRtdeRobot, ursim: Ursim
) -> None:
    """The blocking moveL reads the safety bits and the runtime state from one RTDE packet: a
    program stopped on the controller mid-move is named as such (a protective stop, which stops
    the script too, is the test above)."""
    start = robot.state_now().T_robot_from_tcp
    timer = threading.Timer(0.3, ursim.control.stop_program)
    timer.start()
    try:
        with pytest.raises(DeviceFaultError, match="moveL interrupted: the control script stopped"):
            robot.move_linear(shifted(start, [0.0, 100.0, 0.0]), 50.0, 500.0)
    finally:
        timer.cancel()
    s = robot.state_now()
    assert (s.safety, s.mode) == (SafetyStatus.NORMAL, RobotMode.STOPPED)
    robot.recover()
    robot.move_linear(start, 100.0, 500.0)
    assert robot.state_now().T_robot_from_tcp.is_close(start, atol_mm=1e-6, atol_rad=1e-9)


def test_emergency_stop_needs_release_before_recovery(robot: UrRtdeRobot, ursim: Ursim) -> None:
    ursim.control.estop()
    wait_for(lambda: robot.state_now().safety is SafetyStatus.EMERGENCY_STOP, what="e-stop seen")
    with pytest.raises(SafetyStopError, match="emergency stop engaged"):
        robot.recover()
    ursim.control.release()  # the operator twists the e-stop button out
    wait_for(lambda: robot.state_now().safety is not SafetyStatus.EMERGENCY_STOP, what="release seen")
    robot.recover()  # powers on, releases brakes, re-uploads the control script
    s = robot.state_now()
    assert (s.safety, s.mode) == (SafetyStatus.NORMAL, RobotMode.IDLE)
    robot.move_linear(shifted(s.T_robot_from_tcp, [10.0, 0.0, 0.0]), 100.0, 500.0)


def test_disconnect_and_recovery_rebuilds_the_interfaces(robot: UrRtdeRobot, ursim: Ursim) -> None:
    assert ursim.control.drop_connection(1.0) >= 3
    with pytest.raises(DisconnectedError):
        wait_for(lambda: robot.state_now() is None, what="disconnect noticed")
    robot.recover()  # retries until the outage is over, then builds new clients
    s = robot.state_now()
    assert s.safety is SafetyStatus.NORMAL
    robot.move_linear(shifted(s.T_robot_from_tcp, [0.0, 0.0, 20.0]), 100.0, 500.0)
    assert ursim.control.status()["rtde_connections"] == 2


def test_program_stopped_on_the_controller_is_a_device_fault(robot: UrRtdeRobot, ursim: Ursim) -> None:
    ursim.control.stop_program()
    start = robot.state_now().T_robot_from_tcp
    # refused whether the state stream already shows the stopped program (the base class's check
    # before the command) or not yet (the controller's refusal of the command): one error class
    with pytest.raises(DeviceFaultError, match=r"control script\)? is not running"):
        robot.move_linear(shifted(start, [5.0, 0.0, 0.0]), 100.0, 500.0)
    assert robot.state_now().mode is RobotMode.STOPPED
    with pytest.raises(DeviceFaultError, match=r"arm program \(control script\) is not running"):
        robot.move_linear(shifted(start, [5.0, 0.0, 0.0]), 100.0, 500.0)   # refused before sending
    robot.recover()
    robot.move_linear(shifted(start, [5.0, 0.0, 0.0]), 100.0, 500.0)


def test_stalled_arm_times_out_and_is_stopped(ursim: Ursim) -> None:
    r = make_robot(ursim, move_timeout_margin_s=0.3)
    r.open()
    try:
        ursim.control.stall(True)
        start = r.state_now().T_robot_from_tcp
        with pytest.raises(DeviceTimeoutError, match="did not finish"):
            r.move_linear(shifted(start, [0.0, 0.0, 10.0]), 100.0, 500.0)
        ursim.control.stall(False)
        wait_for(lambda: ursim.control.status()["motion"] is None, what="stop after the timeout")
        assert r.state_now().T_robot_from_tcp.is_close(start, atol_mm=1e-9, atol_rad=1e-9)
    finally:
        r.close()


def test_frozen_state_stream_is_a_timeout_then_resumes(robot: UrRtdeRobot, ursim: Ursim) -> None:
    ursim.control.pause_stream(2.0)  # under the client's 2.5 s silence limit
    with pytest.raises(DeviceTimeoutError, match="timestamp stuck"):
        wait_for(lambda: robot.state_now() is None, timeout_s=3.0, what="stale stream noticed")
    wait_for(lambda: _state_ok(robot), timeout_s=3.0, what="stream resumed")


def test_a_state_is_stamped_with_when_the_controller_sampled_it(ursim: Ursim) -> None:
    """``sample_t_ns`` is the controller's timestamp on the host clock: a state read again from a
    stream that went quiet keeps its sample time while ``t_ns`` (the read) moves on, so the
    following supervision compares it with the expectation of that time (hil/safety/following.py)."""
    r = make_robot(ursim, state_max_age_s=5.0)
    r.open()
    try:
        st = r.state_now()
        assert st.sample_t_ns is not None
        assert st.sample_t_ns <= st.t_ns
        ursim.control.pause_stream(1.5)   # under the client's 2.5 s silence limit

        def quiet() -> bool:   # two reads 20 ms apart from the same packet: nothing in flight
            a = r.state_now().sample_t_ns
            time.sleep(0.02)
            return r.state_now().sample_t_ns == a
        wait_for(quiet, timeout_s=2.0, what="the paused stream's last packet")
        before = r.state_now()
        time.sleep(0.1)
        after = r.state_now()
        assert after.sample_t_ns == before.sample_t_ns
        assert after.t_ns - before.t_ns >= 100_000_000
        assert after.sample_t_ns is not None
        assert after.t_ns - after.sample_t_ns >= 100_000_000
        wait_for(lambda: r.state_now().sample_t_ns != after.sample_t_ns, timeout_s=5.0, what="stream resumed")
    finally:
        r.close()


def _state_ok(robot: UrRtdeRobot) -> bool:
    try:
        robot.state_now()
    except DeviceTimeoutError:
        return False
    return True


def test_rtde_watchdog_keeps_an_idle_program_running(robot: UrRtdeRobot, ursim: Ursim) -> None:
    status = ursim.control.status()
    # configured 5 Hz, armed lower so the window outlasts the longest stop at 1000 mm/s^2: from
    # 200 mm/s, 0.2 s; from 1 rad/s, decelerated at 1 rad/s^2 (stopl's aRot = a), 1 s:
    # 1 / (1.5 x (1.0 s + 0.05 s)) = 0.635 Hz
    assert status["watchdog_hz"] == pytest.approx(1.0 / 1.575)
    time.sleep(2 * 1.575)  # two watchdog windows with no motion command: the kicker feeds it
    assert ursim.control.status()["runtime_state"] == "PLAYING"


def test_a_slow_turning_arm_s_watchdog_window_is_set_by_its_linear_stop(ursim: Ursim) -> None:
    # a slow-turning arm: the linear stop is the longest (100 mm/s at 500 mm/s^2: 0.2 s; 0.05 rad/s
    # at 0.5 rad/s^2: 0.1 s): 1 / (1.5 x (0.2 s + 0.05 s)) = 2.667 Hz
    r = UrRtdeRobot("robot", MotionLimits(max_speed_mm_s=100.0, max_accel_mm_s2=500.0,
                                          max_angular_speed_rad_s=0.05),
                    UrRtdeRobotConfig(driver="ur_rtde", host=ursim.host, state_max_age_s=1.0,
                                      controller="cb3"),
                    MonotonicClock())
    r.open()
    try:
        assert ursim.control.status()["watchdog_hz"] == pytest.approx(1.0 / 0.375)
    finally:
        r.close()


def test_recovery_rearms_the_watchdog_at_the_rate_its_kicker_is_paced_for(
        robot: UrRtdeRobot, ursim: Ursim) -> None:
    armed_hz = ursim.control.status()["watchdog_hz"]
    assert armed_hz == pytest.approx(1.0 / 1.575)  # lowered from the configured 5 Hz
    ursim.control.stop_program()
    wait_for(lambda: robot.state_now().mode is RobotMode.STOPPED, what="program stop seen")
    robot.recover()  # re-uploads the script and arms its watchdog again
    # the same window as at connect: the kicker (a third of the armed window) and a blocking stop
    # were sized for it; the configured 5 Hz would let a stop plus one kicker period expire it
    assert ursim.control.status()["watchdog_hz"] == pytest.approx(armed_hz)


def test_slow_controller_responses_still_work(robot: UrRtdeRobot, ursim: Ursim) -> None:
    ursim.control.slow_responses(30.0)
    start = robot.state_now().T_robot_from_tcp
    robot.move_linear(shifted(start, [0.0, 10.0, 0.0]), 100.0, 500.0)
    assert robot.state_now().T_robot_from_tcp.is_close(shifted(start, [0.0, 10.0, 0.0]), atol_mm=1e-6)


def test_unreachable_controller_fails_fast() -> None:
    from drivers.interfaces.robot import MotionLimits
    from drivers.ur_rtde.config import UrRtdeRobotConfig
    from hil.clock import MonotonicClock

    host = free_loopback_address()  # a loopback address where nothing listens
    cfg = UrRtdeRobotConfig(driver="ur_rtde", host=host, connect_timeout_s=0.5)
    r = UrRtdeRobot("robot", MotionLimits(), cfg, MonotonicClock())
    with pytest.raises(DisconnectedError, match=f"cannot reach {re.escape(host)}:30004"):
        r.open()
    assert r.state.value == "configured"


def test_controller_family_mismatch_is_refused(ursim_e_series: Ursim) -> None:
    r = make_robot(ursim_e_series, controller="cb3")
    with pytest.raises(ProtocolError, match=r"PolyScope 5\.11"):
        r.open()


def test_e_series_at_500_hz(ursim_e_series: Ursim) -> None:
    r = make_robot(ursim_e_series)
    r.open()
    try:
        assert r.control_rate_hz == 500.0
        status = ursim_e_series.control.status()
        assert status["frequency_hz"] == 500.0
        assert status["version"].startswith("5.11")
        start = r.state_now().T_robot_from_tcp
        r.move_linear(shifted(start, [0.0, 0.0, 50.0]), 100.0, 500.0)
        assert r.state_now().T_robot_from_tcp.is_close(shifted(start, [0.0, 0.0, 50.0]), atol_mm=1e-6)
        for i in range(1, 101):
            r.servo(shifted(start, [10.0 * i / 100, 0.0, 50.0]), 0.002)
            time.sleep(0.002)
        r.stop()
    finally:
        r.close()


def test_servo_after_a_running_async_move_stops_the_move_first(robot: UrRtdeRobot, ursim: Ursim) -> None:
    start = robot.state_now().T_robot_from_tcp
    robot.move_linear(shifted(start, [0.0, 0.0, 100.0]), 50.0, 500.0, blocking=False)
    wait_for(lambda: robot.state_now().mode is RobotMode.MOVING, what="moving")
    here = robot.state_now().T_robot_from_tcp
    robot.servo(shifted(here, [0.0, 0.0, 1.0]), 0.008)
    wait_for(lambda: ursim.control.status()["motion"] == "servo", what="servo running")
    wait_for(lambda: robot.state_now().tcp_speed_mm_s < 1e-6, what="servo settled")
    assert robot.state_now().T_robot_from_tcp.t[2] < start.t[2] + 50.0  # the 100 mm move did not go on
    robot.stop()


def test_close_over_a_dead_link_does_not_wait_on_stale_state(ursim: Ursim) -> None:
    r = make_robot(ursim)
    r.open()
    ursim.control.drop_connection(3.0)
    wait_for(lambda: not r._rcv.isConnected(), what="link down")
    r.close()  # must not run stopScript against stale state (the library would wait up to 300 s)
    assert r._ctrl is None
