"""A robot wrapper that records, at the driver boundary, every command the controller sends and
every state it reads, and checks each command against the setup's limits independently of the
controller's safety layer and of the driver's own checks.

It never refuses anything itself (so it cannot hide a violation): a command is forwarded as is,
and counts as *reached the driver* unless the driver refused it with LimitViolationError.
"""

from __future__ import annotations

import math
from array import array
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.interfaces.errors import DriverError, LimitViolationError
from drivers.interfaces.robot import FollowingModel, MotionLimits, Robot, RobotState
from hil.clock import Clock
from hil.geometry.transform import RigidTransform

_EPS = 1e-6


@dataclass
class CommandRecord:
    """One motion command offered to the driver (times on the controller clock, ns)."""

    t_ns: int
    kind: str  # "move_linear" | "servo" | "stop"
    target_mm: tuple[float, float, float] | None
    speed_mm_s: float | None
    accel_mm_s2: float | None
    violations: tuple[str, ...]
    reached_driver: bool = True
    error: str | None = None


@dataclass
class StateSample:
    t_ns: int
    speed_mm_s: float
    mode: str
    safety: str


@dataclass
class Recording:
    commands: list[CommandRecord] = field(default_factory=list)
    states: list[StateSample] = field(default_factory=list)

    def violations_reached(self) -> list[CommandRecord]:
        """Commands outside the limits that the driver did not refuse."""
        return [c for c in self.commands if c.violations and c.reached_driver]

    def max_speed_mm_s(self) -> float:
        return max((s.speed_mm_s for s in self.states), default=0.0)


