"""Fault handling of the controller (campaign findings), on in-memory devices and a ManualClock.

- a stop that could not be delivered (connection down) is re-sent every tick until delivered;
- reset / start after a protective stop try ``robot.recover()``; START is refused while the
  robot is still stopped;
- the servo stream keeps absolute deadlines (no drift from the work done per command);
- the watchdogs are armed on a fresh frame (start-up does not judge a stale first frame).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.interfaces.camera import Frame, StereoFrame
from drivers.interfaces.errors import DisconnectedError, SafetyStopError
from drivers.interfaces.robot import MotionLimits, Robot, RobotMode, RobotState, SafetyStatus
from hil.clock import Clock, ManualClock
from hil.controller.config import ProcedureConfig
from hil.controller.controller import Controller
from hil.controller.deadline import DeadlineTimer
from hil.controller.fsm import Event, State
from hil.controller.operator_input import OperatorView
from hil.controller.plan_file import load_plan
from hil.controller.planning import RigGeometry
from hil.geometry.transform import RigidTransform
from hil.session import SessionLog, read_session_log

from .fakes import FakeRobot, StubCamera

PLAN = load_plan("configs/plans/sim_plan.json")
RIG = RigGeometry(RigidTransform.identity(), np.zeros((3, 3)), RigidTransform.identity())
FRAME_S = 1 / 30


class FakeCamera(StubCamera):
    """30 Hz pairs exposed ``age_s`` before the grab; a grab takes a frame period of clock time
    (the first one ``first_render_s`` when given)."""

    def __init__(self, clock: ManualClock, first_render_s: float = 0.0, age_s: float = 0.02) -> None:
        super().__init__(frame_rate_hz=30.0, image_size=(8, 8))
        self.clock = clock
        self.first_render_s = first_render_s
        self.age_ns = round(age_s * 1e9)
        self.seq = 0

    def grab(self, timeout_s: float) -> StereoFrame:
        t_exp = self.clock.now_ns() - self.age_ns
        if self.seq == 0 and self.first_render_s > 0:
            self.clock.sleep(self.first_render_s)  # a slow first render (caches, JIT, buffers)
        else:
            self.clock.sleep(FRAME_S)
        self.seq += 1
        img = np.zeros((8, 8), np.uint8)
        return StereoFrame(Frame(img, t_exp, self.seq), Frame(img, t_exp, self.seq))


class FlakyRobot(FakeRobot):
    """A fake robot whose link can drop (every call raises DisconnectedError; ``recover`` brings it
    back when ``reconnects``), that can be in a protective stop which ``recover`` clears only when
    ``clearable``, and whose program can be stopped (``program_running``; mode STOPPED, as a UR
    reports a stopped script or any safety stop) until ``recover`` restarts it."""

    def __init__(self, clock: ManualClock) -> None:
        super().__init__(clock, MotionLimits())
        self.connected = True
        self.reconnects = False
        self.clearable = True
        self.program_running = True
        self.recover_calls = 0

    def _link(self) -> None:
        if not self.connected:
            raise DisconnectedError(self.name, "RTDE connection lost (test)")

    def _stop(self, decel_mm_s2: float) -> None:
        self._link()
        super()._stop(decel_mm_s2)

    def _state_now(self) -> RobotState:
        self._link()
        st = super()._state_now()
        if self.program_running and st.safety is SafetyStatus.NORMAL:
            return st
        return RobotState(st.T_robot_from_tcp, st.q_rad, RobotMode.STOPPED, st.safety, st.t_ns)

    def recover(self) -> None:
        self.recover_calls += 1
        if self.reconnects:
            self.connected = True
        self._link()
        if not self.clearable:
            raise SafetyStopError(self.name, "protective stop cannot be cleared yet")
        self.safety_status = SafetyStatus.NORMAL
        self.program_running = True


class Scripted:
    """Sends the events of ``script`` (one per tick, None = nothing) and then nothing."""

    def __init__(self, script: list[Event | None]) -> None:
        self.script = list(script)

    def poll(self, view: OperatorView) -> Event | None:
        return self.script.pop(0) if self.script else None

    def finished(self, view: OperatorView) -> bool:
        return not self.script


def _controller(tmp_path: Path, clock: ManualClock, robot: FakeRobot, operator: Scripted,
                camera: FakeCamera | None = None) -> tuple[Controller, SessionLog]:
    cam = camera or FakeCamera(clock)
    cam.open()
    robot.open()
    log = SessionLog(tmp_path / "s.jsonl", clock)
    ctl = Controller(camera=cam, robot=robot, tracker=None, clock=clock,
                     locate=lambda f: np.zeros((0, 3)), plan=PLAN, rig=RIG, procedure=ProcedureConfig(),
                     limits=MotionLimits(), watchdog_ages_s={"camera": 0.25, "robot": 0.05},
                     session=log, operator=operator)
    return ctl, log


def _events(log: SessionLog) -> list[dict[str, object]]:
    log.close()
    return list(read_session_log(log.path))


# ---------------------------------------------------------------------- stop re-sent until delivered
def test_a_stop_lost_to_a_disconnect_is_resent_every_tick_until_delivered(tmp_path: Path) -> None:
    clock = ManualClock(10**9)
    robot = FlakyRobot(clock)
    ctl, log = _controller(tmp_path, clock, robot, Scripted([]))
    ctl.tick()
    robot.connected = False
    ctl.tick()  # the state read fails: FAULT, and the stop on entry cannot be delivered
    assert ctl.state is State.FAULT
    assert ("stop", None) not in robot.calls
    for _ in range(3):
        ctl.tick()  # still down: one attempt per tick, none delivered
    assert ("stop", None) not in robot.calls
    robot.connected = True
    ctl.tick()
    assert robot.calls.count(("stop", None)) == 1
    ctl.tick()
    ctl.tick()
    assert robot.calls.count(("stop", None)) == 1  # delivered once: not repeated
    ev = _events(log)
    failed = [r for r in ev if r["event"] == "stop_failed"]
    assert len(failed) == 4  # on entry + 3 ticks while down
    delivered = [r for r in ev if r["event"] == "stop_delivered"]
    assert len(delivered) == 1
    assert delivered[0]["attempts"] == 5
    assert delivered[0]["reason"] == "fault: robot: RTDE connection lost (test)"


def test_a_new_state_entry_cancels_a_pending_stop_retry(tmp_path: Path) -> None:
    """Once the state moved on (its entry action commands the robot itself), an old stop is not
    re-sent on top of the new command."""
    clock = ManualClock(10**9)
    robot = FlakyRobot(clock)
    ctl, log = _controller(tmp_path, clock, robot, Scripted([]))
    ctl.tick()
    robot.connected = False
    ctl.tick()
    assert ctl.state is State.FAULT
    robot.connected = True
    ctl.fire(Event.RESET_REQUESTED, "operator")  # IDLE's entry stop is delivered now
    assert ctl.state is State.IDLE
    assert robot.calls.count(("stop", None)) == 1
    ctl.tick()
    assert robot.calls.count(("stop", None)) == 1
    log.close()


# ---------------------------------------------------------------------- protective stop and start/reset
def test_reset_after_a_protective_stop_recovers_the_robot_and_start_proceeds(tmp_path: Path) -> None:
    clock = ManualClock(10**9)
    robot = FlakyRobot(clock)
    robot.safety_status = SafetyStatus.PROTECTIVE_STOP
    ctl, log = _controller(tmp_path, clock, robot,
                           Scripted([None, Event.RESET_REQUESTED, None, Event.START_REQUESTED, None]))
    ctl.tick()
    assert ctl.state is State.FAULT
    assert ctl.faults == ["robot: protective_stop"]
    ctl.tick()  # reset: recover() is tried, the robot leaves the protective stop
    assert robot.recover_calls == 1
    assert ctl.state is State.IDLE
    ctl.tick()
    assert ctl.state is State.IDLE  # no new fault in IDLE
    ctl.tick()
    assert ctl.state is State.REGISTER
    assert ctl.faults == ["robot: protective_stop"]
    ev = _events(log)
    rec = [r for r in ev if r["event"] == "robot_recover_attempted"]
    assert len(rec) == 1
    assert rec[0]["ok"] is True
    assert rec[0]["input"] == "reset_requested"


def test_start_is_refused_while_the_robot_stays_in_protective_stop(tmp_path: Path) -> None:
    clock = ManualClock(10**9)
    robot = FlakyRobot(clock)
    robot.safety_status = SafetyStatus.PROTECTIVE_STOP
    robot.clearable = False
    ctl, log = _controller(tmp_path, clock, robot, Scripted([Event.START_REQUESTED]))
    ctl.tick()
    assert robot.recover_calls == 1
    assert ctl.state is not State.REGISTER
    assert "register" not in [r["state"] for r in ctl.timeline]
    ev = _events(log)
    refused = [r for r in ev if r["event"] == "start_refused"]
    assert len(refused) == 1
    assert refused[0]["reason"] == ("robot still protective_stop / stopped after recover(): "
                                    "robot: protective stop cannot be cleared yet")


def test_start_after_a_stopped_program_restarts_it(tmp_path: Path) -> None:
    # an e-stop released, or the script stopped by its watchdog: safety normal, program stopped
    clock = ManualClock(10**9)
    robot = FlakyRobot(clock)
    robot.program_running = False
    ctl, log = _controller(tmp_path, clock, robot, Scripted([Event.START_REQUESTED]))
    ctl.tick()
    assert robot.recover_calls == 1
    assert ctl.state is State.REGISTER
    rec = [r for r in _events(log) if r["event"] == "robot_recover_attempted"]
    assert [(r["ok"], r["mode"], r["safety"]) for r in rec] == [(True, "idle", "normal")]


def test_reset_and_start_after_a_dropped_link_reconnect_first(tmp_path: Path) -> None:
    clock = ManualClock(10**9)
    robot = FlakyRobot(clock)
    ctl, log = _controller(tmp_path, clock, robot,
                           Scripted([None, None, Event.RESET_REQUESTED, Event.START_REQUESTED]))
    ctl.tick()
    robot.connected = False
    ctl.tick()
    assert ctl.state is State.FAULT
    robot.reconnects = True  # the network is back: recover() rebuilds the link
    ctl.tick()
    assert (ctl.state, robot.recover_calls) == (State.IDLE, 1)
    ctl.tick()
    assert ctl.state is State.REGISTER
    rec = [r for r in _events(log) if r["event"] == "robot_recover_attempted"]
    assert [(r["input"], r["ok"]) for r in rec] == [("reset_requested", True)]
    assert "RTDE connection lost (test)" in str(rec[0]["state_error"])


def test_start_is_refused_while_the_link_stays_down(tmp_path: Path) -> None:
    clock = ManualClock(10**9)
    robot = FlakyRobot(clock)
    robot.connected = False
    ctl, log = _controller(tmp_path, clock, robot, Scripted([Event.START_REQUESTED]))
    ctl.tick()
    assert robot.recover_calls == 1
    assert ctl.state is not State.REGISTER
    refused = [r for r in _events(log) if r["event"] == "start_refused"]
    assert refused[0]["reason"] == ("robot state unavailable after recover(): "
                                    "robot: RTDE connection lost (test)")


def test_start_with_a_normal_robot_does_not_call_recover(tmp_path: Path) -> None:
    clock = ManualClock(10**9)
    robot = FlakyRobot(clock)
    ctl, log = _controller(tmp_path, clock, robot, Scripted([Event.START_REQUESTED]))
    ctl.tick()
    assert robot.recover_calls == 0
    assert ctl.state is State.REGISTER
    log.close()


# ---------------------------------------------------------------------- absolute deadlines
def test_deadlines_are_absolute_whatever_the_work_takes() -> None:
    clock = ManualClock(0)
    timer = DeadlineTimer(clock, 0.008)
    timer.start(clock.now_ns())
    sent: list[int] = []
    for _ in range(10):
        clock.advance(0.003)  # the work of one command
        timer.wait()
        sent.append(clock.now_ns())
    assert np.diff(sent).tolist() == [8_000_000] * 9
    assert sent[0] == 8_000_000
    assert timer.missed == 0


def test_a_late_deadline_skips_ahead_and_is_counted() -> None:
    clock = ManualClock(0)
    timer = DeadlineTimer(clock, 0.008)
    timer.start(0)
    clock.advance(0.0205)  # 12.5 ms past the first deadline (8 ms): more than a period late
    timer.wait()
    assert clock.now_ns() == 20_500_000  # no sleep: sent at once
    assert timer.missed == 1
    assert timer.deadline_ns == 16_000_000  # the grid is kept: the missed slot is skipped
    clock.advance(0.001)
    timer.wait()
    assert clock.now_ns() == 24_000_000
    assert timer.missed == 1
    clock.advance(0.010)  # late by less than a period: no skip, sent at once, not missed
    timer.wait()
    assert clock.now_ns() == 34_000_000
    assert timer.deadline_ns == 32_000_000
    assert timer.missed == 1


def test_deadline_timer_rejects_a_bad_period() -> None:
    with pytest.raises(ValueError, match="period"):
        DeadlineTimer(ManualClock(0), 0.0)


# ---------------------------------------------------------------------- start-up
def test_a_slow_first_frame_does_not_trip_the_camera_watchdog(tmp_path: Path) -> None:
    """The first grab takes 1.5 s (a camera's first buffer, a simulator's first render): the
    pipeline is primed before the watchdogs are armed, so no frame judged is stale."""
    clock = ManualClock(10**9)
    robot = FlakyRobot(clock)
    cam = FakeCamera(clock, first_render_s=1.5)
    ctl, log = _controller(tmp_path, clock, robot, Scripted([None] * 5), camera=cam)
    ctl.run(10.0)
    assert ctl.faults == []
    assert ctl.state is State.IDLE
    ev = _events(log)
    primed = [r for r in ev if r["event"] == "pipeline_primed"]
    assert len(primed) == 1
    assert primed[0]["first_frame_age_s"] == pytest.approx(1.52)


def test_a_loop_driving_tick_itself_is_primed_too(tmp_path: Path) -> None:
    """A caller that arms the watchdogs and ticks without run() (the console) gets the same start."""
    clock = ManualClock(10**9)
    cam = FakeCamera(clock, first_render_s=1.5)
    ctl, log = _controller(tmp_path, clock, FlakyRobot(clock), Scripted([]), camera=cam)
    ctl.watchdogs.arm(clock.now_ns())
    for _ in range(3):
        ctl.tick()
    assert ctl.faults == []
    assert cam.seq == 4  # one pair consumed by priming, then one per tick
    assert [r["event"] for r in _events(log)].count("pipeline_primed") == 1


def test_every_frame_after_priming_is_judged_by_the_watchdog(tmp_path: Path) -> None:
    """No frame is exempt: a camera whose pairs are always 0.4 s old faults on the first tick."""
    clock = ManualClock(10**9)
    robot = FlakyRobot(clock)
    cam = FakeCamera(clock, age_s=0.4)
    ctl, log = _controller(tmp_path, clock, robot, Scripted([None]), camera=cam)  # one tick
    ctl.run(10.0)
    assert ctl.state is State.FAULT
    assert ctl.frames == 1
    assert ctl.faults[0].startswith("watchdog: camera data 0.4")
    log.close()


# ---------------------------------------------------------------------- the servo stream, end to end
class SlowServo(Robot):
    """Forwards everything to the robot the setup built; each servo command then costs ``work_s``
    of clock time (inverse kinematics, I/O) -- what stretched the old stream's period."""

    def __init__(self, inner: Robot, clock: Clock, work_s: float) -> None:
        super().__init__(inner.name, inner.limits, T_flange_from_tcp=inner.T_flange_from_tcp)
        self.inner, self.clock, self.work_s = inner, clock, work_s
        self.servo_t_ns: list[int] = []

    def _open(self) -> None:
        self.inner.open()

    def _close(self) -> None:
        self.inner.close()

    @property
    def control_rate_hz(self) -> float:
        return self.inner.control_rate_hz

    def _move_linear(self, T: RigidTransform, speed_mm_s: float, accel_mm_s2: float, blocking: bool) -> None:
        self.inner.move_linear(T, speed_mm_s, accel_mm_s2, blocking=blocking)

    def _servo(self, T: RigidTransform, period_s: float) -> None:
        self.servo_t_ns.append(self.clock.now_ns())
        self.inner.servo(T, period_s)
        self.clock.sleep(self.work_s)

    def _stop(self, decel_mm_s2: float) -> None:
        self.inner.stop(decel_mm_s2)

    def _state_now(self) -> RobotState:
        return self.inner.state_now()

    def recover(self) -> None:
        self.inner.recover()


