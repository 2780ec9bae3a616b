"""The safety layer: every motion command passes here before it may reach a robot driver.

It checks, in addition to the :class:`~drivers.interfaces.robot.Robot` base class's own limits
(defence in depth; the two may be configured differently): the workspace box, the commanded
speed and acceleration, the implied speed and acceleration of servo streams, the freshness of
the robot state and its safety status. A refused command raises
:class:`SafetyViolationError` and is never sent. Every command, refusal and stop is reported to
an optional :class:`CommandLog` callback (the session log).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.robot import MotionLimits, Robot, RobotState, SafetyStatus
from hil.clock import Clock
from hil.errors import HilError
from hil.geometry.transform import RigidTransform
from hil.safety.servo_check import servo_step_violation

FloatArray = NDArray[np.float64]


@runtime_checkable
class TrackingRobot(Protocol):
    """A robot driven by a servo loop (hil.servo.client.ServoRobot): it takes tracking setpoints."""

    def start_tracking(self) -> int: ...

    def hold(self) -> None: ...

    def track(self, T_robot_from_tcp: RigidTransform, v_mm_s: FloatArray, w_rad_s: FloatArray, *,
              t_ref_ns: int, valid_until_ns: int, exposure_t_ns: int, frame_seq: int,
              speed_scale: float, max_horizon_s: float, lead_s: float) -> None: ...

    def move_profile_done(self) -> bool: ...


#: ``(event, fields)`` — e.g. ``("command_sent", {...})`` or ``("command_refused", {...})``.
CommandLog = Callable[[str, dict[str, Any]], None]


class SafetyViolationError(HilError):
    """A command was refused by the safety layer (nothing was sent).

    Attributes:
        check: ``workspace``, ``speed``, ``acceleration``, ``angular_speed``, ``state_age``,
            ``robot_safety``, ``period``, ``setpoint``, ``following_error`` (the servo loop's
            :mod:`hil.safety.following`: the arm did not follow).
        detail: what exactly.
    """

    def __init__(self, check: str, detail: str) -> None:
        self.check = check
        self.detail = detail
        super().__init__(f"safety: {check}: {detail}")


class SafetyLayer:
    """The only path from the controller to the robot's motion commands.

    Args:
        robot: an ACTIVE robot.
        limits: the safety layer's limits (usually the setup's ``[safety]`` limits).
        clock: the controller clock (state age).
        robot_state_max_age_s: refuse to command on a robot state older than this.
        log: receives ``command_sent`` / ``command_refused`` / ``stop_sent`` records.
    """

    def __init__(self, robot: Robot, limits: MotionLimits, clock: Clock, *,
                 robot_state_max_age_s: float = 0.05, log: CommandLog | None = None) -> None:
        self.robot = robot
        self.limits = limits
        self.clock = clock
        self.robot_state_max_age_s = robot_state_max_age_s
        self._log = log
        # once, not per setpoint: the limits are frozen, and a Protocol isinstance costs microseconds
        self._box_lo_mm = np.asarray(limits.workspace_min_mm, dtype=np.float64)
        self._box_hi_mm = np.asarray(limits.workspace_max_mm, dtype=np.float64)
        self._tracking_robot: TrackingRobot | None = robot if isinstance(robot, TrackingRobot) else None
        self._last_servo: RigidTransform | None = None
        self._last_servo_velocity_mm_s: np.ndarray[Any, np.dtype[np.float64]] | None = None
        self.commands_sent = 0
        self.commands_refused = 0

    # ------------------------------------------------------------------ checks
    def _refuse(self, kind: str, check: str, detail: str, **fields: Any) -> SafetyViolationError:
        self.commands_refused += 1
        if self._log is not None:
            self._log("command_refused", {"command": kind, "check": check, "detail": detail, **fields})
        return SafetyViolationError(check, detail)

    def _check_box(self, kind: str, T: RigidTransform) -> None:
        p = T.t
        if not np.isfinite(p).all() or (p < self._box_lo_mm).any() or (p > self._box_hi_mm).any():
            box = f"{list(self.limits.workspace_min_mm)}..{list(self.limits.workspace_max_mm)} mm"
            raise self._refuse(kind, "workspace", f"target {np.round(p, 3).tolist()} mm outside box {box}")

    def _tracker(self) -> TrackingRobot:
        """The robot as the servo loop's client. Raises TypeError: it has no servo loop."""
        if self._tracking_robot is None:
            name = type(self.robot).__name__
            raise TypeError(f"{name} has no servo loop (wrap it in hil.servo's ServoRobot)")
        return self._tracking_robot

    def _fresh_state(self, kind: str, state: RobotState | None = None) -> RobotState:
        """``state`` (None: the robot's latest, read now), refused unless it is at most
        :attr:`robot_state_max_age_s` old by the clock and the arm is in NORMAL safety."""
        if state is None:
            state = self.robot.state_now()
        age_s = (self.clock.now_ns() - state.t_ns) * 1e-9
        if age_s > self.robot_state_max_age_s:
            raise self._refuse(kind, "state_age",
                               f"robot state {age_s:.3f} s old > {self.robot_state_max_age_s:.3f} s")
        if state.safety is not SafetyStatus.NORMAL:
            raise self._refuse(kind, "robot_safety", f"robot is in {state.safety.value}")
        return state

    # ------------------------------------------------------------------ commands
    def move_linear(self, T_robot_from_tcp: RigidTransform, speed_mm_s: float, accel_mm_s2: float) -> None:
        """Start a linear move (non-blocking) after the checks.

        Raises:
            SafetyViolationError: refused (nothing sent).
            DriverError: the driver refused or failed (the base class checks again).
        """
        self._check_box("move_linear", T_robot_from_tcp)
        if not (math.isfinite(speed_mm_s) and 0 < speed_mm_s <= self.limits.max_speed_mm_s):
            raise self._refuse("move_linear", "speed",
                               f"{speed_mm_s} mm/s not in (0, {self.limits.max_speed_mm_s}] mm/s")
        if not (math.isfinite(accel_mm_s2) and 0 < accel_mm_s2 <= self.limits.max_accel_mm_s2):
            raise self._refuse("move_linear", "acceleration",
                               f"{accel_mm_s2} mm/s^2 not in (0, {self.limits.max_accel_mm_s2}] mm/s^2")
        self._fresh_state("move_linear")
        self._last_servo = None
        self._last_servo_velocity_mm_s = None
        self.robot.move_linear(T_robot_from_tcp, speed_mm_s, accel_mm_s2, blocking=False)
        self.commands_sent += 1
        if self._log is not None:
            self._log("command_sent", {"command": "move_linear", "target": T_robot_from_tcp,
                                       "speed_mm_s": speed_mm_s, "accel_mm_s2": accel_mm_s2})

    def servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None:
        """Stream one servo target after the checks: state freshness and safety, then the merged
        step check of :mod:`hil.safety.servo_check` (box, implied speed, angular speed and
        acceleration relative to the previous servo target, or the actual pose for the first) —
        the same check the servo loop (hil/servo) applies every period.

        Raises:
            SafetyViolationError: refused (nothing sent).
            DriverError: the driver refused or failed.
        """
        state = self._fresh_state("servo") if math.isfinite(period_s) and period_s > 0 else None
        prev = self._last_servo if self._last_servo is not None else (
            state.T_robot_from_tcp if state is not None else T_robot_from_tcp)
        v_prev = self._last_servo_velocity_mm_s
        if v_prev is None:
            v_prev = np.zeros(3)  # the first step starts from rest (or a ramp after a stop)
        why = servo_step_violation(self.limits, prev.R, prev.t, v_prev, T_robot_from_tcp.R,
                                   T_robot_from_tcp.t, period_s)
        if why is not None:
            raise self._refuse("servo", *why)
        v = (T_robot_from_tcp.t - prev.t) / period_s
        speed = float(np.linalg.norm(v))
        self.robot.servo(T_robot_from_tcp, period_s)
        self._last_servo = T_robot_from_tcp
        self._last_servo_velocity_mm_s = v
        self.commands_sent += 1
        if self._log is not None:
            self._log("command_sent", {"command": "servo", "target_mm": T_robot_from_tcp.t,
                                       "period_s": period_s, "speed_mm_s": speed})

    def move_profile_done(self) -> bool:
        """Whether the servo loop has streamed the last move's whole profile (its target is now
        commanded and held). A phase's arrival check needs it besides the arm's pose and speed: a
        short correction move starts within the arrival tolerance of its target, and the state
        read on the tick after the command may precede the move. True for a robot without a servo
        loop (its state's MOVING mode covers a move it runs itself)."""
        return True if self._tracking_robot is None else self._tracking_robot.move_profile_done()

    def start_tracking(self) -> None:
        """A new tracking session: the servo loop restarts from the actual pose, at rest."""
        self.forget_stream()
        robot = self._tracker()
        robot.start_tracking()

    def track(self, T_robot_from_tcp: RigidTransform, v_mm_s: FloatArray, w_rad_s: FloatArray, *,
              t_ref_ns: int, valid_until_ns: int, exposure_t_ns: int, frame_seq: int,
              speed_scale: float, max_horizon_s: float, lead_s: float,
              state: RobotState | None = None) -> None:
        """Publish a tracking setpoint to the servo loop after the checks: the target inside the
        box, a finite velocity, a fresh robot state in NORMAL safety. (The velocity is the patient's
        and may exceed the arm's limits: the loop's rate limiter bounds what is commanded.) The
        loop applies the merged step check (:mod:`hil.safety.servo_check`) to every command it
        derives. Logged once per setpoint (``command_sent``, command ``track``), not per period.

        ``state``: the robot state the setpoint was made with (the tick read it moments ago), held
        to the same age and safety checks as one read here; None reads one here. Passing it
        saves the supervisor a second read of the servo loop's ring on the pair's path.

        Raises:
            SafetyViolationError: refused (nothing published).
            DriverError: the servo loop is gone.
        """
        self._check_box("track", T_robot_from_tcp)
        if not (np.isfinite(v_mm_s).all() and np.isfinite(w_rad_s).all()):
            raise self._refuse("track", "velocity", "setpoint velocity is not finite")
        self._fresh_state("track", state)
        robot = self._tracker()
        robot.track(T_robot_from_tcp, v_mm_s, w_rad_s, t_ref_ns=t_ref_ns, valid_until_ns=valid_until_ns,
                    exposure_t_ns=exposure_t_ns, frame_seq=frame_seq, speed_scale=speed_scale,
                    max_horizon_s=max_horizon_s, lead_s=lead_s)
        self.commands_sent += 1
        if self._log is not None:
            self._log("command_sent", {"command": "track", "target_mm": T_robot_from_tcp.t,
                                       "v_mm_s": v_mm_s, "frame_seq": frame_seq,
                                       "speed_scale": speed_scale})

    def hold(self, reason: str) -> None:
        """Hold the arm under the servo loop (never refused: the loop brings it to rest from its
        current command at the acceleration limit and commands that pose every period, through
        its step check and following supervision). Logged as ``command_sent``, command ``hold``.

        Raises:
            DriverError: the servo loop is gone.
        """
        robot = self._tracker()
        robot.hold()
        self.commands_sent += 1
        if self._log is not None:
            self._log("command_sent", {"command": "hold", "reason": reason})

    def stop(self, reason: str) -> None:
        """Stop the robot (never refused). Forgets the servo history so a later stream restarts
        from the actual pose and from rest.

        Raises:
            DriverError: the stop could not be delivered (the caller enters FAULT).
        """
        self._last_servo = None
        self._last_servo_velocity_mm_s = None
        if self._log is not None:
            self._log("stop_sent", {"reason": reason})
        self.robot.stop()

    def forget_stream(self) -> None:
        """Start the next servo stream from the actual pose and from rest."""
        self._last_servo = None
        self._last_servo_velocity_mm_s = None
