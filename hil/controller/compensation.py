"""COMPENSATE: follow the rigid change of the patient markers (seed 000 section 3).

The change reference -> live, ``T_live_from_ref`` (optical frame), is solved from the matched
marker sets with Horn's quaternion method (seed 000 eqs 17-21) and applied to the planned path:
the desired guide pose is ``T_live_from_ref @ T_optical_from_guide_planned``. The estimate is
smoothed by an alpha-beta filter (position and velocity of the 6 pose parameters), predicted
forward over the measured latency plus the robot's actuation lag (capped), bounded (beyond the
bound the controller pauses and asks the operator), and the command is rate-limited in speed and
acceleration (a stopping-distance limit keeps it from overshooting).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil.controller.config import CompensationConfig
from hil.errors import GeometryError
from hil.geometry.registration import Registration, register_horn
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

FloatArray = NDArray[np.float64]


def rigid_change(reference_mm: FloatArray, live_mm: FloatArray) -> Registration | None:
    """``T_live_from_ref`` from corresponding marker rows (NaN rows = not seen), seed 000 eqs
    17-21 (Horn). Returns None with fewer than 3 usable, non-degenerate pairs."""
    ok = np.all(np.isfinite(reference_mm), axis=1) & np.all(np.isfinite(live_mm), axis=1)
    if int(ok.sum()) < 3:
        return None
    try:
        return register_horn(live_mm[ok], reference_mm[ok])
    except GeometryError:
        return None


def _to_vec(T: RigidTransform) -> FloatArray:
    return np.concatenate([T.t, T.as_rotvec()])


def _from_vec(x: FloatArray) -> RigidTransform:
    return RigidTransform(rotvec_to_matrix(x[3:]), x[:3])


def correction_out_of_bounds(T_change: RigidTransform, cfg: CompensationConfig) -> str | None:
    """None when the change is within the correction bounds, else the reason.

    ``T_change`` must be expressed about the point that matters (the controller uses the planned
    entry), so that its translation is that point's displacement.
    """
    t = T_change.translation_norm()
    a = math.degrees(T_change.rotation_angle_rad())
    if t > cfg.max_correction_mm:
        return f"patient moved {t:.1f} mm from the registered state (bound {cfg.max_correction_mm} mm)"
    if a > cfg.max_correction_deg:
        return f"patient turned {a:.1f} deg from the registered state (bound {cfg.max_correction_deg} deg)"
    return None


class MotionFilter:
    """Alpha-beta filter on ``T_live_from_ref`` as a 6-vector (t mm, rotation vector rad).

    The rotation vector is additive for the small rotations compensated here (bounded by
    ``max_correction_deg``).
    """

    def __init__(self, alpha: float, beta: float) -> None:
        self.alpha = alpha
        self.beta = beta
        self._x: FloatArray | None = None
        self._v = np.zeros(6)
        self._t_ns = 0

    @property
    def initialised(self) -> bool:
        return self._x is not None

    def reset(self) -> None:
        self._x = None
        self._v = np.zeros(6)

    def update(self, T_meas: RigidTransform, t_ns: int) -> None:
        """Feed the measured change at frame time ``t_ns`` (must not go back in time)."""
        z = _to_vec(T_meas)
        if self._x is None:
            self._x, self._v, self._t_ns = z, np.zeros(6), t_ns
            return
        dt = (t_ns - self._t_ns) * 1e-9
        if dt <= 0:
            return
        x_pred = self._x + self._v * dt
        r = z - x_pred
        self._x = x_pred + self.alpha * r
        self._v = self._v + (self.beta / dt) * r
        self._t_ns = t_ns

    def estimate(self, t_ns: int | None = None, max_horizon_s: float = 0.0) -> RigidTransform:
        """The filtered change, extrapolated to ``t_ns`` (at most ``max_horizon_s`` ahead of the
        last sample; never backwards).

        Raises:
            GeometryError: nothing fed yet.
        """
        if self._x is None:
            raise GeometryError("motion filter has no sample yet")
        h = 0.0 if t_ns is None else min(max((t_ns - self._t_ns) * 1e-9, 0.0), max_horizon_s)
        return _from_vec(self._x + self._v * h)

    @property
    def speed_mm_s(self) -> float:
        return float(np.linalg.norm(self._v[:3]))


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


def interpolate_pose(a: RigidTransform, b: RigidTransform, f: float) -> RigidTransform:
    """Pose ``f`` of the way from ``a`` to ``b`` (linear in translation, geodesic in rotation)."""
    rel = a.inverse() @ b
    R = a.R @ rotvec_to_matrix(rel.as_rotvec() * f)
    return RigidTransform(R, a.t + f * (b.t - a.t))