@pytest.mark.slow
def test_the_servo_stream_keeps_the_robot_rate_when_each_command_takes_time(tmp_path: Path) -> None:
    """Through ``run_procedure(robot_wrapper=...)``: 3 ms of work per servo command must not
    stretch the 8 ms period (the old stream slept 8 ms after the work: 11 ms, ~91 Hz)."""
    from hil.cli.cmd_run import run_procedure
    from hil.config import load_setup

    clock = ManualClock(10**9)
    wrapped: list[SlowServo] = []

    def slow(robot: Robot) -> Robot:
        wrapped.append(SlowServo(robot, clock, 0.003))
        return wrapped[0]

    setup = load_setup("configs/sim.toml")
    s = run_procedure(Path("configs/sim.toml"), setup, PLAN, auto=True, session_dir=tmp_path,
                      max_duration_s=20.0, clock=clock, robot_wrapper=slow)
    assert s.final_state == "done"
    iv_ns = np.diff(wrapped[0].servo_t_ns)
    on_period = int(np.sum(iv_ns == 8_000_000))
    other = iv_ns[iv_ns != 8_000_000]  # from the last command of a frame's stream to the next frame's
    # 30 Hz frames, 125 Hz stream: a frame's command and 3 more 8 ms apart, then the frame gap
    assert on_period >= 30
    assert on_period >= 3 * int(np.sum(other < 100_000_000))
    assert np.all(other > 8_000_000)


