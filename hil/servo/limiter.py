"""Speed and acceleration limiting of a streamed pose command (the servo loop's, and a phase's
own stream in the simulated, in-process loop). Translation with a stopping-distance cap, rotation
at a bounded angular speed."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil.errors import GeometryError
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

FloatArray = NDArray[np.float64]


@dataclass
class RateLimiter:
    """Speed/acceleration limiting of a streamed pose command, from rest at the actual pose.

    Translation and rotation are each limited in speed and acceleration, the same way: the
    velocity wanted to reach the target in one step, capped by the speed limit and by the
    stopping distance (angle) ``sqrt(2 a d)`` so it does not overshoot, then changed by at most
    ``a dt``. Without an angular acceleration limit (``inf``) the rotation goes at the angular
    speed limit from the first step, and noise in the target's attitude reaches the arm as
    bursts of up to that speed (a UR then needs ``w / a`` to stop them).

    ``speed_scale`` (0..1] scales both speed limits (the resume ramp).
    """

    max_speed_mm_s: float
    max_accel_mm_s2: float
    max_angular_speed_rad_s: float
    max_angular_accel_rad_s2: float = math.inf
    command: RigidTransform | None = None
    velocity_mm_s: FloatArray | None = None
    angular_velocity_rad_s: FloatArray | None = None   # robot base frame

    def reset(self, actual: RigidTransform) -> None:
        """Restart from the actual pose, at rest (after any stop, pause or fault)."""
        self.command = actual
        self.velocity_mm_s = np.zeros(3)
        self.angular_velocity_rad_s = np.zeros(3)

    def step(self, desired: RigidTransform, dt_s: float, speed_scale: float = 1.0) -> RigidTransform:
        """The next command towards ``desired`` after ``dt_s`` (class doc).

        Raises:
            GeometryError: not reset yet, or dt_s <= 0.
        """
        if self.command is None or self.velocity_mm_s is None or self.angular_velocity_rad_s is None:
            raise GeometryError("rate limiter not reset to the actual pose")
        if not dt_s > 0:
            raise GeometryError(f"dt_s must be > 0, got {dt_s}")
        scale = min(max(speed_scale, 0.0), 1.0)
        v = _limited_velocity(desired.t - self.command.t, self.velocity_mm_s, dt_s,
                              self.max_speed_mm_s * scale, self.max_accel_mm_s2, 1.0)
        t_new = self.command.t + v * dt_s
        # the rotation still to go, as a rotation vector in the base frame
        e_rot = self.command.R @ (self.command.inverse() @ desired).as_rotvec()
        w = _limited_velocity(e_rot, self.angular_velocity_rad_s, dt_s,
                              self.max_angular_speed_rad_s * scale, self.max_angular_accel_rad_s2, 0.999)
        R_new = rotvec_to_matrix(w * dt_s) @ self.command.R
        self.command = RigidTransform(R_new, t_new)
        self.velocity_mm_s = v
        self.angular_velocity_rad_s = w
        return self.command


def _limited_velocity(e: FloatArray, v_prev: FloatArray, dt_s: float, v_max: float, a_max: float,
                      speed_margin: float) -> FloatArray:
    """The velocity for one step towards the offset ``e``: wanted to reach it in the step, capped
    by ``v_max`` (times ``speed_margin``) and by the discrete stopping distance (after moving
    ``v dt`` this step, braking at ``a_max`` must still stop in time: ``v dt + v^2 / (2 a) <= d``,
    so ``v <= a (sqrt(dt^2 + 2 d / a) - dt)``), changed by at most ``a_max dt`` (x 0.999).
    ``a_max`` may be ``inf`` (no acceleration limit)."""
    d = float(np.linalg.norm(e))
    v_cap_max = v_max * speed_margin
    if d > 1e-12:
        v_cap = min(v_cap_max, d / dt_s)
        if math.isfinite(a_max):
            v_cap = min(v_cap, a_max * (math.sqrt(dt_s * dt_s + 2.0 * d / a_max) - dt_s))
        v_want = e / d * v_cap
    else:
        v_want = np.zeros(3)
    if math.isfinite(a_max):
        dv = v_want - v_prev
        dv_n = float(np.linalg.norm(dv))
        dv_max = a_max * dt_s * 0.999
        if dv_n > dv_max:
            dv = dv * (dv_max / dv_n)
        v = v_prev + dv
    else:
        v = v_want
    sp = float(np.linalg.norm(v))
    if sp > v_cap_max:
        v = v * (v_cap_max / sp)
    out: FloatArray = v
    return out
