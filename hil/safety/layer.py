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
from typing import Any

import numpy as np

from drivers.interfaces.robot import MotionLimits, Robot, RobotState, SafetyStatus
from hil.clock import Clock
from hil.errors import HilError
from hil.geometry.transform import RigidTransform

#: ``(event, fields)`` — e.g. ``("command_sent", {...})`` or ``("command_refused", {...})``.
CommandLog = Callable[[str, dict[str, Any]], None]


class SafetyViolationError(HilError):
    """A command was refused by the safety layer (nothing was sent).

    Attributes:
        check: ``workspace``, ``speed``, ``acceleration``, ``angular_speed``, ``state_age``,
            ``robot_safety``, ``period``.
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
        lo = np.asarray(self.limits.workspace_min_mm)
        hi = np.asarray(self.limits.workspace_max_mm)
        if not np.all(np.isfinite(p)) or np.any(p < lo) or np.any(p > hi):
            box = f"{list(self.limits.workspace_min_mm)}..{list(self.limits.workspace_max_mm)} mm"
            raise self._refuse(kind, "workspace", f"target {np.round(p, 3).tolist()} mm outside box {box}")

    def _fresh_state(self, kind: str) -> RobotState:
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
        """Stream one servo target after the checks: box, implied speed, angular speed and
        acceleration relative to the previous servo target (or the actual pose for the first).

        Raises:
            SafetyViolationError: refused (nothing sent).
            DriverError: the driver refused or failed.
        """
        if not (math.isfinite(period_s) and period_s > 0):
            raise self._refuse("servo", "period", f"servo period {period_s} s must be > 0")
        self._check_box("servo", T_robot_from_tcp)
        state = self._fresh_state("servo")
        prev = self._last_servo if self._last_servo is not None else state.T_robot_from_tcp
        v = (T_robot_from_tcp.t - prev.t) / period_s
        speed = float(np.linalg.norm(v))
        if speed > self.limits.max_speed_mm_s:
            raise self._refuse("servo", "speed",
                               f"step implies {speed:.1f} mm/s > {self.limits.max_speed_mm_s} mm/s")
        w = (prev.inverse() @ T_robot_from_tcp).rotation_angle_rad() / period_s
        if w > self.limits.max_angular_speed_rad_s:
            raise self._refuse("servo", "angular_speed",
                               f"step implies {w:.3f} rad/s > {self.limits.max_angular_speed_rad_s} rad/s")
        v_prev = self._last_servo_velocity_mm_s
        if v_prev is None:
            v_prev = np.zeros(3)  # the first step starts from rest (or a ramp after a stop)
        accel = float(np.linalg.norm(v - v_prev)) / period_s
        if accel > self.limits.max_accel_mm_s2:
            raise self._refuse("servo", "acceleration",
                               f"step implies {accel:.0f} mm/s^2 > {self.limits.max_accel_mm_s2} mm/s^2")
        self.robot.servo(T_robot_from_tcp, period_s)
        self._last_servo = T_robot_from_tcp
        self._last_servo_velocity_mm_s = v
        self.commands_sent += 1
        if self._log is not None:
            self._log("command_sent", {"command": "servo", "target_mm": T_robot_from_tcp.t,
                                       "period_s": period_s, "speed_mm_s": speed})

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