# ---------------------------------------------------------------------- a stopped robot program
class ProgramStopsInCompensate(SlowServo):
    """Forwards to the setup's robot; after ``after`` servo commands the arm's program stops
    (safety still normal, mode STOPPED), as a UR script does when its RTDE watchdog expires."""

    def __init__(self, inner: Robot, clock: Clock, after: int) -> None:
        super().__init__(inner, clock, 0.0)
        self.after = after
        self.servo_after_stop = 0

    def _servo(self, T: RigidTransform, period_s: float) -> None:
        if len(self.servo_t_ns) >= self.after:
            self.servo_after_stop += 1
        super()._servo(T, period_s)

    def _state_now(self) -> RobotState:
        st = self.inner.state_now()
        if len(self.servo_t_ns) >= self.after:
            return RobotState(st.T_robot_from_tcp, st.q_rad, RobotMode.STOPPED, st.safety, st.t_ns, 0.0)
        return st


@pytest.mark.slow
def test_a_robot_program_that_stops_while_commanded_is_a_fault(tmp_path: Path) -> None:
    """Safety normal but the program not running: the controller must fault at once instead of
    waiting on an arm that can no longer execute anything (found by the transport campaign)."""
    from hil.cli.cmd_run import run_procedure
    from hil.config import load_setup

    clock = ManualClock(10**9)
    wrapped: list[ProgramStopsInCompensate] = []

    def stops(robot: Robot) -> Robot:
        wrapped.append(ProgramStopsInCompensate(robot, clock, after=20))
        return wrapped[0]

    setup = load_setup("configs/sim.toml")
    s = run_procedure(Path("configs/sim.toml"), setup, PLAN, auto=True, session_dir=tmp_path,
                      max_duration_s=30.0, clock=clock, robot_wrapper=stops)
    assert s.final_state == "fault"
    assert any("not running" in f and "mode stopped" in f for f in s.faults), s.faults
    assert wrapped[0].servo_after_stop == 0  # the Robot base class refuses motion to a stopped program
