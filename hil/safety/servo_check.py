"""The one limit check of a servo step, shared by the safety layer (a stream from the control
thread) and the servo loop (hil/servo): the workspace box, the implied TCP speed, angular speed and
acceleration of a step from the previous target, all against one :class:`MotionLimits` with one
tolerance.

Returns the refusal as ``(check, detail)`` instead of raising, so the servo loop can refuse
without building an exception on its hot path; :class:`~hil.safety.layer.SafetyLayer` turns it
into a :class:`~hil.safety.layer.SafetyViolationError`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.robot import MotionLimits

FloatArray = NDArray[np.float64]

#: Relative tolerance on the speed, angular speed and acceleration limits (rounding of a step
#: computed to exactly the limit, e.g. by the rate limiter, must not be refused).
LIMIT_TOLERANCE = 1e-6


def box_violation(limits: MotionLimits, t_mm: FloatArray) -> tuple[str, str] | None:
    """``("workspace", detail)`` when ``t_mm`` (robot frame) is not finite or outside the box."""
    lo, hi = limits.workspace_min_mm, limits.workspace_max_mm
    x, y, z = float(t_mm[0]), float(t_mm[1]), float(t_mm[2])
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)) or not (
            lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]):
        return ("workspace", f"target {[round(x, 3), round(y, 3), round(z, 3)]} mm outside box "
                             f"{list(lo)}..{list(hi)} mm")
    return None


def servo_step_violation(limits: MotionLimits, R_prev: FloatArray, t_prev_mm: FloatArray,
                         v_prev_mm_s: FloatArray, R_next: FloatArray, t_next_mm: FloatArray,
                         period_s: float) -> tuple[str, str] | None:
    """The merged check of one servo step from ``(R_prev, t_prev)`` (the previous target, or the
    actual pose for the first) moving at ``v_prev`` to ``(R_next, t_next)`` within ``period_s``.

    Returns None when allowed, else ``(check, detail)`` with check one of ``period``,
    ``workspace``, ``speed``, ``angular_speed``, ``acceleration``.
    """
    if not (math.isfinite(period_s) and period_s > 0):
        return ("period", f"servo period {period_s} s must be > 0")
    box = box_violation(limits, t_next_mm)
    if box is not None:
        return box
    tol = 1.0 + LIMIT_TOLERANCE
    dx = float(t_next_mm[0] - t_prev_mm[0])
    dy = float(t_next_mm[1] - t_prev_mm[1])
    dz = float(t_next_mm[2] - t_prev_mm[2])
    speed = math.sqrt(dx * dx + dy * dy + dz * dz) / period_s
    if speed > limits.max_speed_mm_s * tol:
        return ("speed", f"step implies {speed:.1f} mm/s > {limits.max_speed_mm_s} mm/s")
    # rotation angle of R_prev^T R_next from its trace
    tr = float(np.sum(R_prev * R_next))
    angle = math.acos(min(1.0, max(-1.0, (tr - 1.0) / 2.0)))
    w = angle / period_s
    if w > limits.max_angular_speed_rad_s * tol:
        return ("angular_speed", f"step implies {w:.3f} rad/s > {limits.max_angular_speed_rad_s} rad/s")
    ax = (dx / period_s - float(v_prev_mm_s[0])) / period_s
    ay = (dy / period_s - float(v_prev_mm_s[1])) / period_s
    az = (dz / period_s - float(v_prev_mm_s[2])) / period_s
    accel = math.sqrt(ax * ax + ay * ay + az * az)
    if accel > limits.max_accel_mm_s2 * tol:
        return ("acceleration", f"step implies {accel:.0f} mm/s^2 > {limits.max_accel_mm_s2} mm/s^2")
    return None
