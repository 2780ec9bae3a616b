"""Universal Robots UR3 / UR3e kinematics: DH tables, forward and analytic inverse kinematics.

Standard (distal) Denavit-Hartenberg convention, ``T_{i-1,i} = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``,
with Universal Robots' published parameters (the table in ``reference/ur-rtde.md``). The tables are in
metres, as UR publishes them; every function here takes and returns millimetres (the core's unit).
Poses are ``T_base_from_tool0``: the tool flange (``tool0``, no TCP offset) in the robot base frame.

The inverse is the closed-form solution for the UR's geometry (three parallel middle axes, a1 = a4 =
a5 = a6 = 0, d2 = d3 = 0), as in K. P. Hawkins, "Analytic Inverse Kinematics for the Universal Robots
UR-5/UR-10 Arms" (Georgia Tech, 2013): shoulder (2 branches) x wrist (2) x elbow (2) = up to 8 solutions.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import GeometryError
from hil.geometry import native
from hil.geometry.transform import RigidTransform, matrix_to_rotvec

FloatArray = NDArray[np.float64]

_HALF_PI = math.pi / 2.0
_TWO_PI = 2.0 * math.pi
# A solution is accepted only when its forward kinematics reproduces the asked pose this well.
_IK_CHECK_MM = 1e-6
_IK_CHECK_RAD = 1e-7
# Rounding slack for acos/asin arguments at the workspace boundary.
_TRIG_SLACK = 1e-9
# |sin q5| below this is the wrist singularity: q6 is then free.
_WRIST_SINGULAR = 1e-10


@dataclass(frozen=True)
class DHParams:
    """Standard DH parameters of a 6-axis UR arm (metres, radians), index i = joint i+1.

    Attributes:
        name: model name (``ur3``, ``ur3e``).
        d_m, a_m, alpha_rad: the DH columns.
    """

    name: str
    d_m: tuple[float, float, float, float, float, float]
    a_m: tuple[float, float, float, float, float, float]
    alpha_rad: tuple[float, float, float, float, float, float]

    @property
    def d_mm(self) -> FloatArray:
        return np.asarray(self.d_m, dtype=np.float64) * 1000.0

    @property
    def a_mm(self) -> FloatArray:
        return np.asarray(self.a_m, dtype=np.float64) * 1000.0


_UR_ALPHA = (_HALF_PI, 0.0, 0.0, _HALF_PI, -_HALF_PI, 0.0)

UR_DH: dict[str, DHParams] = {
    "ur3": DHParams(
        name="ur3",
        d_m=(0.1519, 0.0, 0.0, 0.11235, 0.08535, 0.0819),
        a_m=(0.0, -0.24365, -0.21325, 0.0, 0.0, 0.0),
        alpha_rad=_UR_ALPHA,
    ),
    "ur3e": DHParams(
        name="ur3e",
        d_m=(0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921),
        a_m=(0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0),
        alpha_rad=_UR_ALPHA,
    ),
}

# UR3 (CB3) software joint limits: every joint +-360 deg (wrist 3 is mechanically unlimited on the
# UR3, but the controller's default joint limits still bound it to +-360 deg). Row = joint, [min, max].
UR3_JOINT_LIMITS_RAD: FloatArray = np.array([[-_TWO_PI, _TWO_PI]] * 6, dtype=np.float64)
UR3_JOINT_LIMITS_RAD.setflags(write=False)

# Working radius of the UR3 from the base axis, as Universal Robots specifies it.
UR3_REACH_MM = 500.0


def dh_params(model: str) -> DHParams:
    """The DH table of ``model`` (``ur3`` or ``ur3e``). Raises GeometryError for another name."""
    try:
        return UR_DH[model]
    except KeyError:
        raise GeometryError(f"unknown UR model {model!r}; known: {sorted(UR_DH)}") from None


def _as_q(q_rad: ArrayLike, name: str = "q_rad") -> FloatArray:
    q = np.asarray(q_rad, dtype=np.float64).reshape(-1)
    if q.shape != (6,) or not np.isfinite(q).all():
        raise GeometryError(f"{name} must be 6 finite joint angles (rad), got {q_rad!r}")
    return q


def _dh_matrix(theta: float, d: float, a: float, alpha: float) -> FloatArray:
    ct, st = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def ur_joint_frames(q_rad: ArrayLike, model: str = "ur3") -> list[FloatArray]:
    """The 4x4 matrices ``T_base_from_link_i`` for i = 1..6 (mm), e.g. for drawing or collision checks.

    The six DH matrices are built in one array from plain floats and the model's cached constants
    (the simulated arm evaluates this several times per servo period, in the real-time loop).
    The latest results are cached by the joint angles' exact bits (a servo period asks again for
    the pose the previous one ended at): the matrices are read-only, shared between callers.

    Raises:
        GeometryError: ``q_rad`` is not 6 finite values, or the model is unknown.
    """
    q = _as_q(q_rad)
    return list(_joint_frames(q.tobytes(), model))


@functools.lru_cache(maxsize=16)
def _joint_frames(q_bits: bytes, model: str) -> tuple[FloatArray, ...]:
    """:func:`ur_joint_frames` of the angles whose float64 bytes are ``q_bits`` (read-only)."""
    rows = []
    for theta, (d, a, ca, sa) in zip(np.frombuffer(q_bits).tolist(), _dh_columns(model), strict=True):
        ct, st = math.cos(theta), math.sin(theta)
        rows.append((ct, -st * ca, st * sa, a * ct, st, ct * ca, -ct * sa, a * st,
                     0.0, sa, ca, d, 0.0, 0.0, 0.0, 1.0))
    A = np.array(rows).reshape(6, 4, 4)
    frames = [A[0]]
    for i in range(1, 6):
        frames.append(frames[-1] @ A[i])
    for f in frames:
        f.setflags(write=False)
    return tuple(frames)


@functools.cache
def _dh_columns(model: str) -> tuple[tuple[float, float, float, float], ...]:
    """Per joint: ``d`` (mm), ``a`` (mm), ``cos(alpha)``, ``sin(alpha)`` of the model."""
    p = dh_params(model)
    return tuple((float(p.d_mm[i]), float(p.a_mm[i]), math.cos(p.alpha_rad[i]), math.sin(p.alpha_rad[i]))
                 for i in range(6))


def ur_forward(q_rad: ArrayLike, model: str = "ur3") -> RigidTransform:
    """Forward kinematics: ``T_base_from_tool0`` (mm) for joint angles ``q_rad`` (6, rad).

    Raises:
        GeometryError: ``q_rad`` is not 6 finite values, or the model is unknown.
    """
    T = ur_joint_frames(q_rad, model)[-1]
    return RigidTransform(T[:3, :3], T[:3, 3])


@functools.cache
def _dh_array(model: str) -> FloatArray:
    """:func:`_dh_columns` as a read-only (6, 4) float64 array (the compiled Newton step's table)."""
    a = np.array(_dh_columns(model), dtype=np.float64)
    a.setflags(write=False)
    return a


def ur_newton_ik(T_base_from_tool0: RigidTransform, q_seed_rad: FloatArray, model: str = "ur3", *,
                 iterations: int, tol_mm: float, tol_rad: float, min_det_mm3: float,
                 max_jump_rad: float) -> FloatArray | None:
    """Inverse kinematics for a small step: Newton steps with the geometric Jacobian from
    ``q_seed_rad`` (the same branch as the seed), for the flange pose ``T_base_from_tool0`` (mm).

    Returns the joint angles (6, rad, a fresh array) once the position error is below ``tol_mm``
    and the orientation error (rotation vector) below ``tol_rad``, or None when it does not get
    there cleanly: ``iterations`` ran out, ``|det J|`` fell below ``min_det_mm3`` (near a
    singularity), or a joint ended more than ``max_jump_rad`` from the seed (a flip). Callers fall
    back to :func:`ur_inverse` on None. Runs compiled (``hil/geometry/_native.c``,
    :mod:`hil.geometry.native`) when built and selected, else :func:`ur_newton_ik_numpy`; the two
    agree to rounding (tests/kinematics/test_newton.py). Never blocks.

    Raises:
        GeometryError: ``q_seed_rad`` is not 6 finite values, or the model is unknown.
    """
    q_seed = _as_q(q_seed_rad, "q_seed_rad")
    k = native.active()
    if k is not None:
        q = np.empty(6)
        status = k.ur_newton(_dh_array(model), T_base_from_tool0.R, T_base_from_tool0.t, q_seed, iterations,
                             tol_mm, tol_rad, min_det_mm3, max_jump_rad, q)
        if status == 0:
            return q
        if status == 1:
            return None
    return ur_newton_ik_numpy(T_base_from_tool0, q_seed, model, iterations=iterations, tol_mm=tol_mm,
                              tol_rad=tol_rad, min_det_mm3=min_det_mm3, max_jump_rad=max_jump_rad)


def ur_newton_ik_numpy(T_base_from_tool0: RigidTransform, q_seed_rad: FloatArray, model: str = "ur3", *,
                       iterations: int, tol_mm: float, tol_rad: float, min_det_mm3: float,
                       max_jump_rad: float) -> FloatArray | None:
    """:func:`ur_newton_ik` in numpy (the reference the compiled code is tested against)."""
    q_seed = _as_q(q_seed_rad, "q_seed_rad")
    q = q_seed.copy()
    for _ in range(iterations):
        frames = ur_joint_frames(q, model)
        T_e = frames[-1]
        dp = T_base_from_tool0.t - T_e[:3, 3]
        dw = matrix_to_rotvec(T_base_from_tool0.R @ T_e[:3, :3].T)
        if float(np.linalg.norm(dp)) < tol_mm and float(np.linalg.norm(dw)) < tol_rad:
            if float(np.max(np.abs(q - q_seed))) > max_jump_rad:
                return None
            return q
        axes = np.array([(0.0, 0.0, 1.0)] + [f[:3, 2] for f in frames[:5]])      # (6, 3)
        origins = np.array([(0.0, 0.0, 0.0)] + [f[:3, 3] for f in frames[:5]])
        lever = T_e[:3, 3] - origins
        J = np.empty((6, 6))
        # axes x lever, column-wise (np.cross costs ~60 us here, this ~5)
        J[0] = axes[:, 1] * lever[:, 2] - axes[:, 2] * lever[:, 1]
        J[1] = axes[:, 2] * lever[:, 0] - axes[:, 0] * lever[:, 2]
        J[2] = axes[:, 0] * lever[:, 1] - axes[:, 1] * lever[:, 0]
        J[3:] = axes.T
        if abs(float(np.linalg.det(J))) < min_det_mm3:
            return None
        q = q + np.linalg.solve(J, np.concatenate([dp, dw]))
    return None


def wrap_to_pi(q_rad: ArrayLike) -> FloatArray:
    """Angles wrapped into (-pi, pi]."""
    q = np.asarray(q_rad, dtype=np.float64)
    w: FloatArray = np.pi - np.mod(np.pi - q, _TWO_PI)
    return w


def _nearest_equivalent(q: FloatArray, q_near: FloatArray, limits: FloatArray) -> FloatArray:
    """Per joint, the 2*pi-equivalent of ``q`` closest to ``q_near`` that stays inside ``limits``."""
    base = q_near + wrap_to_pi(q - q_near)  # the nearest equivalent, |base - q_near| <= pi
    lo, hi = limits[:, 0] - 1e-12, limits[:, 1] + 1e-12
    out = base.copy()
    for shift in (_TWO_PI, -_TWO_PI):  # base outside the limits: try the next equivalent inwards
        bad = (out < lo) | (out > hi)
        if not np.any(bad):
            break
        alt = base + shift
        use = bad & (alt >= lo) & (alt <= hi)
        out[use] = alt[use]
    return out


def _planar_solutions(
    T_base_from_tool0: RigidTransform, p: DHParams, q1: float, q5: float, q6: float
) -> list[FloatArray]:
    """The elbow-up and elbow-down solutions (q2, q3, q4 of the planar 3R chain, Hawkins 2013)
    for given q1, q5, q6 (rad), as full joint vectors wrapped to (-pi, pi]; none when the wrist
    is out of the arm's reach. Distances in mm."""
    d, a = p.d_mm, p.a_mm
    d1, d5, d6 = float(d[0]), float(d[4]), float(d[5])
    a2, a3 = float(a[1]), float(a[2])
    T01 = _dh_matrix(q1, d1, 0.0, p.alpha_rad[0])
    T45 = _dh_matrix(q5, d5, 0.0, p.alpha_rad[4])
    T56 = _dh_matrix(q6, d6, 0.0, p.alpha_rad[5])
    T14 = np.linalg.inv(T01) @ T_base_from_tool0.as_matrix() @ np.linalg.inv(T45 @ T56)
    x, y = float(T14[0, 3]), float(T14[1, 3])
    c3 = (x * x + y * y - a2 * a2 - a3 * a3) / (2.0 * a2 * a3)
    if abs(c3) > 1.0 + 1e-9:
        return []
    c3 = max(-1.0, min(1.0, c3))
    solutions: list[FloatArray] = []
    for q3 in (math.acos(c3), -math.acos(c3)):
        q2 = math.atan2(y, x) - math.atan2(a3 * math.sin(q3), a2 + a3 * math.cos(q3))
        q234 = math.atan2(float(T14[1, 0]), float(T14[0, 0]))
        q4 = q234 - q2 - q3
        q = wrap_to_pi(np.array([q1, q2, q3, q4, q5, q6]))
        solutions.append(q)
    return solutions


def ur_inverse(
    T_base_from_tool0: RigidTransform,
    model: str = "ur3",
    q_near: ArrayLike | None = None,
    *,
    q6_free_rad: float | None = None,
) -> FloatArray:
    """All analytic inverse-kinematics solutions for a tool0 pose (Hawkins 2013; see module doc).

    Args:
        T_base_from_tool0: the wanted flange pose in the base frame (mm).
        model: ``ur3`` or ``ur3e``.
        q_near: optional joint vector (rad). When given, each joint of every solution is moved by
            multiples of 2*pi to the equivalent nearest ``q_near`` (inside ``UR3_JOINT_LIMITS_RAD``)
            and the solutions are sorted by Euclidean joint distance to ``q_near``, nearest first.
            Without it, angles are in (-pi, pi] and the order is shoulder, wrist, elbow branch.
        q6_free_rad: the value given to q6 at the wrist singularity (sin q5 = 0), where only
            q4 + q6 (or q4 - q6) is defined; default ``q_near[5]`` or 0.

    Returns:
        (K, 6) array of joint solutions in rad, K in 0..8; K = 0 when the pose is unreachable.
        Every returned solution reproduces the pose to 1e-6 mm / 1e-7 rad by :func:`ur_forward`.

    Raises:
        GeometryError: unknown model, or ``q_near`` not 6 finite values.
    """
    p = dh_params(model)
    d4, d6 = float(p.d_mm[3]), float(p.d_mm[5])
    near = _as_q(q_near, "q_near") if q_near is not None else None
    if q6_free_rad is None:
        q6_free_rad = float(near[5]) if near is not None else 0.0

    R06 = T_base_from_tool0.R
    p06 = T_base_from_tool0.t
    # Wrist centre (origin of frame 5): back off d6 along the tool z axis.
    p05 = p06 - d6 * R06[:, 2]
    r = math.hypot(float(p05[0]), float(p05[1]))
    if r < abs(d4) - _TRIG_SLACK or r < 1e-12:
        return np.zeros((0, 6))
    phi = math.atan2(float(p05[1]), float(p05[0]))
    # p05 . z1 = d4 with z1 = (sin q1, -cos q1, 0)  ->  r sin(q1 - phi) = d4.
    s = max(-1.0, min(1.0, d4 / r))
    q1_candidates = (phi + math.asin(s), phi + math.pi - math.asin(s))

    solutions: list[FloatArray] = []
    for q1 in q1_candidates:
        s1, c1 = math.sin(q1), math.cos(q1)
        # z1 = (sin q1, -cos q1, 0) seen from the tool frame is (sin q5 cos q6, -sin q5 sin q6, cos q5);
        # its z component is also (p06 . z1 - d4) / d6, the form Hawkins uses. Taking |sin q5| from the
        # x, y components keeps q5 accurate near the wrist singularity, where acos would not.
        w = R06.T @ np.array([s1, -c1, 0.0])
        s5_abs = math.hypot(float(w[0]), float(w[1]))
        for sign in (1.0, -1.0):
            q5 = math.atan2(sign * s5_abs, float(w[2]))
            if s5_abs < _WRIST_SINGULAR:
                if sign < 0:
                    continue  # the two wrist branches coincide
                q6 = q6_free_rad
            else:
                q6 = math.atan2(-sign * float(w[1]), sign * float(w[0]))
            solutions += _planar_solutions(T_base_from_tool0, p, q1, q5, q6)

    checked = _verified_unique(solutions, T_base_from_tool0, model)
    if not checked:
        return np.zeros((0, 6))
    out = np.array(checked)
    if near is not None:
        out = np.array([_nearest_equivalent(q, near, UR3_JOINT_LIMITS_RAD) for q in out])
        order = np.argsort(np.linalg.norm(out - near, axis=1), kind="stable")
        out = out[order]
    return out


def _fk_matrix(q: FloatArray, p: DHParams) -> FloatArray:
    d, a = p.d_mm, p.a_mm
    T = np.eye(4)
    for i in range(6):
        T = T @ _dh_matrix(float(q[i]), float(d[i]), float(a[i]), p.alpha_rad[i])
    return T


def _verified_unique(
    solutions: list[FloatArray], T_target: RigidTransform, model: str
) -> list[FloatArray]:
    # Raw matrices here: this runs up to 8 times per call and the emulator calls it every tick.
    p = dh_params(model)
    R_t, p_t = T_target.R, T_target.t
    kept: list[FloatArray] = []
    for q in solutions:
        T = _fk_matrix(q, p)
        if float(np.linalg.norm(T[:3, 3] - p_t)) > _IK_CHECK_MM:
            continue
        c = (float(np.trace(R_t.T @ T[:3, :3])) - 1.0) / 2.0
        if math.acos(max(-1.0, min(1.0, c))) > _IK_CHECK_RAD:
            continue
        if kept and float(np.min(np.max(np.abs(wrap_to_pi(np.asarray(kept) - q)), axis=1))) < 1e-9:
            continue
        kept.append(q)
    return kept


def within_joint_limits(q_rad: ArrayLike, limits: FloatArray = UR3_JOINT_LIMITS_RAD) -> bool:
    """True when every joint of ``q_rad`` lies inside ``limits`` ((6, 2) rad)."""
    q = _as_q(q_rad)
    return bool(np.all(q >= limits[:, 0]) and np.all(q <= limits[:, 1]))


def within_reach(p_base_mm: ArrayLike, reach_mm: float = UR3_REACH_MM, model: str = "ur3") -> bool:
    """Coarse reach test: the point is within ``reach_mm`` of the shoulder (base axis at height d1).

    Necessary, not sufficient: use :func:`ur_inverse` for the exact answer for a full pose.
    """
    pt = np.asarray(p_base_mm, dtype=np.float64).reshape(3)
    shoulder = np.array([0.0, 0.0, float(dh_params(model).d_mm[0])])
    return bool(np.linalg.norm(pt - shoulder) <= reach_mm)