class RecordingRobot(Robot):
    """Wraps an already built robot (opened and closed through this wrapper).

    Args:
        inner: the robot the setup built (fault-wrapped or not).
        limits: the limits every command is checked against (the setup's ``[safety]``).
        clock: the controller clock.
        compact: keep only what a long run needs, in constant memory per command: the times of
            the servo commands that reached the driver (``servo_t_ns``, 8 bytes each) and the
            commands with a violation; no state samples (the soak uses this).
    """

    def __init__(self, inner: Robot, limits: MotionLimits, clock: Clock, *, compact: bool = False) -> None:
        super().__init__(inner.name, inner.limits, T_flange_from_tcp=inner.T_flange_from_tcp)
        self.inner = inner
        self.check_limits = limits
        self.clock = clock
        self.recording = Recording()
        self.compact = compact
        self.servo_t_ns: array[int] = array("q")
        self._last_servo: RigidTransform | None = None
        self._last_servo_v: np.ndarray[Any, np.dtype[np.float64]] | None = None
        self._last_pose: RigidTransform | None = None

    # ------------------------------------------------------------------ lifecycle
    def _open(self) -> None:
        self.inner.open()

    def _close(self) -> None:
        self.inner.close()

    @property
    def control_rate_hz(self) -> float:
        return self.inner.control_rate_hz

    @property
    def following_model(self) -> FollowingModel:
        """The inner robot's."""
        return self.inner.following_model

    @property
    def T_flange_from_tcp(self) -> RigidTransform:
        """The inner robot's TCP in the flange frame (mm), never a default of its own."""
        return self.inner.T_flange_from_tcp

    # ------------------------------------------------------------------ checks
    def _box(self, T: RigidTransform) -> list[str]:
        p = np.asarray(T.t, dtype=np.float64)
        lo = np.asarray(self.check_limits.workspace_min_mm) - _EPS
        hi = np.asarray(self.check_limits.workspace_max_mm) + _EPS
        if not np.all(np.isfinite(p)) or np.any(p < lo) or np.any(p > hi):
            return [f"workspace: {np.round(p, 3).tolist()} mm"]
        return []

    def _record(self, rec: CommandRecord, call: Any) -> None:
        if not self.compact or rec.violations:
            self.recording.commands.append(rec)
        try:
            call()
        except LimitViolationError as exc:
            rec.reached_driver = False
            rec.error = str(exc)
            raise
        except Exception as exc:
            rec.error = f"{type(exc).__name__}: {exc}"
            raise
        if rec.kind == "servo":
            self.servo_t_ns.append(rec.t_ns)

    # ------------------------------------------------------------------ forwarded API
    def move_linear(
        self,
        T_robot_from_tcp: RigidTransform,
        speed_mm_s: float,
        accel_mm_s2: float,
        *,
        blocking: bool = True,
    ) -> None:
        lim = self.check_limits
        v = self._box(T_robot_from_tcp)
        if not (math.isfinite(speed_mm_s) and 0 < speed_mm_s <= lim.max_speed_mm_s + _EPS):
            v.append(f"speed: {speed_mm_s} mm/s")
        if not (math.isfinite(accel_mm_s2) and 0 < accel_mm_s2 <= lim.max_accel_mm_s2 + _EPS):
            v.append(f"acceleration: {accel_mm_s2} mm/s^2")
        self._last_servo = None
        self._last_servo_v = None
        t = T_robot_from_tcp.t
        rec = CommandRecord(
            self.clock.now_ns(),
            "move_linear",
            (float(t[0]), float(t[1]), float(t[2])),
            speed_mm_s,
            accel_mm_s2,
            tuple(v),
        )
        self._record(
            rec, lambda: self.inner.move_linear(T_robot_from_tcp, speed_mm_s, accel_mm_s2, blocking=blocking)
        )

    def servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None:
        lim = self.check_limits
        v = self._box(T_robot_from_tcp)
        speed = None
        if not (math.isfinite(period_s) and period_s > 0):
            v.append(f"period: {period_s} s")
        else:
            # the first step of a stream starts from rest at the pose the robot last reported
            prev = self._last_servo if self._last_servo is not None else self._last_pose
            vel = (T_robot_from_tcp.t - prev.t) / period_s if prev is not None else np.zeros(3)
            speed = float(np.linalg.norm(vel))
            if speed > lim.max_speed_mm_s * (1 + 1e-6) + _EPS:
                v.append(f"servo step speed: {speed:.1f} mm/s")
            v_prev = self._last_servo_v if self._last_servo_v is not None else np.zeros(3)
            accel = float(np.linalg.norm(vel - v_prev)) / period_s
            if accel > lim.max_accel_mm_s2 * (1 + 1e-6) + _EPS:
                v.append(f"servo step acceleration: {accel:.0f} mm/s^2")
            self._last_servo_v = vel
            w = 0.0 if prev is None else (prev.inverse() @ T_robot_from_tcp).rotation_angle_rad() / period_s
            if w > lim.max_angular_speed_rad_s * (1 + 1e-6) + _EPS:
                v.append(f"servo step angular speed: {w:.3f} rad/s")
        t = T_robot_from_tcp.t
        rec = CommandRecord(
            self.clock.now_ns(), "servo", (float(t[0]), float(t[1]), float(t[2])), speed, None, tuple(v)
        )
        try:
            self._record(rec, lambda: self.inner.servo(T_robot_from_tcp, period_s))
        except DriverError:
            # refused or failed: the servo loop starts its stream again from the actual pose at
            # rest once commands are accepted again (hil.servo.loop), so the next step is checked
            # from rest at the last reported pose, as a stream's first step always is
            self._last_servo = None
            self._last_servo_v = None
            raise
        self._last_servo = T_robot_from_tcp

    def stop(self, decel_mm_s2: float | None = None) -> None:
        self._last_servo = None
        self._last_servo_v = None
        rec = CommandRecord(self.clock.now_ns(), "stop", None, None, decel_mm_s2, ())
        self._record(rec, lambda: self.inner.stop(decel_mm_s2))

    def state_now(self) -> RobotState:
        st = self.inner.state_now()
        self._last_pose = st.T_robot_from_tcp
        if self.compact:
            return st
        self.recording.states.append(
            StateSample(
                self.clock.now_ns(),
                float(st.tcp_speed_mm_s),
                str(getattr(st.mode, "value", st.mode)),
                str(getattr(st.safety, "value", st.safety)),
            )
        )
        return st

    def recover(self) -> None:
        self.inner.recover()

    # the abstract driver hooks are never reached: every public method forwards to ``inner``
    def _move_linear(
        self, T_robot_from_tcp: RigidTransform, speed_mm_s: float, accel_mm_s2: float, blocking: bool
    ) -> None:  # pragma: no cover
        raise NotImplementedError

    def _servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None:  # pragma: no cover
        raise NotImplementedError

    def _stop(self, decel_mm_s2: float) -> None:  # pragma: no cover
        raise NotImplementedError

    def _state_now(self) -> RobotState:  # pragma: no cover
        raise NotImplementedError
