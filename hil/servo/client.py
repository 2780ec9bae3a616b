"""The supervisor's robot: a :class:`~drivers.interfaces.robot.Robot` whose every command goes to
the servo loop that owns the arm (:mod:`hil.servo.link`).

- :meth:`ServoRobot.track` publishes a tracking setpoint (pose at the pair's exposure, its
  velocity, validity); the loop extrapolates, limits, checks and commands it every period.
- ``stop`` writes STOP to the setpoint block and returns once the loop delivered it (the loop
  retries every period; :data:`STOP_ACK_TIMEOUT_S` bounds the wait, then DeviceTimeoutError).
- ``move_linear`` writes a MOVE setpoint: the loop streams the straight-line move every period
  (:mod:`hil.servo.trajectory`); ``recover`` goes over the command channel.
- ``servo`` (a single target, for callers outside the procedure's tracking) publishes a
  zero-velocity setpoint valid for two periods.
- ``state_now`` is the loop's newest ring record (process link; never blocks) or the robot's own
  state (in-process link). The loop's events are drained here: a refused step raises
  SafetyViolationError naming the check, an arm that does not follow its targets raises
  SafetyViolationError ``following_error`` stating the figures, a failed stop, command or read
  raises the driver's own error, and a servo process that is gone raises DisconnectedError, so
  the controller faults on them at its next read.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError, DriverError, LifecycleError
from drivers.interfaces.lifecycle import DeviceState
from drivers.interfaces.robot import FollowingModel, MotionLimits, Robot, RobotState
from hil.clock import Clock
from hil.geometry.transform import RigidTransform
from hil.safety.layer import SafetyViolationError
from hil.servo.limiter import RateLimiter
from hil.servo.link import InProcessLink, ServoLink
from hil.servo.loop import (
    EV_COMMAND_FAILED,
    EV_FOLLOWING,
    EV_READ_FAILED,
    EV_REFUSED,
    EV_STOP_FAILED,
    record_to_state,
)
from hil.servo.process import ServoProcess
from hil.servo.rt import RtGranted
from hil.servo.shm import RingRecord, ServoMode, Stat
from hil.servo.wire import error_from_wire

#: session-log event: the servo process had ended on its own and recover() started a new one
EV_PROCESS_RESTARTED = "servo_process_restarted"

#: How long ``stop`` waits for the loop to deliver the stop, s (a UR's servoStop / stopL returns
#: once the arm is at rest: a fraction of a second from following speed).
STOP_ACK_TIMEOUT_S = 2.0

class ServoRobot(Robot):
    """The robot as the supervisor sees it (module doc).

    Args:
        link: the loop (in-process or the servo process), started.
        limits: the robot's limits (the base class checks them before anything goes to the loop).
        on_event: receives every loop event (the session log).
    """

    def __init__(self, link: ServoLink, limits: MotionLimits,
                 on_event: Callable[[str, dict[str, Any]], None] | None = None) -> None:
        super().__init__(link.robot_name, limits, T_flange_from_tcp=link.T_flange_from_tcp)
        self.link = link
        self.on_event = on_event
        self._rec = RingRecord()
        self._track_id = 0
        self._last_move_id = 0
        self._tracking = False
        self._pending: DriverError | SafetyViolationError | None = None
        self._stop_error: tuple[int, DriverError] | None = None   # (stop request, why it failed)
        self.stop_latency_ns: list[int] = []
        #: what the OS granted the servo process (None: in-process loop, or not started)
        self.rt: RtGranted | None = None

    # ------------------------------------------------------------------ lifecycle
    @property
    def state(self) -> DeviceState:
        """In-process: the inner robot's lifecycle (its owner opens and closes it); servo process:
        this device's own (``open`` starts the process, ``close`` stops the arm and ends it)."""
        if isinstance(self.link, InProcessLink):
            return self.link.robot.state
        return self._state

    def require_active(self, operation: str) -> None:
        state = self.state
        if state is not DeviceState.ACTIVE:
            raise LifecycleError(self.name, f"{operation}() needs state active, is {state}")

    def _open(self) -> None:
        if isinstance(self.link, ServoProcess):
            self.link.start()
            self.rt = self.link.ready.rt if self.link.ready is not None else None

    def _close(self) -> None:
        if isinstance(self.link, ServoProcess):
            self.link.close()

    @property
    def control_rate_hz(self) -> float:
        return self.link.control_rate_hz

    @property
    def following_model(self) -> FollowingModel:
        """The bounds the loop supervises with (the robot's model, [safety] overrides applied)."""
        return self.link.following_model

    @property
    def T_flange_from_tcp(self) -> RigidTransform:
        """The TCP in the flange frame, mm (the owned robot's)."""
        return self.link.T_flange_from_tcp

    # ------------------------------------------------------------------ tracking
    def start_tracking(self) -> int:
        """A new tracking session (the loop restarts from the actual pose, at rest); its id."""
        self._track_id += 1
        self._tracking = True
        return self._track_id

    def _session_for(self, what: str) -> int:
        """The tracking session a setpoint belongs to (one starts when none is under way).
        Raises LifecycleError (not active) or DisconnectedError (the loop is gone)."""
        self.require_active(what)
        self._raise_if_gone()
        if not self._tracking:
            self.start_tracking()
        return self._track_id

    def track(self, T_robot_from_tcp: RigidTransform, v_mm_s: np.ndarray[Any, Any],
              w_rad_s: np.ndarray[Any, Any], *, t_ref_ns: int, valid_until_ns: int, exposure_t_ns: int,
              frame_seq: int, speed_scale: float, max_horizon_s: float, lead_s: float) -> None:
        """Publish a tracking setpoint (never blocks). See :class:`hil.servo.shm.Setpoint`.

        Raises:
            LifecycleError: not active.  DisconnectedError: the loop is gone.
        """
        self.link.regions.block.write_track(
            track_id=self._session_for("track"), R=T_robot_from_tcp.R, t_mm=T_robot_from_tcp.t, v_mm_s=v_mm_s,
            w_rad_s=w_rad_s, t_ref_ns=t_ref_ns, valid_until_ns=valid_until_ns, exposure_t_ns=exposure_t_ns,
            frame_seq=frame_seq, speed_scale=speed_scale, max_horizon_s=max_horizon_s, lead_s=lead_s)

    def hold(self) -> None:
        """Hold (never blocks): the loop brings the arm to rest from its current command at the
        acceleration limit and keeps commanding that pose every period, checked and supervised,
        in the same tracking session (a later :meth:`track` continues it). With no session under
        way, one starts from the actual pose.

        Raises:
            LifecycleError: not active.  DisconnectedError: the loop is gone.
        """
        self.link.regions.block.write_hold(self._session_for("hold"))
        # the in-process loop is stepped by the holding phase on the period grid (no kick here)

    def idle(self) -> None:
        """Leave TRACK / STOP: the loop sends nothing (the arm holds)."""
        self._tracking = False
        self.link.regions.block.write_mode(ServoMode.IDLE)

    # ------------------------------------------------------------------ Robot driver API
    def _move_linear(self, T_robot_from_tcp: RigidTransform, speed_mm_s: float, accel_mm_s2: float,
                     blocking: bool) -> None:
        """A straight-line MOVE streamed by the loop (:mod:`hil.servo.trajectory`), in a session
        of its own (a later :meth:`track` or :meth:`hold` starts another, from the actual pose).
        Blocking: returns once the arm is at rest within 0.5 mm of the target (the in-process
        loop is stepped on its clock meanwhile); DeviceTimeoutError after the profile's time
        x 1.5 + 5 s; the loop's refusal or a following fault raises SafetyViolationError."""
        start = self._state_now().T_robot_from_tcp
        self._track_id += 1
        move_id = self._last_move_id = self._track_id
        self._tracking = False
        self.link.regions.block.write_move(track_id=move_id, R=T_robot_from_tcp.R, t_mm=T_robot_from_tcp.t,
                                           speed_mm_s=speed_mm_s, accel_mm_s2=accel_mm_s2)
        if not blocking:
            return
        dist_mm = float(np.linalg.norm(T_robot_from_tcp.t - start.t))
        budget_s = 1.5 * (dist_mm / speed_mm_s + speed_mm_s / accel_mm_s2) + 5.0
        waited_s = 0.0
        while True:
            waited_s += self.link.wait_period()
            st = self._state_now()
            if (self.move_profile_done() and st.tcp_speed_mm_s < 0.5
                    and float(np.linalg.norm(st.T_robot_from_tcp.t - T_robot_from_tcp.t)) < 0.5):
                return
            if waited_s > budget_s:
                where = np.round(T_robot_from_tcp.t, 1).tolist()
                raise DeviceTimeoutError(self.name,
                                         f"move to {where} mm did not finish within {budget_s:.1f} s")

    def move_profile_done(self) -> bool:
        """Whether the loop has streamed the whole profile of the last :meth:`move_linear` (the
        target is now commanded and held; the arm settles through its servo lag). True before
        any move. Never blocks."""
        return self.link.regions.stats.get(Stat.MOVE_DONE_ID) >= self._last_move_id

    def _servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None:
        now = time.monotonic_ns() if not self.link.in_process else self._state_now().t_ns
        zero = np.zeros(3)
        self.track(T_robot_from_tcp, zero, zero, t_ref_ns=now, valid_until_ns=now + round(2 * period_s * 1e9),
                   exposure_t_ns=now, frame_seq=0, speed_scale=1.0, max_horizon_s=0.0, lead_s=0.0)
        if self.link.in_process:
            self.link.kick()

    def _stop(self, decel_mm_s2: float) -> None:
        self._raise_if_gone()
        self._tracking = False
        t0 = time.monotonic_ns()
        stop_id = self.link.regions.block.write_mode(ServoMode.STOP)
        self.link.kick()
        stats = self.link.regions.stats
        deadline = time.monotonic() + STOP_ACK_TIMEOUT_S
        while stats.get(Stat.STOP_ACK_ID) < stop_id:
            self._drain_events()
            if self._stop_error is not None and self._stop_error[0] == stop_id:
                err, self._stop_error = self._stop_error[1], None
                raise err
            if time.monotonic() > deadline:
                raise DeviceTimeoutError(self.name, f"servo loop did not deliver the stop within "
                                                    f"{STOP_ACK_TIMEOUT_S} s (it retries every period)")
            self._raise_if_gone()
            time.sleep(0.0002)
        self._stop_error = None
        if not self.link.in_process and stats.get(Stat.STOP_ISSUE_ID) == stop_id:
            self.stop_latency_ns.append(stats.get(Stat.STOP_ISSUE_T_NS) - t0)

    def _state_now(self) -> RobotState:
        self._raise_if_gone()
        self._drain_events()
        if self._pending is not None:
            err, self._pending = self._pending, None
            raise err
        if self.link.in_process:
            st: RobotState = self.link.request("state")
            return st
        rec = self.link.regions.ring.read_latest(self._rec)
        if rec is None:
            raise DeviceTimeoutError(self.name, "servo loop has not read the robot yet")
        return record_to_state(rec)

    def recover(self) -> None:
        """Recover the arm through the loop (the driver's own recover: reconnect, restart its
        program, release a protective stop). A servo process that ended on its own (a crash of the
        robot library, as ur-rtde's reconnect can on a dropped link) is started again instead:
        the robot is opened anew there, which is that recovery; the session log gets
        ``servo_process_restarted`` with the reason and the new pid.

        Raises:
            LifecycleError: not active, or the servo process was closed.
            DriverError: the driver's (a link still down, a stop that cannot be released), from
                the restarted process too (a later recover tries again).
        """
        if isinstance(self.link, ServoProcess) and self.state is DeviceState.ACTIVE:
            why = self.link.gone()
            if why is not None and not self.link.closed:
                self._restart_process(why)
                return
        self._raise_if_gone()
        self.idle()
        self._pending = None
        self.link.request("recover", timeout_s=30.0)

    def _restart_process(self, why: str) -> None:
        assert isinstance(self.link, ServoProcess)
        self._pending, self._stop_error = None, None
        self._tracking = False
        ready = self.link.restart()
        self.rt = ready.rt
        if self.on_event is not None:
            self.on_event(EV_PROCESS_RESTARTED, {"reason": why, "pid": ready.pid})

    def state_view(self) -> Robot:
        """A read-only robot for observers (a simulated world following the arm): its
        ``state_now`` reads the loop's newest record and never takes the loop's events (those are
        the controller's to raise); its commands raise LifecycleError."""
        return _StateView(self)

    # ------------------------------------------------------------------ events
    def _drain_events(self) -> None:
        """Hand the loop's events to ``on_event``; keep the error to raise at the next read (a
        refused step, a failed command or read) or in the waiting ``stop``."""
        for kind, fields in self.link.take_events():
            if self.on_event is not None:
                self.on_event(kind, fields)
            if kind == EV_REFUSED:
                self._pending = SafetyViolationError(str(fields.get("check")),
                                                     f"servo loop: {fields.get('detail')}")
            elif kind == EV_FOLLOWING:
                self._pending = SafetyViolationError("following_error",
                                                     f"servo loop: {fields.get('message')}")
            elif kind == EV_STOP_FAILED:   # raised by the waiting stop (the supervisor retries it)
                self._stop_error = (int(fields["stop_id"]), error_from_wire(*fields["wire"]))
            elif kind == EV_COMMAND_FAILED:
                # a servo command the driver refused or could not send: the controller faults at
                # its next read, in-process as in the servo process (never retried silently)
                self._pending = error_from_wire(*fields["wire"])
            elif kind == EV_READ_FAILED and not self.link.in_process:
                # (in-process, the controller's own state read raises the same error itself)
                self._pending = error_from_wire(*fields["wire"])

    def _raise_if_gone(self) -> None:
        why = self.link.gone()
        if why is not None:
            if self.state.value != "active":
                raise LifecycleError(self.name, why)
            raise DisconnectedError(self.name, why)


