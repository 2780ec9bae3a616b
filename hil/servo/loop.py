"""One period of the servo loop: the only code that commands the arm at its control rate.

:meth:`ServoLoop.step` (called every period by :mod:`hil.servo.process` in its own real-time
process, or stepped in-process by a simulated run on the manual clock — the same code):

1. read the robot state (a read error is counted and reported once per run of errors);
2. read the setpoint block (:class:`~hil.servo.shm.SetpointBlock`, a seqlock: never blocks);
3. by mode:
   - STOP: ``robot.stop()`` once per stop request, retried every period until delivered; the
     state is still read every period;
   - TRACK: extrapolate the setpoint pose along its velocity to the command time (the horizon is
     the measured latency since the pair's exposure plus the arm's actuation lag, capped at
     ``max_horizon_s``); a setpoint past ``valid_until_ns`` is *stale*: the target becomes the
     last command, so the rate limiter brings the arm to rest at its acceleration limit (bounded:
     ``max_speed / max_accel``) and holds it there; rate- and acceleration-limit; the merged step
     check (:mod:`hil.safety.servo_check`); ``robot.servo``; the following-error supervision
     (:mod:`hil.safety.following`) compares the arm's reported pose with the pose the commands
     should have brought it to. A refused step or an arm that does not follow stops the arm and is
     reported, and that tracking session is over: the loop holds until the supervisor starts a
     new one (a new ``track_id``) — it never resumes on its own after a refusal;
   - HOLD: as TRACK with the last command as the target: the arm comes to rest at the
     acceleration limit and is held there, commanded, checked and supervised every period (LOCK).
     Holding continues the tracking session (no restart from the actual pose); a HOLD with no
     session under way starts one from the actual pose, at rest;
   - MOVE (APPROACH, RETRACT): a straight-line move from the actual pose at rest to the setpoint
     pose (:class:`~hil.servo.trajectory.LinearMove`, a trapezoidal profile in the move's speed
     and acceleration, each capped by the robot's limits), one profile sample per period, then
     the target held; each sample goes through the same step check, command and following
     supervision as TRACK, from the move's first period (the reported pose is compared with the
     expectation at the time the arm sampled it, so its age does not read as a lag at approach
     speeds: :mod:`hil.safety.following`). A new move (a new ``track_id``) restarts from the
     actual pose;
   - IDLE: no command (the arm holds);
4. write the period's record to the state ring and the counters (:class:`~hil.servo.shm.LoopStats`).

Events (refusals, delivered stops, the first of a run of errors, a move's start and the end of
its profile) go to ``report(kind, fields)``:
rare, so they may allocate; the hot path otherwise builds only the transforms of the limiter.

Frames: poses are ``T_robot_from_tcp`` (mm, robot base frame); the setpoint velocity is the TCP's
linear velocity (mm/s) and angular velocity (rad/s), both in the robot base frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.interfaces.errors import DriverError
from drivers.interfaces.robot import MotionLimits, Robot, RobotMode, RobotState, SafetyStatus
from hil.clock import Clock
from hil.errors import GeometryError
from hil.geometry.transform import RigidTransform, rotvec_to_matrix
from hil.safety.following import FollowingMonitor
from hil.safety.servo_check import servo_step_violation
from hil.servo.limiter import RateLimiter
from hil.servo.shm import LoopStats, RingRecord, ServoMode, Setpoint, SetpointBlock, Stat, StateRing
from hil.servo.trajectory import LinearMove
from hil.servo.wire import error_to_wire

#: Enum <-> code tables for the ring (declaration order).
SAFETY_CODES: tuple[SafetyStatus, ...] = tuple(SafetyStatus)
MODE_CODES: tuple[RobotMode, ...] = tuple(RobotMode)
_SAFETY_INDEX = {s: k for k, s in enumerate(SAFETY_CODES)}
_MODE_INDEX = {m: k for k, m in enumerate(MODE_CODES)}

#: kind, fields -> None (session log records in the supervisor)
Report = Callable[[str, dict[str, Any]], None]

# event kinds the loop reports
EV_REFUSED = "servo_refused"
EV_STOP_DELIVERED = "servo_stop_delivered"
EV_STOP_FAILED = "servo_stop_failed"
EV_READ_FAILED = "servo_state_read_failed"
EV_COMMAND_FAILED = "servo_command_failed"
EV_STALE = "servo_setpoint_stale"
EV_FOLLOWING = "servo_following_error"
EV_MOVE_STARTED = "servo_move_started"
EV_MOVE_DONE = "servo_move_profile_done"


def record_to_state(rec: RingRecord) -> RobotState:
    """The :class:`RobotState` a ring record holds."""
    T = RigidTransform(rec.pose[:9].reshape(3, 3).copy(), rec.pose[9:].copy())
    return RobotState(T, rec.q_rad.copy(), MODE_CODES[rec.mode_code], SAFETY_CODES[rec.safety_code],
                      rec.t_ns, rec.tcp_speed_mm_s)


class ServoLoop:
    """The servo loop's period (module doc).

    Args:
        robot: the ACTIVE robot this loop owns (no one else commands it while the loop runs).
        limits: the safety layer's limits (the merged check; their following-error overrides
            applied to the robot's :attr:`~drivers.interfaces.robot.Robot.following_model`).
        clock: the controller clock (``now_ns`` of the command and the delivered stop).
        block, ring, stats: the shared regions (:mod:`hil.servo.shm`).
        period_s: the robot's control period (1 / control rate).
        limiter: the rate limiter's limits (the procedure's compensation speed, acceleration).
        report: receives the loop's events (module doc).
    """

    def __init__(self, robot: Robot, limits: MotionLimits, clock: Clock, block: SetpointBlock,
                 ring: StateRing, stats: LoopStats, *, period_s: float, limiter: RateLimiter,
                 report: Report) -> None:
        if not period_s > 0:
            raise ValueError(f"servo period must be > 0 s, got {period_s}")
        self.robot, self.limits, self.clock = robot, limits, clock
        self.block, self.ring, self.stats = block, ring, stats
        self.period_s = period_s
        self.period_ns = round(period_s * 1e9)
        self.limiter = limiter
        self.report = report
        self._sp = Setpoint()
        self._track_id: int | None = None
        self._halted_track_id: int | None = None   # a session ended by a refusal: never resumed
        self.following = FollowingMonitor(limits.following(robot.following_model))
        self._v_prev = np.zeros(3)
        self._stop_done_id = 0
        self._stop_failed_id = 0     # the newest stop request whose failure was reported
        self._last_step_ns: int | None = None
        self._period = 0
        self._latency_seq = -1       # the setpoint whose first command's latency was measured
        self._read_failing = False
        self._cmd_failing = False
        self._stale = False
        self._last_state: RobotState | None = None
        self._pose_buf = np.zeros(12)
        self._zero6 = np.zeros(6)
        self._trajectory: LinearMove | None = None
        self._move_periods = 0

    # ------------------------------------------------------------------ the period
    def step(self, now_ns: int) -> None:
        """One period at ``now_ns`` (controller clock). Never raises for a device error (they are
        counted and reported); a programming error propagates (the host stops the arm)."""
        c = self.stats.c
        c[Stat.PERIODS] += 1
        if self._last_step_ns is not None:
            self.stats.add_interval(now_ns - self._last_step_ns, self.period_ns)
        self._last_step_ns = now_ns
        c[Stat.LAST_PERIOD_T_NS] = now_ns
        st = self._read_state()
        sp = self._sp
        if self.block.read(sp) is None:   # a write in progress throughout: the last copy
            c[Stat.SETPOINT_BUSY] += 1
        cmd_t_ns = 0
        if sp.mode == ServoMode.STOP:
            self._track_id = None
            self._do_stop(sp.stop_id)
        elif sp.mode == ServoMode.TRACK or sp.mode == ServoMode.HOLD or sp.mode == ServoMode.MOVE:
            if st is not None and st.safety is SafetyStatus.NORMAL and sp.track_id != self._halted_track_id:
                if sp.mode == ServoMode.MOVE:
                    cmd_t_ns = self._move(sp, st, now_ns)
                else:
                    cmd_t_ns = self._track(sp, st, now_ns, hold=sp.mode == ServoMode.HOLD)
            else:
                self.following.stop()
        else:
            self._track_id = None
            self.following.stop()
        self._publish(st, cmd_t_ns, int(sp.mode))
        self._period += 1

    def _read_state(self) -> RobotState | None:
        try:
            st = self.robot.state_now()
        except DriverError as exc:
            self.stats.c[Stat.READ_ERRORS] += 1
            if not self._read_failing:
                self._read_failing = True
                self.report(EV_READ_FAILED, {"error": type(exc).__name__, "detail": str(exc),
                                             "wire": error_to_wire(exc)})
            return None
        self._read_failing = False
        self._last_state = st
        return st

    def _do_stop(self, stop_id: int) -> None:
        if stop_id == self._stop_done_id:
            return
        c = self.stats.c
        if c[Stat.STOP_ISSUE_ID] != stop_id:
            c[Stat.STOP_ISSUE_T_NS] = self.clock.now_ns()
            c[Stat.STOP_ISSUE_ID] = stop_id
        try:
            self.robot.stop()
        except DriverError as exc:
            self.stats.c[Stat.COMMAND_ERRORS] += 1
            if self._stop_failed_id != stop_id:
                # once per stop request: each waiting stop learns why, at once (a failure
                # reported only once per streak left a retried request waiting for an ack
                # that never came - and an in-process loop is not stepped while it waits)
                self._stop_failed_id = stop_id
                self.report(EV_STOP_FAILED, {"stop_id": stop_id, "error": type(exc).__name__,
                                             "detail": str(exc), "wire": error_to_wire(exc)})
            return   # retried next period
        self._cmd_failing = False
        t = self.clock.now_ns()
        c[Stat.STOPS_SENT] += 1
        c[Stat.STOP_ACK_T_NS] = t
        c[Stat.STOP_ACK_ID] = stop_id
        self._stop_done_id = stop_id
        self.report(EV_STOP_DELIVERED, {"stop_id": stop_id, "issued_ns": int(c[Stat.STOP_ISSUE_T_NS]),
                                        "delivered_ns": t})

    def _track(self, sp: Setpoint, st: RobotState, now_ns: int, hold: bool) -> int:
        if sp.track_id != self._track_id:   # a new tracking session: from the actual pose, at rest
            self._track_id = sp.track_id
            self.limiter.reset(st.T_robot_from_tcp)
            self._v_prev[:] = 0.0
            self._stale = False
            self.following.start(st.T_robot_from_tcp.R, st.T_robot_from_tcp.t)
        prev = self.limiter.command
        assert prev is not None
        if hold:
            desired = prev   # come to rest at the acceleration limit and hold there
        elif now_ns > sp.valid_until_ns:
            self.stats.c[Stat.STALE] += 1
            if not self._stale:
                self._stale = True
                self.report(EV_STALE, {"frame_seq": sp.frame_seq,
                                       "age_ms": (now_ns - sp.t_ref_ns) * 1e-6})
            desired = prev   # come to rest at the acceleration limit and hold there
        else:
            self._stale = False
            try:
                desired = self._extrapolate(sp, now_ns)
            except GeometryError as exc:   # a non-finite or improper setpoint: never moved on
                self._refuse(sp, ("setpoint", str(exc)))
                return 0
        cmd = self.limiter.step(desired, self.period_s, sp.speed_scale)
        sent_ns = self._send(sp, st, prev, cmd, now_ns)
        if sent_ns is None:
            return 0
        v = self.limiter.velocity_mm_s
        if v is not None:
            self._v_prev[:] = v
        self.stats.c[Stat.COMMANDS] += 1
        if sp.seq != self._latency_seq and not self._stale and not hold:
            self._latency_seq = sp.seq
            self.stats.add_latency(sent_ns - sp.exposure_t_ns)
        return sent_ns

    def _move(self, sp: Setpoint, st: RobotState, now_ns: int) -> int:
        """One period of a MOVE (:mod:`hil.servo.trajectory`): the profile's pose at this period,
        checked, sent and supervised like a tracking command (module doc); the rate limiter
        follows the profile, so a HOLD in the same session comes to rest from where the move is.
        A command the driver could not send ends the move: the next period starts it again from
        the actual pose, at rest."""
        if sp.track_id != self._track_id and not self._start_move(sp, st):   # a new move
            return 0
        move = self._trajectory
        assert move is not None
        prev = self.limiter.command
        assert prev is not None
        self._move_periods += 1
        t_s = self._move_periods * self.period_s
        cmd, v_mm_s, w_rad_s = move.pose_at(t_s)
        done = move.done(t_s)
        sent_ns = self._send(sp, st, prev, cmd, now_ns)
        if sent_ns is None:
            return 0
        self.limiter.command = cmd
        self.limiter.velocity_mm_s = v_mm_s
        self.limiter.angular_velocity_rad_s = w_rad_s
        self._v_prev[:] = (cmd.t - prev.t) / self.period_s   # what the step check compares with
        c = self.stats.c
        if done and c[Stat.MOVE_DONE_ID] != sp.track_id:
            c[Stat.MOVE_DONE_ID] = sp.track_id
            self.report(EV_MOVE_DONE, {"move_id": sp.track_id, "duration_s": round(move.duration_s, 4)})
        c[Stat.COMMANDS] += 1
        return sent_ns

    def _start_move(self, sp: Setpoint, st: RobotState) -> bool:
        """A new move ``sp`` from the actual pose at rest (False: its target was refused)."""
        start = st.T_robot_from_tcp
        self._track_id = sp.track_id
        self._stale = False
        try:
            target = RigidTransform(sp.R.copy(), sp.t_mm.copy())
            self._trajectory = LinearMove(
                start, target, speed_mm_s=min(sp.move_speed_mm_s, self.limits.max_speed_mm_s),
                accel_mm_s2=min(sp.move_accel_mm_s2, self.limits.max_accel_mm_s2),
                angular_speed_rad_s=min(self.limiter.max_angular_speed_rad_s,
                                        self.limits.max_angular_speed_rad_s),
                angular_accel_rad_s2=self.limiter.max_angular_accel_rad_s2)
        except GeometryError as exc:   # a non-finite or improper target: never moved on
            self._refuse(sp, ("setpoint", str(exc)))
            return False
        self._move_periods = 0
        self.limiter.reset(start)
        self._v_prev[:] = 0.0
        self.following.start(start.R, start.t)   # from the actual pose, at rest
        self.report(EV_MOVE_STARTED, {"move_id": sp.track_id, "from_mm": start.t.round(3).tolist(),
                                      "to_mm": target.t.round(3).tolist(),
                                      "distance_mm": round(self._trajectory.distance_mm, 3),
                                      "angle_deg": round(math.degrees(self._trajectory.angle_rad), 3),
                                      "duration_s": round(self._trajectory.duration_s, 4)})
        return True

    def _send(self, sp: Setpoint, st: RobotState, prev: RigidTransform, cmd: RigidTransform,
              now_ns: int) -> int | None:
        """The merged step check, the servo command and the following supervision of one
        period's command ``cmd`` after ``prev``. Returns the clock time the driver took the
        command (the command time of the loop's latency and of the ring), or None when it was
        refused, failed or the arm does not follow (reported; a refusal or following fault ended
        the session and stopped the arm)."""
        why = servo_step_violation(self.limits, prev.R, prev.t, self._v_prev, cmd.R, cmd.t, self.period_s)
        if why is not None:
            self._refuse(sp, why)
            return None
        try:
            self.robot.servo(cmd, self.period_s)
        except DriverError as exc:
            self.stats.c[Stat.COMMAND_ERRORS] += 1
            if not self._cmd_failing:
                self._cmd_failing = True
                self.report(EV_COMMAND_FAILED, {"error": type(exc).__name__, "detail": str(exc),
                                                "wire": error_to_wire(exc)})
            self._track_id = None   # restart from the actual pose once it works again
            self.following.stop()
            return None
        sent_ns = self.clock.now_ns()
        self._cmd_failing = False
        T_act = st.T_robot_from_tcp
        fault = self.following.update(now_ns, cmd.R, cmd.t, T_act.R, T_act.t, st.sample_t_ns)
        if fault is not None:
            self.stats.c[Stat.FOLLOWING_FAULTS] += 1
            self.report(EV_FOLLOWING, {"message": fault.message(), "frame_seq": sp.frame_seq,
                                       **fault.fields()})
            self._halt(sp)   # after the report: the stop can block (see _refuse)
            return None
        self._note_peak()
        return sent_ns

    def _extrapolate(self, sp: Setpoint, now_ns: int) -> RigidTransform:
        h = (now_ns - sp.t_ref_ns) * 1e-9 + sp.lead_s
        h = min(max(h, 0.0), sp.max_horizon_s)
        t = sp.t_mm + sp.v_mm_s * h
        w = sp.w_rad_s
        if float(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) > 0.0:
            R = rotvec_to_matrix(w * h) @ sp.R
        else:
            R = sp.R.copy()
        return RigidTransform(R, t)

    def _refuse(self, sp: Setpoint, why: tuple[str, str]) -> None:
        self.stats.c[Stat.REFUSALS] += 1
        # reported before the stop: a stop can block on a controller that stopped answering, and
        # the supervisor (in its own process) must learn of the refusal at once
        self.report(EV_REFUSED, {"check": why[0], "detail": why[1], "frame_seq": sp.frame_seq})
        self._halt(sp)

    def _halt(self, sp: Setpoint) -> None:
        """End the tracking session ``sp`` belongs to for good and stop the arm."""
        self._track_id = None
        self._halted_track_id = sp.track_id
        self.following.stop()
        try:
            self.robot.stop()
        except DriverError:
            self.stats.c[Stat.COMMAND_ERRORS] += 1

    def _note_peak(self) -> None:
        """The largest following error since the counters were reset, in µm (the loop's figures)."""
        c = self.stats.c
        peak_um = int(self.following.last_error_mm * 1000.0)
        if peak_um > c[Stat.FOLLOWING_PEAK_UM]:
            c[Stat.FOLLOWING_PEAK_UM] = peak_um

    def _publish(self, st: RobotState | None, cmd_t_ns: int, servo_mode: int) -> None:
        st = st if st is not None else self._last_state
        if st is None:
            return
        buf = self._pose_buf
        T = st.T_robot_from_tcp
        buf[:9] = T.R.reshape(9)
        buf[9:] = T.t
        self.ring.write(t_ns=st.t_ns, cmd_t_ns=cmd_t_ns, safety_code=_SAFETY_INDEX[st.safety],
                        mode_code=_MODE_INDEX[st.mode], period=self._period, servo_mode=servo_mode,
                        pose=buf, q_rad=st.q_rad if st.q_rad.shape == (6,) else self._zero6,
                        tcp_speed_mm_s=st.tcp_speed_mm_s if math.isfinite(st.tcp_speed_mm_s) else 0.0)
