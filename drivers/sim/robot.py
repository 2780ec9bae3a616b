"""Simulated UR3 (CB3) or UR3e: analytic kinematics, joint limits, joint-speed limit, servo lag.

State is a pure function of the commands and the clock: a move is a trapezoidal Cartesian
profile sampled into joint waypoints (inverse kinematics once per command, forward kinematics
per query, so queries are cheap); a servo target is followed by a first-order lag in joint space
(time constant ``servo_time_constant_s``). Commands the arm cannot execute (no inverse
kinematics, a joint limit, a joint-speed limit, a wrist flip) put it in a protective stop, as a
real controller does; it stays there until :meth:`SimRobot.recover`. ``stop`` decelerates a
running linear move along its path at the given deceleration; a servo follow simply holds.
:meth:`SimRobot.connection_lost` does the same when the link drops (a UR program stops then).
Servo targets are inverted by Newton steps from the previous target (fast, same branch), falling
back to the analytic solver of :mod:`hil.kinematics.ur`. Joint accelerations are not limited.

Limits of :class:`~drivers.interfaces.robot.MotionLimits` are checked by the base class before
any of this runs.

Rig errors (``[simulation.rig_errors]`` of the world, all off by default): with
``robot_joint_offset_error_rad`` the true flange (:meth:`SimRobot.T_robot_from_flange_at`, what the
world and the cameras see) is the forward kinematics of ``q + offsets`` while the arm reports the
nominal kinematics of ``q``; with ``robot_state_latency_ms`` a state stamped ``t`` reports the
joints (pose, speed) of ``t - latency``.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, Field

from drivers.interfaces.errors import SafetyStopError
from drivers.interfaces.robot import (
    UR_FOLLOWING_ERROR_DEG,
    UR_FOLLOWING_ERROR_DURATION_S,
    UR_FOLLOWING_ERROR_MM,
    FollowingModel,
    MotionLimits,
    Robot,
    RobotMode,
    RobotState,
    SafetyStatus,
)
from drivers.sim.rig_errors import joint_offsets
from drivers.sim.world import SimWorld
from hil.clock import Clock
from hil.config.types import STRICT, TransformConfig
from hil.geometry.transform import RigidTransform
from hil.kinematics.ur import UR3_JOINT_LIMITS_RAD, ur_forward, ur_inverse, ur_newton_ik
from hil.log import get_logger
from plugins.registry import DriverContext

FloatArray = NDArray[np.float64]
Q6 = tuple[float, float, float, float, float, float]
_log = get_logger(__name__)

_WAYPOINT_MM = 5.0
_WAYPOINT_RAD = 0.05
_MAX_WAYPOINTS = 60
_FLIP_RAD = 0.6  # a joint jumping this much between close waypoints: wrist/elbow flip
_NEWTON_ITERATIONS = 6
_NEWTON_TOL_MM = 1e-6
_NEWTON_TOL_RAD = 1e-9
_NEWTON_MIN_DET = 1e3  # mm^3: |det J| below this is near a singularity (use the analytic solver)


class SimRobotConfig(BaseModel):
    """``[robot] driver = "sim"``."""

    model_config = STRICT

    driver: Literal["sim"]
    model: Literal["ur3", "ur3e"] = Field("ur3", description="DH table (hil.kinematics.ur)")
    control_rate_hz: float = Field(125.0, gt=0, le=1000, description="CB3: 125, e-Series: 500")
    initial_q_rad: Q6 = Field((1.9513, -1.4523, -1.8396, -1.4204, 1.5708, 0.3805),
                              description="joint angles at start (default: flange above the phantom)")
    max_joint_speed_rad_s: float = Field(3.14, gt=0, description="protective stop above this")
    servo_time_constant_s: float = Field(0.03, ge=0, description="first-order servo tracking lag")
    T_flange_from_tcp: TransformConfig = Field(TransformConfig.identity(),
                                               description="TCP offset (the pose the arm reports)")


@dataclass(frozen=True)
class _Hold:
    start_ns: int
    q: FloatArray


@dataclass(frozen=True)
class _Move:
    start_ns: int
    duration_s: float
    accel_fraction: float        # fraction of the duration spent accelerating (and decelerating)
    waypoints: FloatArray        # (M, 6), at equal path fractions
    length_mm: float = 0.0       # TCP path length
    decel_only: bool = False     # a stopping ramp: full speed at start, rest at the end


@dataclass(frozen=True)
class _Servo:
    start_ns: int
    q_from: FloatArray
    q_target: FloatArray
    tau_s: float


_Segment = _Hold | _Move | _Servo


def trapezoid_duration_s(distance: float, speed: float, accel: float) -> tuple[float, float]:
    """Duration of a rest-to-rest trapezoidal (or triangular) profile and its acceleration time."""
    if distance <= 0.0:
        return 0.0, 0.0
    if distance <= speed * speed / accel:
        t_acc = math.sqrt(distance / accel)
        return 2.0 * t_acc, t_acc
    t_acc = speed / accel
    return distance / speed + t_acc, t_acc


def decel_fraction(t: float, duration: float) -> float:
    """Path fraction of a constant deceleration from speed 2/duration to rest in ``duration``."""
    if duration <= 0.0 or t >= duration:
        return 1.0
    if t <= 0.0:
        return 0.0
    r = 1.0 - t / duration
    return 1.0 - r * r


def trapezoid_speed(t: float, duration: float, accel_fraction: float) -> float:
    """Path-fraction speed ds/dt of :func:`trapezoid_fraction` (1/s)."""
    if duration <= 0.0 or t <= 0.0 or t >= duration:
        return 0.0
    ta = accel_fraction * duration
    v = 1.0 / (duration - ta)
    if t < ta:
        return v * t / ta
    if t <= duration - ta:
        return v
    return v * (duration - t) / ta


def trapezoid_fraction(t: float, duration: float, accel_fraction: float) -> float:
    """Path fraction s(t) in [0, 1] of a normalised trapezoidal profile."""
    if duration <= 0.0 or t >= duration:
        return 1.0
    if t <= 0.0:
        return 0.0
    ta = accel_fraction * duration
    v = 1.0 / (duration - ta)  # peak path-fraction speed
    if t < ta:
        return 0.5 * v / ta * t * t
    if t <= duration - ta:
        return 0.5 * v * ta + v * (t - ta)
    r = duration - t
    return 1.0 - 0.5 * v / ta * r * r


def _interpolate(waypoints: FloatArray, s: float) -> FloatArray:
    """Joint vector at path fraction ``s`` of equally spaced waypoints (piecewise linear)."""
    x = min(max(s, 0.0), 1.0) * (len(waypoints) - 1)
    i = min(int(x), len(waypoints) - 2)
    f = x - i
    q: FloatArray = waypoints[i] * (1.0 - f) + waypoints[i + 1] * f
    return q


class SimRobot(Robot):
    """A simulated UR arm on the injected clock."""

    def __init__(self, name: str, limits: MotionLimits, cfg: SimRobotConfig, clock: Clock,
                 world: SimWorld | None = None) -> None:
        super().__init__(name, limits, T_flange_from_tcp=cfg.T_flange_from_tcp.as_transform())
        self.cfg = cfg
        self.clock = clock
        self.world = world
        self.T_tcp_from_flange = self.T_flange_from_tcp.inverse()
        self.joint_limits_rad: FloatArray = np.asarray(UR3_JOINT_LIMITS_RAD, dtype=np.float64)
        q0 = np.asarray(cfg.initial_q_rad, dtype=np.float64)
        self._segments: deque[_Segment] = deque([_Hold(clock.now_ns(), q0)], maxlen=16)
        self._safety = SafetyStatus.NORMAL
        self._lock = threading.RLock()
        self._q_error: FloatArray = np.zeros(6)
        self._report_lag_ns = 0
        if world is not None:
            e = world.rig_errors
            self._q_error = joint_offsets(e.robot_joint_offset_error_rad, world.rng("robot_joint_offsets"))
            self._report_lag_ns = round(e.robot_state_latency_ms * 1e6)
            world.attach_robot(self)

    # ------------------------------------------------------------------ lifecycle
    def _open(self) -> None:
        with self._lock:
            q = self.q_at(self.clock.now_ns())
            self._segments.append(_Hold(self.clock.now_ns(), q))

    def _close(self) -> None:
        pass

    @property
    def control_rate_hz(self) -> float:
        return self.cfg.control_rate_hz

    @property
    def following_model(self) -> FollowingModel:
        """The simulated arm's own first-order servo lag (``servo_time_constant_s``) and the
        UR defaults' bounds (docs/safety.md, "Following error")."""
        return FollowingModel(self.cfg.servo_time_constant_s, UR_FOLLOWING_ERROR_MM, UR_FOLLOWING_ERROR_DEG,
                              UR_FOLLOWING_ERROR_DURATION_S,
                              f"simulated arm, servo lag {self.cfg.servo_time_constant_s:g} s")

    # ------------------------------------------------------------------ kinematic state
    def _segment_at(self, t_ns: int) -> _Segment:
        for seg in reversed(self._segments):
            if seg.start_ns <= t_ns:
                return seg
        return self._segments[0]

    def q_at(self, t_ns: int) -> FloatArray:
        """Joint angles (rad) at ``t_ns`` (any time since the last few commands)."""
        with self._lock:
            seg = self._segment_at(t_ns)
        dt = (t_ns - seg.start_ns) * 1e-9
        if isinstance(seg, _Hold):
            return seg.q
        if isinstance(seg, _Servo):
            if seg.tau_s <= 0.0:
                return seg.q_target
            return seg.q_target + (seg.q_from - seg.q_target) * math.exp(-max(dt, 0.0) / seg.tau_s)
        if seg.decel_only:
            s = decel_fraction(dt, seg.duration_s)
        else:
            s = trapezoid_fraction(dt, seg.duration_s, seg.accel_fraction)
        return _interpolate(seg.waypoints, s)

    def _path_state(self, seg: _Move, t_ns: int) -> tuple[float, float]:
        """Path fraction and TCP speed (mm/s) of a move at ``t_ns``."""
        dt = (t_ns - seg.start_ns) * 1e-9
        if seg.decel_only:
            s = decel_fraction(dt, seg.duration_s)
            ds = 2.0 / seg.duration_s * max(1.0 - dt / seg.duration_s, 0.0) if seg.duration_s > 0 else 0.0
        else:
            s = trapezoid_fraction(dt, seg.duration_s, seg.accel_fraction)
            ds = trapezoid_speed(dt, seg.duration_s, seg.accel_fraction)
        return s, ds * seg.length_mm

    def T_robot_from_flange_at(self, t_ns: int) -> RigidTransform:
        """The true flange pose at ``t_ns`` (with the rig's joint offset errors, if any)."""
        return ur_forward(self.q_at(t_ns) + self._q_error, self.cfg.model)

    def T_robot_from_tcp_at(self, t_ns: int) -> RigidTransform:
        """The TCP pose the arm reports for ``t_ns`` (nominal kinematics of its joints)."""
        return ur_forward(self.q_at(t_ns), self.cfg.model) @ self.T_flange_from_tcp

    def _mode_at(self, t_ns: int) -> RobotMode:
        if self._safety is not SafetyStatus.NORMAL:
            return RobotMode.STOPPED
        seg = self._segment_at(t_ns)
        dt = (t_ns - seg.start_ns) * 1e-9
        if isinstance(seg, _Move) and dt < seg.duration_s:
            return RobotMode.MOVING
        if isinstance(seg, _Servo) and dt < max(0.2, 5.0 * seg.tau_s):
            return RobotMode.SERVOING
        return RobotMode.IDLE

    def _safety_and_mode(self) -> tuple[SafetyStatus, RobotMode]:
        """What :meth:`_state_now` reports for both, without its kinematics."""
        return self._safety, self._mode_at(self.clock.now_ns())

    def _state_now(self) -> RobotState:
        t_stamp = self.clock.now_ns()
        t = t_stamp - self._report_lag_ns  # the joints the report carries
        q = self.q_at(t)
        T = ur_forward(q, self.cfg.model) @ self.T_flange_from_tcp
        dt_ns = 2_000_000
        speed = 0.0
        with self._lock:
            seg = self._segment_at(t)
            resting = isinstance(seg, _Hold) and self._segment_at(t - dt_ns) is seg
        if not resting:
            T_prev = self.T_robot_from_tcp_at(t - dt_ns)
            speed = float(np.linalg.norm(T.t - T_prev.t)) / (dt_ns * 1e-9)
        return RobotState(T_robot_from_tcp=T, q_rad=q.copy(), mode=self._mode_at(t_stamp),
                          safety=self._safety, t_ns=t_stamp, tcp_speed_mm_s=speed)

    # ------------------------------------------------------------------ limits of the arm
    def _ik(self, T_robot_from_tcp: RigidTransform, q_near: FloatArray) -> FloatArray | None:
        T_flange = T_robot_from_tcp @ self.T_tcp_from_flange
        q_fast = ur_newton_ik(T_flange, q_near, self.cfg.model, iterations=_NEWTON_ITERATIONS,
                              tol_mm=_NEWTON_TOL_MM, tol_rad=_NEWTON_TOL_RAD, min_det_mm3=_NEWTON_MIN_DET,
                              max_jump_rad=_FLIP_RAD)
        if q_fast is not None and bool(np.all(q_fast >= self.joint_limits_rad[:, 0])) \
                and bool(np.all(q_fast <= self.joint_limits_rad[:, 1])):
            return q_fast
        sols = ur_inverse(T_flange, self.cfg.model, q_near=q_near)
        for q in sols:
            if np.all(q >= self.joint_limits_rad[:, 0]) and np.all(q <= self.joint_limits_rad[:, 1]):
                return np.asarray(q, dtype=np.float64)
        return None

    def _protective_stop(self, reason: str) -> SafetyStopError:
        t = self.clock.now_ns()
        with self._lock:
            q = self.q_at(t)
            self._segments.append(_Hold(t, q))
            self._safety = SafetyStatus.PROTECTIVE_STOP
        _log.warning("robot_protective_stop", device=self.name, reason=reason)
        return SafetyStopError(self.name, f"protective stop: {reason}")

    # ------------------------------------------------------------------ commands
    def _move_linear(self, T_robot_from_tcp: RigidTransform, speed_mm_s: float, accel_mm_s2: float,
                     blocking: bool) -> None:
        t = self.clock.now_ns()
        q_start = self.q_at(t)
        T_start = ur_forward(q_start, self.cfg.model) @ self.T_flange_from_tcp
        dist = float(np.linalg.norm(T_robot_from_tcp.t - T_start.t))
        rel = (T_start.inverse() @ T_robot_from_tcp).as_rotvec()
        angle = float(np.linalg.norm(rel))
        dur_lin, ta_lin = trapezoid_duration_s(dist, speed_mm_s, accel_mm_s2)
        w = self.limits.max_angular_speed_rad_s
        dur_ang, ta_ang = trapezoid_duration_s(angle, w, w * accel_mm_s2 / speed_mm_s)
        duration, t_acc = (dur_lin, ta_lin) if dur_lin >= dur_ang else (dur_ang, ta_ang)
        n = int(min(_MAX_WAYPOINTS, max(2, math.ceil(dist / _WAYPOINT_MM) + 1,
                                        math.ceil(angle / _WAYPOINT_RAD) + 1)))
        waypoints = [q_start]
        for k in range(1, n):
            s = k / (n - 1)
            T_k = RigidTransform(T_start.R @ RigidTransform.from_rotvec(rel * s).R,
                                 T_start.t + s * (T_robot_from_tcp.t - T_start.t))
            q_k = self._ik(T_k, waypoints[-1])
            if q_k is None:
                raise self._protective_stop(
                    f"no inverse kinematics within joint limits at {np.round(T_k.t, 1).tolist()} mm")
            if float(np.max(np.abs(q_k - waypoints[-1]))) > _FLIP_RAD:
                raise self._protective_stop("the path crosses a singularity (joint flip)")
            waypoints.append(q_k)
        wp = np.array(waypoints)
        if duration > 0.0:
            v_peak = 1.0 / (duration - t_acc)  # path fraction per second
            dq_ds = np.max(np.abs(np.diff(wp, axis=0))) * (n - 1)
            if dq_ds * v_peak > self.cfg.max_joint_speed_rad_s:
                raise self._protective_stop(
                    f"joint speed {dq_ds * v_peak:.2f} rad/s > {self.cfg.max_joint_speed_rad_s} rad/s")
        with self._lock:
            self._segments.append(_Move(t, duration, t_acc / duration if duration > 0 else 0.0, wp, dist))
        if blocking and duration > 0.0:
            self.clock.sleep(duration)

    def _servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None:
        t = self.clock.now_ns()
        q_now = self.q_at(t)
        with self._lock:
            seg = self._segments[-1]
        q_prev_target = seg.q_target if isinstance(seg, _Servo) else q_now
        q_target = self._ik(T_robot_from_tcp, q_prev_target)
        if q_target is None:
            raise self._protective_stop(
                f"servo target {np.round(T_robot_from_tcp.t, 1).tolist()} mm has no inverse kinematics")
        joint_speed = float(np.max(np.abs(q_target - q_prev_target))) / period_s
        if joint_speed > self.cfg.max_joint_speed_rad_s:
            raise self._protective_stop(
                f"servo step needs {joint_speed:.2f} rad/s > {self.cfg.max_joint_speed_rad_s} rad/s")
        with self._lock:
            self._segments.append(_Servo(t, q_now, q_target, self.cfg.servo_time_constant_s))

    def _stop(self, decel_mm_s2: float) -> None:
        """A running linear move decelerates at ``decel_mm_s2`` along its path (returns at once);
        anything else holds where the arm is now."""
        self._stop_from(self.clock.now_ns(), decel_mm_s2)

    def connection_lost(self, at_ns: int | None = None) -> None:
        """The RTDE / script link dropped at ``at_ns`` (default: now): as on a UR, the running
        program stops -- a linear move decelerates to rest at the stop deceleration (the
        acceleration limit), a servo follow holds. Later commands start from rest. Works in any
        lifecycle state (it is what the arm does, not a command); returns at once."""
        with self._lock:
            t = self.clock.now_ns() if at_ns is None else max(at_ns, self._segments[-1].start_ns)
            self._stop_from(t, self.limits.max_accel_mm_s2)
        _log.warning("robot_connection_lost_stop", device=self.name, t_ns=t)

    def _stop_from(self, t: int, decel_mm_s2: float) -> None:
        with self._lock:
            seg = self._segment_at(t)
            q_now = self.q_at(t)
            if isinstance(seg, _Move) and seg.length_mm > 0.0 and decel_mm_s2 > 0.0:
                s, v = self._path_state(seg, t)
                if v > 0.0:
                    s_end = min(s + v * v / (2.0 * decel_mm_s2) / seg.length_mm, 1.0)
                    d_mm = (s_end - s) * seg.length_mm
                    n = max(2, min(_MAX_WAYPOINTS, math.ceil(d_mm / _WAYPOINT_MM) + 1))
                    fractions = s + (s_end - s) * np.arange(n) / (n - 1)
                    wp = np.array([_interpolate(seg.waypoints, float(f)) for f in fractions])
                    self._segments.append(_Move(t, 2.0 * d_mm / v, 0.0, wp, d_mm, decel_only=True))
                    return
            self._segments.append(_Hold(t, q_now))

    def recover(self) -> None:
        """Unlock a protective stop (the arm holds where it stopped)."""
        self.require_active("recover")
        with self._lock:
            if self._safety is SafetyStatus.PROTECTIVE_STOP:
                self._safety = SafetyStatus.NORMAL
                _log.info("robot_protective_stop_cleared", device=self.name)

    def trigger_protective_stop(self, reason: str = "requested") -> None:
        """Put the arm in a protective stop (what a collision or the pendant would do)."""
        self._protective_stop(reason)


def make_sim_robot(config: SimRobotConfig, ctx: DriverContext) -> SimRobot:
    """Factory registered as robot driver ``sim``."""
    world = ctx.world if isinstance(ctx.world, SimWorld) else None
    return SimRobot(ctx.role, ctx.limits, config, ctx.clock, world)
