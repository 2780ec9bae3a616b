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

    ``speed_scale`` (0..1] scales the speed limit (the resume ramp).
    """

    max_speed_mm_s: float
    max_accel_mm_s2: float
    max_angular_speed_rad_s: float
    command: RigidTransform | None = None
    velocity_mm_s: FloatArray | None = None

    def reset(self, actual: RigidTransform) -> None:
        """Restart from the actual pose, at rest (after any stop, pause or fault)."""
        self.command = actual
        self.velocity_mm_s = np.zeros(3)

    def step(self, desired: RigidTransform, dt_s: float, speed_scale: float = 1.0) -> RigidTransform:
        """The next command towards ``desired`` after ``dt_s``.

        Translation: the velocity wanted to reach the target in one step, capped by the speed
        limit and by the stopping distance ``sqrt(2 a d)`` (so it does not overshoot), then
        changed by at most ``a dt``. Rotation: at most ``w dt`` towards the desired attitude.

        Raises:
            GeometryError: not reset yet, or dt_s <= 0.
        """
        if self.command is None or self.velocity_mm_s is None:
            raise GeometryError("rate limiter not reset to the actual pose")
        if not dt_s > 0:
            raise GeometryError(f"dt_s must be > 0, got {dt_s}")
        vmax = self.max_speed_mm_s * min(max(speed_scale, 0.0), 1.0)
        e = desired.t - self.command.t
        d = float(np.linalg.norm(e))
        v_prev = self.velocity_mm_s
        if d > 1e-12:
            # discrete stopping-distance cap: after travelling v*dt this step, braking at a must
            # still stop in time, v dt + v^2 / (2 a) <= d  ->  v <= a (sqrt(dt^2 + 2 d / a) - dt)
            a = self.max_accel_mm_s2
            v_stop = a * (math.sqrt(dt_s * dt_s + 2.0 * d / a) - dt_s)
            v_cap = min(vmax, v_stop, d / dt_s)
            v_want = e / d * v_cap
        else:
            v_want = np.zeros(3)
        dv = v_want - v_prev
        dv_n = float(np.linalg.norm(dv))
        dv_max = self.max_accel_mm_s2 * dt_s * 0.999
        if dv_n > dv_max:
            dv = dv * (dv_max / dv_n)
        v = v_prev + dv
        sp = float(np.linalg.norm(v))
        if sp > vmax:
            v = v * (vmax / sp)
        t_new = self.command.t + v * dt_s
        rel = self.command.inverse() @ desired
        ang = rel.rotation_angle_rad()
        amax = self.max_angular_speed_rad_s * dt_s * 0.999
        scale = amax / ang if ang > amax else 1.0
        R_new = self.command.R @ rotvec_to_matrix(rel.as_rotvec() * scale)
        self.command = RigidTransform(R_new, t_new)
        self.velocity_mm_s = v
        return self.command
