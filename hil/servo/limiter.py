"""Speed and acceleration limiting of a streamed pose command (the servo loop's, and a phase's
own stream in the simulated, in-process loop): the translation of a pivot point fixed to the tool
(the entry, below the guide) and the rotation about it, with the TCP's own speed and acceleration
capped."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hil.errors import GeometryError
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

FloatArray = NDArray[np.float64]

#: The share of the TCP's speed and acceleration limits the rotation alone may take at the
#: pivot's lever arm (the rest is the pivot's own translation's).
_LEVER_SHARE = 0.9
#: Relative tolerance of the TCP's limits (rounding).
_ROUNDING = 1e-9

#: A :class:`RateLimiter`'s arguments: max speed mm/s, max acceleration mm/s², max angular speed
#: rad/s, max angular acceleration rad/s², the pivot in the TCP frame (mm).
LimiterArgs = tuple[float, float, float, float, tuple[float, float, float]]


@dataclass
class RateLimiter:
    """Speed/acceleration limiting of a streamed pose command, from rest at the actual pose.

    The motion is split into the translation of a *pivot* point fixed to the tool
    (``pivot_tcp_mm``, TCP frame: the entry, ``standoff_mm`` down the guide's axis, so that the
    axis keeps passing through the entry while a fast turn is clipped) and the rotation about it.
    Each is limited in speed and acceleration, the same way: the velocity wanted to reach the
    target in one step, capped by the speed limit and by the stopping distance (angle)
    ``sqrt(2 a d)`` so it does not overshoot, then changed by at most ``a dt``. The TCP's own
    velocity (the pivot's, plus the turn's at the pivot's lever arm) is held to the same
    translation limits, so that the pivot stands still in a pure turn as the TCP swings round it:

    - the rotation's limits are lowered to what the lever arm allows (at most 0.9 of the TCP's
      speed and acceleration limits: ``w <= 0.9 v_max / |pivot|``, ``a <= 0.9 a_max / |pivot|``);
    - the pivot's speed limit is what the turn leaves of the TCP's, and its change is measured
      from the velocity it would have were the TCP's unchanged (so the TCP's acceleration is the
      pivot's);
    - the TCP's velocity is then projected onto its limits (acceleration, then speed): a no-op
      but for rounding, unless ``speed_scale`` fell (the resume ramp) - only then does the pivot
      drift.

    With the pivot at the TCP (the default, ``(0, 0, 0)``) the TCP's translation and the rotation
    are limited separately, as before issue 41.

    Without an angular acceleration limit (``inf``) the rotation goes at the angular speed limit
    from the first step, and noise in the target's attitude reaches the arm as bursts of up to
    that speed (a UR then needs ``w / a`` to stop them).

    ``speed_scale`` (0..1] scales both speed limits (the resume ramp). ``velocity_mm_s`` is the
    TCP's velocity (what the servo loop's step check compares with), ``angular_velocity_rad_s``
    the rotation's (robot base frame).

    Raises:
        GeometryError: ``pivot_tcp_mm`` not 3 finite values.
    """

    max_speed_mm_s: float
    max_accel_mm_s2: float
    max_angular_speed_rad_s: float
    max_angular_accel_rad_s2: float = math.inf
    pivot_tcp_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    command: RigidTransform | None = None
    velocity_mm_s: FloatArray | None = None
    angular_velocity_rad_s: FloatArray | None = None   # robot base frame
    _pivot: FloatArray = field(init=False, repr=False)
    _lever_mm: float = field(init=False, repr=False, default=0.0)
    _lever_w_rad_s: float = field(init=False, repr=False, default=math.inf)
    _lever_a_rad_s2: float = field(init=False, repr=False, default=math.inf)

    def __post_init__(self) -> None:
        pivot = np.asarray(self.pivot_tcp_mm, dtype=np.float64)
        if pivot.shape != (3,) or not np.isfinite(pivot).all():
            raise GeometryError(f"pivot_tcp_mm must be 3 finite values, got {self.pivot_tcp_mm!r}")
        self._pivot = pivot
        # the rotation alone never asks the TCP, at the pivot's lever arm, for more than its limits
        lever_mm = self._lever_mm = float(np.linalg.norm(pivot))
        self._lever_w_rad_s = _LEVER_SHARE * self.max_speed_mm_s / lever_mm if lever_mm > 0 else math.inf
        self._lever_a_rad_s2 = _LEVER_SHARE * self.max_accel_mm_s2 / lever_mm if lever_mm > 0 else math.inf

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
        cmd, v_prev, w_prev = self.command, self.velocity_mm_s, self.angular_velocity_rad_s
        if cmd is None or v_prev is None or w_prev is None:
            raise GeometryError("rate limiter not reset to the actual pose")
        if not dt_s > 0:
            raise GeometryError(f"dt_s must be > 0, got {dt_s}")
        scale = min(max(speed_scale, 0.0), 1.0)
        v_max = self.max_speed_mm_s * scale
        # the rotation still to go, as a rotation vector in the base frame
        e_rot = cmd.R @ (cmd.inverse() @ desired).as_rotvec()
        w_max = min(self.max_angular_speed_rad_s, self._lever_w_rad_s) * scale
        a_w_max = min(self.max_angular_accel_rad_s2, self._lever_a_rad_s2)
        w = _limited_velocity(e_rot, w_prev, dt_s, w_max, a_w_max, 0.999)
        R_step = rotvec_to_matrix(w * dt_s)
        if self._lever_mm == 0.0:   # the pivot at the TCP: the translation alone, as before issue 41
            v = _limited_velocity(desired.t - cmd.t, v_prev, dt_s, v_max, self.max_accel_mm_s2, 1.0)
        else:
            v = self._pivot_velocity(desired, cmd, R_step, v_prev, v_max, dt_s)
        # a product of rotations and a fresh translation, finite (the limits bound both):
        # valid by construction, so the checked constructor's cost is skipped
        self.command = RigidTransform._composed(R_step @ cmd.R, cmd.t + v * dt_s)
        self.velocity_mm_s = v
        self.angular_velocity_rad_s = w
        return self.command

    def _pivot_velocity(self, desired: RigidTransform, cmd: RigidTransform, R_step: FloatArray,
                        v_prev: FloatArray, v_max: float, dt_s: float) -> FloatArray:
        """The TCP's velocity (mm/s, base frame) for this step's turn ``R_step`` about the pivot
        and the pivot's own limited translation towards where ``desired`` puts it (class doc)."""
        r = cmd.R @ self._pivot   # the pivot from the TCP, base frame
        # the TCP's velocity that turns the tool about the pivot, the pivot standing still
        turn_v = (r - R_step @ r) / dt_s
        # the pivot's velocity, from what it would be were the TCP's unchanged, within what the
        # turn leaves of the speed limit
        v_p = _limited_velocity(desired.t + desired.R @ self._pivot - (cmd.t + r), v_prev - turn_v, dt_s,
                                max(v_max - _norm(turn_v), 0.0), self.max_accel_mm_s2, 1.0)
        return _within_limits(v_p + turn_v, v_prev, v_max, self.max_accel_mm_s2 * dt_s * 0.999)


def _within_limits(v: FloatArray, v_prev: FloatArray, v_max: float, dv_max: float) -> FloatArray:
    """``v`` changed from ``v_prev`` by at most ``dv_max``, then no faster than ``v_max`` (both
    projections onto a ball: with ``v_prev`` within the speed limit the second keeps the first)."""
    dv = v - v_prev
    dv_n = _norm(dv)
    if dv_n > dv_max * (1.0 + _ROUNDING):
        v = v_prev + dv * (dv_max / dv_n)
    sp = _norm(v)
    if sp > v_max * (1.0 + _ROUNDING):
        v = v * (v_max / sp)
    return v


def _norm(v: FloatArray) -> float:
    return math.sqrt(float(v @ v))


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
