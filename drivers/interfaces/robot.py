"""Robot arm interface. The base class checks limits before any motion reaches a driver.

Poses are ``T_robot_from_tcp`` (the tool centre point in the robot base frame), millimetres and
radians. A driver converts to its device's units (UR: metres, axis-angle) at its own boundary.
"""

from __future__ import annotations

import dataclasses
import math
from abc import abstractmethod
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.errors import DeviceFaultError, LimitViolationError, SafetyStopError
from drivers.interfaces.lifecycle import Device
from hil.geometry.transform import RigidTransform


class RobotMode(StrEnum):
    DISCONNECTED = "disconnected"
    IDLE = "idle"              # powered, brakes released, not moving
    MOVING = "moving"          # executing a move
    SERVOING = "servoing"      # following streamed servo targets
    STOPPED = "stopped"        # program stopped / not ready to accept motion


class SafetyStatus(StrEnum):
    NORMAL = "normal"
    PROTECTIVE_STOP = "protective_stop"
    EMERGENCY_STOP = "emergency_stop"
    FAULT = "fault"


@dataclass(frozen=True)
class RobotState:
    """A snapshot of the arm.

    Attributes:
        T_robot_from_tcp: actual TCP pose in the base frame (mm).
        q_rad: six joint angles, rad.
        mode: what the arm is doing.
        safety: safety status.
        t_ns: host monotonic time of the sample as the driver stamps it (the UR driver: when it
            read the state).
        tcp_speed_mm_s: norm of the actual TCP linear velocity.
        sample_t_ns: host monotonic time at which the arm itself sampled the pose, where the
            driver can tell (the UR driver maps the controller's own timestamp to the host clock,
            :mod:`drivers.ur_rtde.stream_age`); None: not known, take ``t_ns``. The following-error
            supervision compares the pose with the expectation at this time.
    """

    T_robot_from_tcp: RigidTransform
    q_rad: NDArray[np.float64]
    mode: RobotMode
    safety: SafetyStatus
    t_ns: int
    tcp_speed_mm_s: float = 0.0
    sample_t_ns: int | None = None


#: Following-error bounds of a UR3 / UR3e-class arm servoing at breathing-compensation speeds
#: (docs/safety.md, "Following error"): 2 mm / 1.5 deg held for 0.1 s. At the compensation speed
#: limit (60 mm/s by default) a 10 ms mismatch between the lag model and the arm costs 0.6 mm, so a
#: healthy arm stays inside; an arm that stops following a breathing target (5-10 mm/s) leaves the
#: bound within about 0.2-0.4 s.
UR_FOLLOWING_ERROR_MM = 2.0
UR_FOLLOWING_ERROR_DEG = 1.5
UR_FOLLOWING_ERROR_DURATION_S = 0.1


@dataclass(frozen=True)
class FollowingModel:
    """How an arm follows a stream of servo targets, and the bounds of its following-error
    supervision (:mod:`hil.safety.following`; docs/safety.md, "Following error").

    The arm's expected pose is the commanded pose through a first-order lag of
    ``time_constant_s``; the arm is *not following* when its reported pose stays farther than
    ``max_error_mm`` (or turned more than ``max_error_deg``) from that expectation for
    ``max_duration_s`` or longer.

    Attributes:
        time_constant_s: first-order servo tracking lag of the arm, s (>= 0).
        max_error_mm: translation bound, mm (> 0).
        max_error_deg: rotation bound, degrees (> 0).
        max_duration_s: how long a divergence beyond a bound is tolerated, s (> 0).
        source: who chose these values (shown with the figures: "UR servoL lookahead 0.05 s, gain
            500", "[safety] following_error_mm", ...).
    """

    time_constant_s: float = 0.05
    max_error_mm: float = 3.0
    max_error_deg: float = 2.0
    max_duration_s: float = 0.1
    source: str = "generic robot default"

    def __post_init__(self) -> None:
        values = (self.time_constant_s, self.max_error_mm, self.max_error_deg, self.max_duration_s)
        if not all(math.isfinite(v) for v in values) or self.time_constant_s < 0 or min(values[1:]) <= 0:
            raise ValueError(f"following model needs a finite time constant >= 0 and bounds > 0, got {self}")