def in_process_servo(robot: Robot, limits: MotionLimits, limiter: RateLimiter, clock: Clock,
                     on_event: Callable[[str, dict[str, Any]], None] | None = None) -> ServoRobot:
    """``robot`` (opened and closed by its owner) behind a servo loop stepped in this process."""
    return ServoRobot(InProcessLink(robot, limits, clock, limiter), robot.limits, on_event)


def servo_event_logger(session: Any) -> Callable[[str, dict[str, Any]], None]:
    """Loop events -> session log records (the event kind is the record's name; the wire form of
    an error is left out: ``error`` and ``detail`` say it)."""
    def log(kind: str, fields: dict[str, Any]) -> None:
        session.write(kind, **{k: v for k, v in fields.items() if k != "wire"})
    return log


class _StateView(Robot):
    """See :meth:`ServoRobot.state_view`."""

    def __init__(self, owner: ServoRobot) -> None:
        super().__init__(owner.name, owner.limits, T_flange_from_tcp=owner.T_flange_from_tcp)
        self.owner = owner
        self._rec = RingRecord()

    @property
    def state(self) -> DeviceState:
        return self.owner.state

    def require_active(self, operation: str) -> None:
        self.owner.require_active(operation)

    @property
    def T_flange_from_tcp(self) -> RigidTransform:
        return self.owner.T_flange_from_tcp

    @property
    def control_rate_hz(self) -> float:
        return self.owner.control_rate_hz

    def _open(self) -> None:
        raise LifecycleError(self.name, "a state view is opened with its robot")

    def _close(self) -> None:
        """Nothing: the view ends with its robot."""

    def _state_now(self) -> RobotState:
        link = self.owner.link
        if link.in_process:
            st: RobotState = link.request("state")
            return st
        why = link.gone()
        if why is not None:
            raise DisconnectedError(self.name, why)
        rec = link.regions.ring.read_latest(self._rec)
        if rec is None:
            raise DeviceTimeoutError(self.name, "servo loop has not read the robot yet")
        return record_to_state(rec)

    def _move_linear(self, T_robot_from_tcp: RigidTransform, speed_mm_s: float, accel_mm_s2: float,
                     blocking: bool) -> None:
        raise LifecycleError(self.name, "a state view does not command the arm")

    def _servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None:
        raise LifecycleError(self.name, "a state view does not command the arm")

    def _stop(self, decel_mm_s2: float) -> None:
        raise LifecycleError(self.name, "a state view does not command the arm")
