"""A straight-line move as a stream of servo setpoints: what a UR's ``moveL`` does inside its
controller, done here by the servo loop so that APPROACH and RETRACT run under the same period,
the same merged limit check and the same following supervision as tracking.

The path is the straight line from the start TCP pose to the target, and the rotation turns
about one fixed axis (base frame) at the same time, so position and attitude arrive together:

    p(s) = p0 + s (p1 - p0),     R(s) = exp(s [e]x) R0,     e = R0 log(R0^T R1)  (base frame),

with the path fraction ``s(t)`` a trapezoidal profile (constant acceleration, cruise, constant
deceleration; a triangle when the move is too short to reach cruise). The profile's peak rate
and acceleration are the largest that keep the TCP within all four limits at once:

    s_dot_max  = min(v / d, w / theta),      s_ddot_max = min(a / d, alpha / theta),

where ``d`` is the distance (mm) and ``theta`` the rotation angle (rad); a limit whose distance
or angle is zero does not bind. Sampled at the loop's period from t = 0 (the start, at rest),
consecutive samples never imply more than those speeds and (second difference) accelerations:
the merged step check (:mod:`hil.safety.servo_check`) passes a move whose speed and
acceleration the safety layer accepted.

Time is the loop's own count of periods times the period (never the wall clock), so a period
the OS delays makes the move take longer rather than jump.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from hil.errors import GeometryError
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

FloatArray = NDArray[np.float64]

#: below this distance (mm) or angle (rad) a move has no translation (rotation) part
_EPS = 1e-9


class LinearMove:
    """One straight-line move from ``start`` (at rest) to ``target`` (module doc).

    Args:
        start, target: TCP poses ``T_robot_from_tcp``, mm.
        speed_mm_s, accel_mm_s2: the TCP's linear speed and acceleration limits (> 0).
        angular_speed_rad_s, angular_accel_rad_s2: its angular speed and acceleration limits (> 0).
        The speeds must be finite; an acceleration may be ``inf`` (it then does not bind).

    Raises:
        GeometryError: a limit not > 0 (or a speed not finite), or a pose not finite.
    """

    def __init__(self, start: RigidTransform, target: RigidTransform, *, speed_mm_s: float,
                 accel_mm_s2: float, angular_speed_rad_s: float, angular_accel_rad_s2: float) -> None:
        for name, value in (("speed_mm_s", speed_mm_s), ("angular_speed_rad_s", angular_speed_rad_s)):
            if not (math.isfinite(value) and value > 0):
                raise GeometryError(f"move {name} must be finite and > 0, got {value}")
        for name, value in (("accel_mm_s2", accel_mm_s2), ("angular_accel_rad_s2", angular_accel_rad_s2)):
            if not value > 0:   # inf: that acceleration does not bind
                raise GeometryError(f"move {name} must be > 0, got {value}")
        if not (np.all(np.isfinite(start.t)) and np.all(np.isfinite(target.t))):
            raise GeometryError("move start and target must be finite")
        self.start, self.target = start, target
        self.delta_mm: FloatArray = target.t - start.t
        self.distance_mm = float(np.linalg.norm(self.delta_mm))
        #: the rotation still to go, as a rotation vector in the base frame, rad
        self.rotvec_rad: FloatArray = start.R @ (start.inverse() @ target).as_rotvec()
        self.angle_rad = float(np.linalg.norm(self.rotvec_rad))
        rate, acc = math.inf, math.inf   # of the path fraction, 1/s and 1/s^2
        if self.distance_mm > _EPS:
            rate, acc = min(rate, speed_mm_s / self.distance_mm), min(acc, accel_mm_s2 / self.distance_mm)
        if self.angle_rad > _EPS:
            rate = min(rate, angular_speed_rad_s / self.angle_rad)
            acc = min(acc, angular_accel_rad_s2 / self.angle_rad)
        if math.isinf(rate):   # nothing to do
            self.duration_s, self.t_accel_s, self.peak_rate, self.accel = 0.0, 0.0, 0.0, 0.0
            return
        t_accel = rate / acc if math.isfinite(acc) else 0.0
        if rate * t_accel >= 1.0:   # a triangle: the peak is reached half way
            t_accel = math.sqrt(1.0 / acc)
            rate = acc * t_accel
            duration = 2.0 * t_accel
        else:
            duration = 1.0 / rate + t_accel
        self.duration_s, self.t_accel_s, self.peak_rate, self.accel = duration, t_accel, rate, acc

    def fraction(self, t_s: float) -> tuple[float, float]:
        """The path fraction ``s`` in [0, 1] and its rate ``ds/dt`` (1/s) at ``t_s`` after the
        start (before the start: 0; after the end: 1, at rest)."""
        T, ta, a = self.duration_s, self.t_accel_s, self.accel
        if t_s <= 0.0 or T <= 0.0:
            return (0.0 if T > 0.0 else 1.0), 0.0
        if t_s >= T:
            return 1.0, 0.0
        if t_s < ta:
            return 0.5 * a * t_s * t_s, a * t_s
        if t_s > T - ta:
            r = T - t_s
            return 1.0 - 0.5 * a * r * r, a * r
        # (0.5 a ta^2 written as 0.5 rate ta: an infinite acceleration has ta = 0)
        return 0.5 * self.peak_rate * ta + self.peak_rate * (t_s - ta), self.peak_rate

    def pose_at(self, t_s: float) -> tuple[RigidTransform, FloatArray, FloatArray]:
        """The commanded TCP pose at ``t_s`` after the start, with its linear (mm/s) and angular
        (rad/s) velocity, both in the robot base frame."""
        s, rate = self.fraction(t_s)
        if s >= 1.0:
            return self.target, np.zeros(3), np.zeros(3)
        t = self.start.t + s * self.delta_mm
        R = rotvec_to_matrix(s * self.rotvec_rad) @ self.start.R if self.angle_rad > _EPS else self.start.R
        return RigidTransform(R, t), rate * self.delta_mm, rate * self.rotvec_rad

    def done(self, t_s: float) -> bool:
        """Whether the profile has ended at ``t_s`` (the command is the target, at rest)."""
        return t_s >= self.duration_s
