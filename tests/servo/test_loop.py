"""The servo loop's period, stepped in-process on a manual clock against an in-memory robot: the
stop is issued once per request and retried every period until delivered (each request's failure
reported once), tracking follows the
extrapolated setpoint within the limits, a stale setpoint brings the arm to rest and holds it, and a
step the merged check refuses never reaches the driver (the arm is stopped instead). A MOVE
streams its straight line from the actual pose within the robot's limits and holds the target."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from drivers.interfaces.robot import MotionLimits, RobotMode, RobotState, SafetyStatus
from hil.clock import ManualClock
from hil.geometry.transform import RigidTransform
from hil.servo.limiter import RateLimiter
from hil.servo.link import Regions
from hil.servo.loop import (
    EV_FOLLOWING,
    EV_MOVE_DONE,
    EV_MOVE_STARTED,
    EV_REFUSED,
    EV_STALE,
    EV_STOP_DELIVERED,
    EV_STOP_FAILED,
    ServoLoop,
)
from hil.servo.shm import LATENCY_BIN_NS, RingRecord, ServoMode, SetpointBlock, ShmRegion, Stat
from tests.controller.fakes import DroppingRobot

PERIOD_S = 0.008
LIMITS = MotionLimits(max_speed_mm_s=100.0, max_accel_mm_s2=500.0, max_angular_speed_rad_s=1.0)


@pytest.fixture
def rig() -> Any:
    clock = ManualClock(10**9)
    robot = DroppingRobot(clock, LIMITS)
    robot.open()
    regions = Regions.create(shared=False)
    events: list[tuple[str, dict[str, Any]]] = []
    loop = ServoLoop(robot, LIMITS, clock, regions.block, regions.ring, regions.stats, period_s=PERIOD_S,
                     limiter=RateLimiter(60.0, 400.0, 0.5), report=lambda k, f: events.append((k, f)))
    yield clock, robot, regions, loop, events
    regions.close()
    robot.close()


def _run(clock: ManualClock, loop: ServoLoop, n: int) -> None:
    for _ in range(n):
        loop.step(clock.now_ns())
        clock.advance(PERIOD_S)


def _track(block: SetpointBlock, clock: ManualClock, t_mm: Any, v_mm_s: Any = (0.0, 0.0, 0.0), *,
           track_id: int = 1, valid_s: float = 1.0, max_horizon_s: float = 5.0) -> None:
    now = clock.now_ns()
    block.write_track(track_id=track_id, R=np.eye(3), t_mm=np.asarray(t_mm, float),
                      v_mm_s=np.asarray(v_mm_s, float), w_rad_s=np.zeros(3), t_ref_ns=now,
                      valid_until_ns=now + round(valid_s * 1e9), exposure_t_ns=now - 30_000_000, frame_seq=1,
                      speed_scale=1.0, max_horizon_s=max_horizon_s, lead_s=0.0)


def test_idle_reads_the_robot_every_period_and_commands_nothing(rig: Any) -> None:
    clock, robot, regions, loop, _ = rig
    _run(clock, loop, 5)
    assert robot.calls == []
    assert regions.ring.head == 5
    assert regions.stats.get(Stat.PERIODS) == 5
    assert regions.stats.get(Stat.INTERVALS) == 4
    assert regions.stats.get(Stat.LATE) == 0


def test_a_stop_is_issued_once_per_request(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    sid = regions.block.write_mode(ServoMode.STOP)
    _run(clock, loop, 4)
    assert robot.calls == [("stop", None)]
    assert regions.stats.get(Stat.STOP_ACK_ID) == sid
    sid2 = regions.block.write_mode(ServoMode.STOP)
    _run(clock, loop, 3)
    assert robot.calls == [("stop", None), ("stop", None)]
    assert regions.stats.get(Stat.STOP_ACK_ID) == sid2
    assert [k for k, _ in events] == [EV_STOP_DELIVERED, EV_STOP_DELIVERED]


def test_an_undelivered_stop_is_retried_every_period_until_delivered(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    robot.down = True
    sid = regions.block.write_mode(ServoMode.STOP)
    _run(clock, loop, 5)
    assert robot.calls == []
    assert regions.stats.get(Stat.COMMAND_ERRORS) == 5          # one attempt per period
    assert regions.stats.get(Stat.STOP_ACK_ID) == 0
    assert regions.ring.head == 5                               # the arm is read every period
    robot.down = False
    _run(clock, loop, 3)
    assert robot.calls == [("stop", None)]
    assert regions.stats.get(Stat.STOP_ACK_ID) == sid
    assert [k for k, _ in events] == [EV_STOP_FAILED, EV_STOP_DELIVERED]   # the failure reported once


def test_each_stop_request_learns_its_own_failure(rig: Any) -> None:
    """The supervisor re-requests an undelivered stop once per tick: every request is told why it
    failed (a failure reported once per streak left the retried request waiting for an ack)."""
    clock, robot, regions, loop, events = rig
    robot.down = True
    sid = regions.block.write_mode(ServoMode.STOP)
    _run(clock, loop, 3)
    sid2 = regions.block.write_mode(ServoMode.STOP)
    _run(clock, loop, 3)
    assert [(k, f["stop_id"], f["error"]) for k, f in events] == [
        (EV_STOP_FAILED, sid, "DisconnectedError"), (EV_STOP_FAILED, sid2, "DisconnectedError")]
    assert regions.stats.get(Stat.COMMAND_ERRORS) == 6


def test_extrapolation_stops_at_the_horizon_cap(rig: Any) -> None:
    clock, robot, regions, loop, _ = rig
    start = robot.pose.t.copy()
    _track(regions.block, clock, start, v_mm_s=(10.0, 0.0, 0.0), max_horizon_s=0.1)
    _run(clock, loop, 250)
    last = [T for kind, T in robot.calls if kind == "servo"][-1]
    assert last.t[0] == pytest.approx(start[0] + 1.0, abs=1e-9)   # 10 mm/s x 0.1 s, then held


def test_tracking_follows_the_extrapolated_setpoint_within_the_limits(rig: Any) -> None:
    clock, robot, regions, loop, _ = rig
    start = robot.pose.t.copy()
    _track(regions.block, clock, start, v_mm_s=(10.0, 0.0, 0.0), valid_s=10.0)
    _run(clock, loop, 250)   # 2 s
    servo = [T for kind, T in robot.calls if kind == "servo"]
    assert len(servo) == 250
    # the target moves at 10 mm/s from the setpoint's time: after 2 s the arm follows it (rate
    # limited from rest, so it lags by less than a few periods' travel)
    expected_x = start[0] + 10.0 * (clock.now_ns() - PERIOD_S * 1e9 - 10**9) * 1e-9
    assert servo[-1].t[0] == pytest.approx(expected_x, abs=0.2)
    steps = np.diff(np.array([T.t for T in servo]), axis=0) / PERIOD_S
    assert float(np.linalg.norm(steps, axis=1).max()) <= 60.0 + 1e-6   # the tracking speed limit
    assert regions.stats.get(Stat.REFUSALS) == 0
    assert regions.stats.get(Stat.LATENCY_SAMPLES) == 1   # one setpoint: its first command measured


def test_the_command_time_is_when_the_driver_took_the_command(
        rig: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """The latency (exposure -> command) and the ring's command time stop when the driver has taken
    the command: the following supervision that comes after it is not part of them."""
    clock, robot, regions, loop, _ = rig
    sent = robot.servo

    def servo_taking_1_ms(T: RigidTransform, period_s: float) -> None:
        sent(T, period_s)
        clock.advance(0.001)

    def update_taking_3_ms(*args: Any) -> Any:
        clock.advance(0.003)
        return None

    monkeypatch.setattr(robot, "servo", servo_taking_1_ms)
    monkeypatch.setattr(loop.following, "update", update_taking_3_ms)
    _track(regions.block, clock, robot.pose.t.copy(), valid_s=10.0)   # exposed 30 ms before now
    t_step = clock.now_ns()
    loop.step(t_step)
    rec = regions.ring.read_latest(RingRecord())
    assert rec is not None
    assert rec.cmd_t_ns == t_step + 1_000_000
    assert int(np.flatnonzero(regions.stats.latency_hist)[0]) == 31_000_000 // LATENCY_BIN_NS   # 31 ms
    assert regions.stats.get(Stat.LATENCY_SAMPLES) == 1


def test_a_write_in_progress_never_holds_the_period(rig: Any) -> None:
    clock, robot, regions, loop, _ = rig
    _track(regions.block, clock, (1.0, 0.0, 0.0))
    _run(clock, loop, 3)
    servos = sum(1 for kind, _ in robot.calls if kind == "servo")
    regions.block._begin()                       # the supervisor preempted half-way through a write
    _run(clock, loop, 4)                         # each read gives up after READ_MAX_WAIT_NS
    assert regions.stats.get(Stat.SETPOINT_BUSY) == 4
    assert sum(1 for kind, _ in robot.calls if kind == "servo") == servos + 4   # on the last copy
    regions.block._end()
    _run(clock, loop, 1)
    assert regions.stats.get(Stat.SETPOINT_BUSY) == 4


def test_a_stale_setpoint_brings_the_arm_to_rest_and_holds(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    _track(regions.block, clock, robot.pose.t, v_mm_s=(40.0, 0.0, 0.0), valid_s=0.5)
    _run(clock, loop, 125)   # 1 s: stale after 0.5 s
    servo = np.array([T.t for kind, T in robot.calls if kind == "servo"])
    speed = np.linalg.norm(np.diff(servo, axis=0), axis=1) / PERIOD_S
    stale_from = round(0.5 / PERIOD_S)
    # at rest within max_speed / max_accel (40 / 400 = 0.1 s) of going stale, then held
    assert float(speed[stale_from + 13:].max()) == pytest.approx(0.0, abs=1e-9)
    assert float(speed[stale_from - 5]) == pytest.approx(40.0, abs=0.5)
    assert regions.stats.get(Stat.STALE) > 0
    assert [k for k, _ in events].count(EV_STALE) == 1


def test_hold_brings_the_tracking_command_to_rest_and_keeps_commanding_it(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    _track(regions.block, clock, robot.pose.t, v_mm_s=(40.0, 0.0, 0.0), valid_s=10.0)
    _run(clock, loop, 50)   # 0.4 s: at 40 mm/s
    regions.block.write_hold(1)   # the same session (LOCK after COMPENSATE)
    _run(clock, loop, 75)   # 0.6 s
    servo = np.array([T.t for kind, T in robot.calls if kind == "servo"])
    assert len(servo) == 125   # commanded every period, holding included
    speed = np.linalg.norm(np.diff(servo, axis=0), axis=1) / PERIOD_S
    assert float(speed[45]) == pytest.approx(40.0, abs=0.5)
    # continuous: no restart from the actual pose; at rest within 40 / 400 = 0.1 s, then held
    # where it stopped (the stopping distance v^2 / 2a = 2 mm past the hold order, never back)
    assert float(speed[49:].max()) <= 40.0 + 1e-6
    assert float(speed[50 + 13:].max()) == pytest.approx(0.0, abs=1e-9)
    assert float(np.diff(servo[49:, 0]).min()) >= -1e-9
    assert servo[-1][0] - servo[49][0] == pytest.approx(2.0, abs=0.4)
    assert regions.stats.get(Stat.LATENCY_SAMPLES) == 1   # holding is not a camera setpoint
    assert regions.stats.get(Stat.REFUSALS) == 0
    assert EV_STALE not in [k for k, _ in events]


def test_hold_without_a_session_starts_one_at_the_actual_pose(rig: Any) -> None:
    clock, robot, regions, loop, _ = rig
    start = robot.pose.t.copy()
    regions.block.write_hold(7)
    _run(clock, loop, 5)
    servo = [T for kind, T in robot.calls if kind == "servo"]
    assert len(servo) == 5
    assert all(np.allclose(T.t, start) for T in servo)


def test_a_step_outside_the_workspace_is_refused_and_the_arm_stopped(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    far = robot.pose.t + np.array([0.0, 0.0, 10_000.0])   # far outside the box: the limiter heads there
    _track(regions.block, clock, far, valid_s=10.0)
    _run(clock, loop, 800)   # 300 mm to the box's top at 60 mm/s: 5 s
    servo = [T for kind, T in robot.calls if kind == "servo"]
    assert all(float(T.t[2]) <= LIMITS.workspace_max_mm[2] for T in servo)
    assert ("stop", None) in robot.calls
    refused = [f for k, f in events if k == EV_REFUSED]
    assert refused
    assert refused[0]["check"] == "workspace"


def test_a_non_finite_setpoint_is_refused_never_sent(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    _track(regions.block, clock, (np.nan, 0.0, 300.0))
    _run(clock, loop, 3)
    assert [kind for kind, _ in robot.calls if kind == "servo"] == []
    assert next(f["check"] for k, f in events if k == EV_REFUSED) == "setpoint"


def test_a_new_track_id_restarts_from_the_actual_pose_at_rest(rig: Any) -> None:
    clock, robot, regions, loop, _ = rig
    _track(regions.block, clock, robot.pose.t + np.array([20.0, 0.0, 0.0]))
    _run(clock, loop, 10)
    regions.block.write_mode(ServoMode.IDLE)
    robot.move_linear(RigidTransform.from_translation((5.0, 5.0, 250.0)), 50.0, 200.0)   # moved meanwhile
    _track(regions.block, clock, robot.pose.t, track_id=2)
    _run(clock, loop, 1)
    last = [T for kind, T in robot.calls if kind == "servo"][-1]
    assert np.allclose(last.t, (5.0, 5.0, 250.0))


def test_an_arm_that_stops_following_is_stopped_and_the_session_ends(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    start = robot.pose.t.copy()
    _track(regions.block, clock, start, v_mm_s=(10.0, 0.0, 0.0), valid_s=10.0)   # a target moving at 10 mm/s
    _run(clock, loop, 25)
    assert not [k for k, _ in events if k == EV_FOLLOWING]   # follows (the fake robot has no lag)
    robot.stall = True
    _run(clock, loop, 100)
    fe = [f for k, f in events if k == EV_FOLLOWING]
    assert len(fe) == 1
    assert fe[0]["error_mm"] > fe[0]["bound_mm"] == 2.0
    assert fe[0]["duration_ms"] == pytest.approx(104.0)   # the first period >= 100 ms (8 ms periods)
    assert "arm not following its servo targets" in str(fe[0]["message"])
    assert regions.stats.get(Stat.FOLLOWING_FAULTS) == 1
    assert regions.stats.get(Stat.FOLLOWING_PEAK_UM) > 2000
    k_stop = max(i for i, (kind, _) in enumerate(robot.calls) if kind == "stop")
    assert [kind for kind, _ in robot.calls[k_stop:]] == ["stop"]   # nothing sent after the stop
    robot.stall = False
    _track(regions.block, clock, robot.pose.t, track_id=2)   # the supervisor starts a new session
    _run(clock, loop, 3)
    assert [kind for kind, _ in robot.calls[k_stop + 1:]] == ["servo"] * 3


def test_a_refusal_is_reported_before_the_stop_that_may_block(rig: Any) -> None:
    # a stop can block for as long as a controller does not answer (an RTDE stream that paused):
    # the supervisor, in its own process, must have the refusal before that
    clock, robot, regions, loop, events = rig
    seen_at_stop: list[list[str]] = []
    stop = robot.stop

    def stop_noting_the_events() -> None:
        seen_at_stop.append([k for k, _ in events])
        stop()

    robot.stop = stop_noting_the_events
    _track(regions.block, clock, (np.nan, 0.0, 300.0), valid_s=10.0)
    _run(clock, loop, 1)
    assert seen_at_stop == [[EV_REFUSED]]


def test_a_refused_session_is_never_resumed_by_the_loop(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    _track(regions.block, clock, (np.nan, 0.0, 300.0), valid_s=10.0)
    _run(clock, loop, 1)
    now = clock.now_ns()   # the same session's next setpoint is fine, but the session was refused
    regions.block.write_track(track_id=1, R=np.eye(3), t_mm=robot.pose.t, v_mm_s=np.zeros(3),
                              w_rad_s=np.zeros(3), t_ref_ns=now, valid_until_ns=now + 10**9,
                              exposure_t_ns=now, frame_seq=2, speed_scale=1.0, max_horizon_s=1.0, lead_s=0.0)
    _run(clock, loop, 5)
    assert [kind for kind, _ in robot.calls] == ["stop"]
    assert [k for k, _ in events if k == EV_REFUSED] == [EV_REFUSED]


def test_region_layouts_refuse_a_short_buffer() -> None:
    with pytest.raises(ValueError, match="words"):
        SetpointBlock(ShmRegion.local(4))


def test_a_move_streams_the_straight_line_from_the_actual_pose_and_holds_the_target(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    start = robot.pose.t.copy()
    target = start + np.array([30.0, -40.0, 0.0])   # 50 mm at 50 mm/s, 200 mm/s^2: 1.25 s
    regions.block.write_move(track_id=3, R=robot.pose.R, t_mm=target, speed_mm_s=50.0, accel_mm_s2=200.0)
    _run(clock, loop, 200)   # 1.6 s
    servo = np.array([T.t for kind, T in robot.calls if kind == "servo"])
    assert len(servo) == 200
    assert np.allclose(servo[-1], target, atol=1e-9)
    assert np.allclose(servo[-20:], target, atol=1e-9)   # the target is held after the profile
    u = (target - start) / 50.0
    assert np.allclose(start + np.outer((servo - start) @ u, u), servo, atol=1e-9)   # on the line
    speeds = np.linalg.norm(np.diff(servo, axis=0), axis=1) / PERIOD_S
    assert speeds.max() == pytest.approx(50.0, rel=1e-9)
    started = [f for k, f in events if k == EV_MOVE_STARTED]
    assert len(started) == 1
    assert started[0]["move_id"] == 3
    assert started[0]["duration_s"] == pytest.approx(1.25)
    assert started[0]["distance_mm"] == pytest.approx(50.0)
    assert [f["move_id"] for k, f in events if k == EV_MOVE_DONE] == [3]
    assert regions.stats.get(Stat.MOVE_DONE_ID) == 3
    assert regions.stats.get(Stat.REFUSALS) == 0
    assert regions.stats.get(Stat.LATENCY_SAMPLES) == 0   # a move has no camera latency


def test_a_move_faster_than_the_robot_limits_is_capped_to_them(rig: Any) -> None:
    clock, robot, regions, loop, _ = rig
    target = robot.pose.t + np.array([0.0, 0.0, -200.0])
    regions.block.write_move(track_id=1, R=robot.pose.R, t_mm=target, speed_mm_s=500.0, accel_mm_s2=5000.0)
    _run(clock, loop, 400)
    servo = np.array([T.t for kind, T in robot.calls if kind == "servo"])
    speeds = np.linalg.norm(np.diff(servo, axis=0), axis=1) / PERIOD_S
    assert speeds.max() == pytest.approx(LIMITS.max_speed_mm_s, rel=1e-9)
    assert regions.stats.get(Stat.REFUSALS) == 0


def test_a_move_out_of_the_workspace_is_refused_where_it_leaves_it(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    far = robot.pose.t + np.array([0.0, 0.0, 10_000.0])
    regions.block.write_move(track_id=1, R=robot.pose.R, t_mm=far, speed_mm_s=100.0, accel_mm_s2=500.0)
    _run(clock, loop, 2000)
    servo = [T for kind, T in robot.calls if kind == "servo"]
    assert servo
    assert all(float(T.t[2]) <= LIMITS.workspace_max_mm[2] for T in servo)
    assert robot.calls[-1] == ("stop", None)
    assert [f["check"] for k, f in events if k == EV_REFUSED] == ["workspace"]


def test_a_stop_during_a_move_stops_the_arm_on_the_next_period(rig: Any) -> None:
    clock, robot, regions, loop, _ = rig
    regions.block.write_move(track_id=1, R=robot.pose.R, t_mm=robot.pose.t + np.array([100.0, 0.0, 0.0]),
                             speed_mm_s=50.0, accel_mm_s2=200.0)
    _run(clock, loop, 50)
    regions.block.write_mode(ServoMode.STOP)
    _run(clock, loop, 5)
    k_stop = max(i for i, (kind, _) in enumerate(robot.calls) if kind == "stop")
    assert k_stop == 50
    assert len(robot.calls) == 51


def test_a_hold_in_the_moves_session_comes_to_rest_from_the_moving_command(rig: Any) -> None:
    clock, robot, regions, loop, _events = rig
    start = robot.pose.t.copy()
    regions.block.write_move(track_id=4, R=robot.pose.R, t_mm=start + np.array([100.0, 0.0, 0.0]),
                             speed_mm_s=50.0, accel_mm_s2=200.0)
    _run(clock, loop, 100)   # cruising at 50 mm/s
    regions.block.write_hold(4)
    _run(clock, loop, 100)
    servo = np.array([T.t for kind, T in robot.calls if kind == "servo"])
    speeds = np.linalg.norm(np.diff(servo, axis=0), axis=1) / PERIOD_S
    assert speeds[98] == pytest.approx(50.0)
    assert np.all(np.abs(np.diff(speeds)) / PERIOD_S <= 400.0 * 1.001)   # the limiter's deceleration
    assert speeds[-10:].max() == 0.0
    assert servo[-1][0] < start[0] + 100.0
    assert regions.stats.get(Stat.REFUSALS) == 0


def test_a_moves_following_is_supervised_from_its_first_period(rig: Any) -> None:
    clock, robot, regions, loop, events = rig
    robot.stall = True   # the arm does not move at all
    regions.block.write_move(track_id=1, R=robot.pose.R, t_mm=robot.pose.t + np.array([50.0, 0.0, 0.0]),
                             speed_mm_s=50.0, accel_mm_s2=200.0)   # a 1.25 s profile
    _run(clock, loop, 40)   # 0.32 s: still accelerating
    fe = [f for k, f in events if k == EV_FOLLOWING]
    assert len(fe) == 1
    # the fake arm has no lag: the expectation is the previous command, 0.5 * 200 mm/s^2 * t^2 at
    # t = 8 ms * (k - 1) for the command of period k (1, 2, ...); beyond 2 mm from period 19 (the
    # command of period 18 at 0.144 s, 2.07 mm), so the fault comes 13 periods (104 ms) later
    assert fe[0]["duration_ms"] == pytest.approx(104.0)
    assert fe[0]["error_mm"] == pytest.approx(0.5 * 200.0 * (31 * PERIOD_S) ** 2, abs=5e-4)   # (rounded)
    assert [kind for kind, _ in robot.calls].count("servo") == 32
    assert robot.calls[-1] == ("stop", None)


class _LateReportingRobot(DroppingRobot):
    """Follows every servo target at once but reports the pose of ``delay_ns`` ago, stamped with
    when it was sampled (``stamps``) or not (as a driver that cannot tell)."""

    def __init__(self, clock: ManualClock, limits: MotionLimits, delay_ns: int, stamps: bool) -> None:
        super().__init__(clock, limits)
        self.delay_ns, self.stamps = delay_ns, stamps
        self.history: list[tuple[int, RigidTransform]] = [(0, self.pose)]

    def _servo(self, T: RigidTransform, period_s: float) -> None:
        super()._servo(T, period_s)
        self.history.append((self.clock.now_ns(), T))

    def _state_now(self) -> RobotState:
        now = self.clock.now_ns()
        sampled = now - self.delay_ns
        pose = next((T for t, T in reversed(self.history) if t < sampled), None)   # read before servo
        assert pose is not None
        return RobotState(pose, np.zeros(6), RobotMode.IDLE,
                          SafetyStatus.NORMAL, now, sample_t_ns=sampled if self.stamps else None)


@pytest.mark.parametrize("stamps", [True, False])
def test_a_late_report_is_judged_at_its_sample_time(stamps: bool) -> None:
    """A healthy arm whose reports are 64 ms old (8 periods) while it moves at 50 mm/s: 3.2 mm
    behind the expectation *now*, exactly on it at the time the pose was sampled. Judged at the
    sample time it never faults; a driver that cannot stamp its reports leaves it to the bound."""
    clock = ManualClock(10**9)
    robot = _LateReportingRobot(clock, LIMITS, delay_ns=64_000_000, stamps=stamps)
    robot.open()
    regions = Regions.create(shared=False)
    events: list[tuple[str, dict[str, Any]]] = []
    try:
        loop = ServoLoop(robot, LIMITS, clock, regions.block, regions.ring, regions.stats, period_s=PERIOD_S,
                         limiter=RateLimiter(60.0, 400.0, 0.5), report=lambda k, f: events.append((k, f)))
        regions.block.write_move(track_id=1, R=robot.pose.R, t_mm=robot.pose.t + np.array([100.0, 0.0, 0.0]),
                                 speed_mm_s=50.0, accel_mm_s2=500.0)   # 2.1 s, at 50 mm/s from 0.1 s
        _run(clock, loop, 300)
        following = [f for k, f in events if k == EV_FOLLOWING]
        if stamps:
            assert following == []
            assert regions.stats.get(Stat.FOLLOWING_PEAK_UM) == 0
            assert [k for k, _ in events] == [EV_MOVE_STARTED, EV_MOVE_DONE]
        else:
            assert len(following) == 1
            assert following[0]["error_mm"] == pytest.approx(50.0 * 0.064, abs=1e-6)   # cruising
    finally:
        regions.close()
        robot.close()
