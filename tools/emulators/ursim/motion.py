"""Motion generators of the emulated UR controller (metres, radians, seconds: UR's own units).

Each generator advances the arm by one controller tick: ``step(arm, dt_s)`` writes ``arm.q`` and
returns True once the motion is complete. Profiles are trapezoidal (acceleration-limited), as UR's
movej/movel; servo follows its target through a first-order lag whose time constant grows with the
lookahead time; speed modes ramp the velocity with the given acceleration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from hil.geometry.transform import matrix_to_rotvec, rotvec_to_matrix

FloatArray = NDArray[np.float64]

# UR3 joint speed limits (rad/s): base, shoulder, elbow 180 deg/s; wrists 360 deg/s.
JOINT_SPEED_LIMIT_RAD_S = np.array([math.pi, math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi])


class Arm(Protocol):
    """What a motion needs from the controller."""

    q: FloatArray
    tcp_twist: FloatArray  # (6,) [v m/s, w rad/s] in the base frame, last tick

    def fk(self, q: FloatArray) -> FloatArray:
        """4x4 T_base_from_tool (m)."""
        ...

    def ik(self, T: FloatArray, q_near: FloatArray) -> FloatArray | None:
        """Joint solution nearest ``q_near`` for a 4x4 pose (m), or None."""
        ...


class MotionError(Exception):
    """The motion cannot continue (e.g. no inverse kinematics solution on the path)."""


class Motion(Protocol):
    name: str

    def step(self, arm: Arm, dt_s: float) -> bool: ...


def trapezoid(distance: float, v_max: float, a_max: float, t_s: float) -> float:
    """Position along a rest-to-rest acceleration-limited profile at time ``t_s`` (clamped to the end)."""
    if distance <= 0.0:
        return 0.0
    v = max(v_max, 1e-9)
    a = max(a_max, 1e-9)
    t_acc = v / a
    d_acc = 0.5 * a * t_acc * t_acc
    if 2 * d_acc > distance:  # triangular profile
        t_acc = math.sqrt(distance / a)
        v = a * t_acc
        d_acc = 0.5 * distance
    t_flat = (distance - 2 * d_acc) / v
    if t_s <= 0:
        return 0.0
    if t_s < t_acc:
        return 0.5 * a * t_s * t_s
    if t_s < t_acc + t_flat:
        return d_acc + v * (t_s - t_acc)
    t_dec = t_s - t_acc - t_flat
    if t_dec < t_acc:
        return distance - 0.5 * a * (t_acc - t_dec) ** 2
    return distance


@dataclass
class JointMove:
    """movej: all joints start and stop together; the largest joint travel sets the profile."""

    q_goal: FloatArray
    speed: float
    accel: float
    name: str = "movej"
    _q0: FloatArray | None = None
    _t: float = 0.0

    def step(self, arm: Arm, dt_s: float) -> bool:
        if self._q0 is None:
            self._q0 = arm.q.copy()
        delta = self.q_goal - self._q0
        dist = float(np.max(np.abs(delta)))
        self._t += dt_s
        if dist < 1e-12:
            arm.q = self.q_goal.copy()
            return True
        s = trapezoid(dist, self.speed, self.accel, self._t)
        arm.q = self._q0 + delta * (s / dist)
        return s >= dist


@dataclass
class LinearMove:
    """movel: the tool moves on a straight line, orientation interpolated on the geodesic."""

    T_goal: FloatArray
    speed: float
    accel: float
    name: str = "movel"
    _T0: FloatArray | None = None
    _rv: FloatArray = field(default_factory=lambda: np.zeros(3))
    _length: float = 0.0
    _by_angle: bool = False
    _t: float = 0.0

    def step(self, arm: Arm, dt_s: float) -> bool:
        if self._T0 is None:
            self._T0 = arm.fk(arm.q)
            self._rv = matrix_to_rotvec(self._T0[:3, :3].T @ self.T_goal[:3, :3])
            lin = float(np.linalg.norm(self.T_goal[:3, 3] - self._T0[:3, 3]))
            ang = float(np.linalg.norm(self._rv))
            self._by_angle = lin < 1e-6
            self._length = ang if self._by_angle else lin
        self._t += dt_s
        if self._length < 1e-12:
            frac = 1.0
        else:
            frac = trapezoid(self._length, self.speed, self.accel, self._t) / self._length
        T = np.eye(4)
        T[:3, 3] = self._T0[:3, 3] + frac * (self.T_goal[:3, 3] - self._T0[:3, 3])
        T[:3, :3] = self._T0[:3, :3] @ rotvec_to_matrix(frac * self._rv)
        q = arm.ik(T, arm.q)
        if q is None:
            raise MotionError("movel: no inverse kinematics solution on the path")
        arm.q = q
        return frac >= 1.0


@dataclass
class PathMove:
    """A sequence of moves (movePath / moveL(path)); blends are not modelled."""

    moves: list[Motion]
    name: str = "move_path"
    index: int = 0

    def step(self, arm: Arm, dt_s: float) -> bool:
        while self.index < len(self.moves):
            if self.moves[self.index].step(arm, dt_s):
                self.index += 1
            return self.index >= len(self.moves)
        return True


@dataclass
class Servo:
    """servoj/servoL: follow the latest target through a first-order lag.

    Time constant ``0.3 * lookahead_time + 1 / gain`` (s): UR's default lookahead 0.1 s and gain 300
    give ~33 ms of lag, as measured on real arms; joint speeds are clamped to the UR3 limits.
    """

    q_target: FloatArray
    lookahead_time_s: float
    gain: float
    name: str = "servo"

    def retarget(self, q_target: FloatArray, lookahead_time_s: float, gain: float) -> None:
        self.q_target = q_target
        self.lookahead_time_s = lookahead_time_s
        self.gain = gain

    def step(self, arm: Arm, dt_s: float) -> bool:
        tau = 0.3 * self.lookahead_time_s + 1.0 / max(self.gain, 1.0)
        k = min(1.0, dt_s / max(tau, 1e-6))
        dq = (self.q_target - arm.q) * k
        dq = np.clip(dq, -JOINT_SPEED_LIMIT_RAD_S * dt_s, JOINT_SPEED_LIMIT_RAD_S * dt_s)
        arm.q = arm.q + dq
        return False


def _norm(x: FloatArray) -> float:
    """Euclidean norm without overflow in the squares (inputs up to 1e308 give a finite norm or inf)."""
    m = float(np.max(np.abs(x))) if x.size else 0.0
    if m == 0.0 or not math.isfinite(m):
        return m
    return m * float(np.linalg.norm(x / m))


def _ramp(current: FloatArray, target: FloatArray, max_change: float) -> FloatArray:
    diff = target - current
    n = _norm(diff)
    if n <= max_change or n < 1e-15:
        return target.copy()
    return current + diff * (max_change / n)


@dataclass
class SpeedL:
    """speedl: ramp the tool twist [v, w] (base frame) to a target with ``accel``; integrate the pose.

    With ``stop_at_zero`` it is stopl: the target is zero and the motion ends at rest.
    """

    twist_target: FloatArray
    accel: float
    name: str = "speedl"
    stop_at_zero: bool = False
    _twist: FloatArray | None = None
    _T: FloatArray | None = None

    def step(self, arm: Arm, dt_s: float) -> bool:
        if self._twist is None:
            self._twist = arm.tcp_twist.copy()
            self._T = arm.fk(arm.q)
        assert self._T is not None
        tw = self._twist
        v = _ramp(tw[:3], self.twist_target[:3], self.accel * dt_s)
        w = _ramp(tw[3:], self.twist_target[3:], self.accel * dt_s)
        self._twist = np.concatenate([v, w])
        T = self._T.copy()
        T[:3, 3] = T[:3, 3] + v * dt_s
        T[:3, :3] = rotvec_to_matrix(w * dt_s) @ T[:3, :3]
        q = arm.ik(T, arm.q)
        if q is None:
            raise MotionError(f"{self.name}: no inverse kinematics solution")
        arm.q = q
        self._T = T
        return self.stop_at_zero and float(np.linalg.norm(self._twist)) == 0.0


@dataclass
class SpeedJ:
    """speedj (and stopj with ``stop_at_zero``): ramp joint velocities to a target with ``accel``."""

    qd_target: FloatArray
    accel: float
    qd_start: FloatArray
    name: str = "speedj"
    stop_at_zero: bool = False
    _qd: FloatArray | None = None

    def step(self, arm: Arm, dt_s: float) -> bool:
        if self._qd is None:
            self._qd = self.qd_start.copy()
        # the joints cannot turn faster than their speed limits, whatever speedj asks for
        target = np.clip(self.qd_target, -JOINT_SPEED_LIMIT_RAD_S, JOINT_SPEED_LIMIT_RAD_S)
        self._qd = _ramp(self._qd, target, self.accel * dt_s)
        arm.q = arm.q + self._qd * dt_s
        return self.stop_at_zero and float(np.linalg.norm(self._qd)) == 0.0