@dataclass(frozen=True)
class MotionLimits:
    """Hard limits every command is checked against before it reaches a driver.

    Attributes:
        workspace_min_mm, workspace_max_mm: axis-aligned box in the robot base frame that every
            commanded TCP position must stay inside.
        max_speed_mm_s: TCP linear speed.
        max_accel_mm_s2: TCP linear acceleration.
        max_angular_speed_rad_s: TCP angular speed (servo steps).
    """

    workspace_min_mm: tuple[float, float, float] = (-500.0, -500.0, -100.0)
    workspace_max_mm: tuple[float, float, float] = (500.0, 500.0, 600.0)
    max_speed_mm_s: float = 100.0
    max_accel_mm_s2: float = 500.0
    max_angular_speed_rad_s: float = 1.0
    #: following-error bounds that override the robot model's (None: the robot's own,
    #: :attr:`Robot.following_model`)
    following_error_mm: float | None = None
    following_error_deg: float | None = None
    following_error_duration_s: float | None = None
    _eps: float = field(default=1e-9, repr=False)

    def following(self, model: FollowingModel) -> FollowingModel:
        """The robot model's following bounds with this limit set's overrides applied."""
        overrides = {k: v for k, v in (("max_error_mm", self.following_error_mm),
                                       ("max_error_deg", self.following_error_deg),
                                       ("max_duration_s", self.following_error_duration_s)) if v is not None}
        if not overrides:
            return model
        return dataclasses.replace(model, **overrides, source=f"{model.source}; bounds from [safety]")

    def check_position(self, device: str, p_mm: NDArray[np.float64]) -> None:
        lo = np.asarray(self.workspace_min_mm)
        hi = np.asarray(self.workspace_max_mm)
        if not np.all(np.isfinite(p_mm)):
            raise LimitViolationError(device, "workspace", "target position is not finite")
        if np.any(p_mm < lo - self._eps) or np.any(p_mm > hi + self._eps):
            raise LimitViolationError(
                device, "workspace",
                f"target {np.round(p_mm, 3).tolist()} mm outside box "
                f"{list(self.workspace_min_mm)}..{list(self.workspace_max_mm)} mm",
            )

    def check_speed(self, device: str, speed_mm_s: float, accel_mm_s2: float) -> None:
        if not (math.isfinite(speed_mm_s) and 0 < speed_mm_s <= self.max_speed_mm_s + self._eps):
            raise LimitViolationError(
                device, "speed", f"{speed_mm_s} mm/s not in (0, {self.max_speed_mm_s}] mm/s")
        if not (math.isfinite(accel_mm_s2) and 0 < accel_mm_s2 <= self.max_accel_mm_s2 + self._eps):
            raise LimitViolationError(
                device, "acceleration",
                f"{accel_mm_s2} mm/s^2 not in (0, {self.max_accel_mm_s2}] mm/s^2")

    def check_step(
        self, device: str, T_from: RigidTransform, T_to: RigidTransform, dt_s: float
    ) -> None:
        """A servo step from ``T_from`` to ``T_to`` within ``dt_s`` must respect the speed limits."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise LimitViolationError(device, "step", f"servo period {dt_s} s must be > 0")
        v = float(np.linalg.norm(T_to.t - T_from.t)) / dt_s
        if v > self.max_speed_mm_s + self._eps:
            raise LimitViolationError(
                device, "speed",
                f"servo step implies {v:.1f} mm/s > {self.max_speed_mm_s} mm/s")
        w = (T_from.inverse() @ T_to).rotation_angle_rad() / dt_s
        if w > self.max_angular_speed_rad_s + self._eps:
            raise LimitViolationError(
                device, "speed",
                f"servo step implies {w:.3f} rad/s > {self.max_angular_speed_rad_s} rad/s")


class Robot(Device):
    """A robot arm. Public motion methods check lifecycle, safety and limits, then call the
    driver's ``_`` implementation: no driver can skip the check.

    Args:
        name: role name for errors.
        limits: the hard limits.
        T_flange_from_tcp: the tool centre point the driver reports and commands, in the flange
            frame (mm); keyword-only and required, so a driver with a configured TCP cannot forget
            to pass it. A driver without one passes ``RigidTransform.identity()`` (TCP = flange).
    """

    kind = "robot"

    def __init__(self, name: str, limits: MotionLimits, *, T_flange_from_tcp: RigidTransform) -> None:
        super().__init__(name)
        self.limits = limits
        self._T_flange_from_tcp = T_flange_from_tcp
        self._last_servo_target: RigidTransform | None = None

    @property
    def T_flange_from_tcp(self) -> RigidTransform:
        """The TCP in the flange frame (mm): poses in :class:`RobotState` and motion commands are
        this point's. Fixed for the device's life; a wrapper returns its inner robot's. Never
        blocks, never raises, available in every lifecycle state."""
        return self._T_flange_from_tcp

    # ------------------------------------------------------------ public, checked API
    def move_linear(
        self, T_robot_from_tcp: RigidTransform, speed_mm_s: float, accel_mm_s2: float,
        *, blocking: bool = True,
    ) -> None:
        """Linear move of the TCP to a pose.

        Blocks until the arm arrives when ``blocking``; otherwise returns once the move started.

        Raises:
            LifecycleError: not active.
            LimitViolationError: outside workspace/speed/acceleration limits (nothing was sent).
            SafetyStopError: the arm is in a protective or emergency stop (or enters one).
            DeviceFaultError: the arm's program is not running (mode stopped: nothing was sent).
            DisconnectedError, DeviceTimeoutError: transport problems.
        """
        self.require_active("move_linear")
        self.limits.check_position(self.name, T_robot_from_tcp.t)
        self.limits.check_speed(self.name, speed_mm_s, accel_mm_s2)
        self._require_safe()
        self._last_servo_target = None
        self._move_linear(T_robot_from_tcp, speed_mm_s, accel_mm_s2, blocking)

    def servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None:
        """Stream one servo target for closed-loop following; returns at once.

        The step from the previous servo target (or from the actual pose for the first target)
        must respect the speed limits over ``period_s``.

        Raises:
            LifecycleError, LimitViolationError, SafetyStopError, DisconnectedError;
            DeviceFaultError when the arm's program is not running.
        """
        self.require_active("servo")
        self.limits.check_position(self.name, T_robot_from_tcp.t)
        previous = self._last_servo_target or self.state_now().T_robot_from_tcp
        self.limits.check_step(self.name, previous, T_robot_from_tcp, period_s)
        self._require_safe()
        self._servo(T_robot_from_tcp, period_s)
        self._last_servo_target = T_robot_from_tcp

    def stop(self, decel_mm_s2: float | None = None) -> None:
        """Stop any motion with a deceleration (default: the acceleration limit). Blocks until
        the stop command was accepted. Allowed in any safety state; never refused by limits."""
        self.require_active("stop")
        self._last_servo_target = None
        self._stop(decel_mm_s2 if decel_mm_s2 is not None else self.limits.max_accel_mm_s2)

    def state_now(self) -> RobotState:
        """The latest state sample, without blocking.

        Raises:
            LifecycleError: not active.  DisconnectedError: the state stream is gone.
        """
        self.require_active("state")
        return self._state_now()

    def is_steady(self, speed_tol_mm_s: float = 0.5) -> bool:
        """True when the TCP speed is below ``speed_tol_mm_s`` and no move is running."""
        s = self.state_now()
        return s.tcp_speed_mm_s < speed_tol_mm_s and s.mode not in (RobotMode.MOVING,)

    def _safety_and_mode(self) -> tuple[SafetyStatus, RobotMode]:
        """The arm's safety status and mode now (for the check before every motion command).
        This reads a whole state; a driver that knows both more cheaply overrides it (the
        simulated arm: no kinematics in the real-time loop's check)."""
        s = self._state_now()
        return s.safety, s.mode

    def _require_safe(self) -> None:
        safety, mode = self._safety_and_mode()
        if safety is not SafetyStatus.NORMAL:
            raise SafetyStopError(self.name, f"arm is in {safety}; motion refused")
        if mode is RobotMode.STOPPED:
            # not a safety stop: the controller's program stopped (pendant, RTDE watchdog); the
            # same error class as a driver that learns it from the command's refusal
            raise DeviceFaultError(self.name, "arm program (control script) is not running (mode stopped); "
                                              "motion refused (recover() restarts it)")

    @property
    def following_model(self) -> FollowingModel:
        """How this arm follows servo targets and the default bounds of its following-error
        supervision (:class:`FollowingModel`). Drivers that know their arm's servo response
        override it; a wrapper returns its inner robot's. Never blocks, never raises."""
        return FollowingModel()

    # ------------------------------------------------------------ driver implementation
    @property
    @abstractmethod
    def control_rate_hz(self) -> float:
        """The servo/state rate (UR3 CB3 RTDE: 125 Hz; e-Series: 500 Hz)."""

    @abstractmethod
    def _move_linear(
        self, T_robot_from_tcp: RigidTransform, speed_mm_s: float, accel_mm_s2: float,
        blocking: bool,
    ) -> None: ...

    @abstractmethod
    def _servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None: ...

    @abstractmethod
    def _stop(self, decel_mm_s2: float) -> None: ...

    @abstractmethod
    def _state_now(self) -> RobotState: ...

    def recover(self) -> None:
        """Try to leave a protective stop / rebuild a lost connection (driver-specific).

        The default does nothing. Raises DriverError when recovery is impossible.
        """
