"""The rigid transform type used everywhere in the core.

Naming (DESIGN.md): a variable ``T_robot_from_image`` maps a point expressed in the image frame
into the robot frame, ``p_robot = T_robot_from_image.apply(p_image)``, and compositions read by
adjacency: ``T_robot_from_image = T_robot_from_optical @ T_optical_from_image``.
Translations are in millimetres unless a caller says otherwise; rotations in radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import GeometryError

FloatArray = NDArray[np.float64]

_ORTHO_TOL = 1e-6
#: the 3x3 identity, read-only (np.eye is Python code; Rodrigues runs in every pair's path)
_EYE3: FloatArray = np.eye(3)
_EYE3.setflags(write=False)


def as_points(points: ArrayLike, name: str = "points") -> FloatArray:
    """Validate and return an (N, 3) float64 array of finite points.

    A single point of shape (3,) is returned as (1, 3).

    Raises:
        GeometryError: not numbers (e.g. strings, ragged lists, an integer beyond float range),
            wrong shape, or any NaN/inf.
    """
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise GeometryError(f"{name} is not an array of numbers ({exc})") from None
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[np.newaxis, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise GeometryError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise GeometryError(f"{name} contains NaN or infinite values")
    return arr


def _clearly_rotation(R: FloatArray) -> bool:
    """Fast path of :func:`_check_rotation` (R is 3x3): True when ``R^T R`` is within half the
    tolerance of I and ``det R`` is near +1, in plain float arithmetic (several times faster than
    the numpy checks on a 3x3; every servo command builds a few dozen transforms). False means
    "not sure" (including NaN/inf): the numpy checks decide and raise."""
    rows: list[list[float]] = R.tolist()
    (a, b, c), (d, e, f), (g, h, i) = rows
    tol = 0.5 * _ORTHO_TOL
    return bool(abs(a * a + d * d + g * g - 1.0) <= tol and abs(b * b + e * e + h * h - 1.0) <= tol
            and abs(c * c + f * f + i * i - 1.0) <= tol and abs(a * b + d * e + g * h) <= tol
            and abs(a * c + d * f + g * i) <= tol and abs(b * c + e * f + h * i) <= tol
            and a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) > 0.5)


def _check_rotation(R: FloatArray) -> None:
    if R.shape != (3, 3):
        raise GeometryError(f"rotation must be 3x3, got {R.shape}")
    if _clearly_rotation(R):
        return
    if not np.all(np.isfinite(R)):
        raise GeometryError("rotation contains NaN or infinite values")
    if not np.allclose(R.T @ R, np.eye(3), atol=_ORTHO_TOL) or np.linalg.det(R) < 0:
        raise GeometryError("matrix is not a proper rotation (orthonormal, det +1)")


def _rot_x(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class RigidTransform:
    """A proper rigid transform ``p' = R p + t`` (rotation ``R``, translation ``t`` in mm).

    Immutable. Construct from parts, a 4x4 matrix, a quaternion, a rotation vector or Euler
    angles; compose with ``@``; invert with :meth:`inverse`; map points with :meth:`apply`.
    """

    R: FloatArray
    t: FloatArray

    def __post_init__(self) -> None:
        R = np.array(self.R, dtype=np.float64, copy=True)
        t = np.array(self.t, dtype=np.float64, copy=True).reshape(-1)
        _check_rotation(R)
        if t.shape != (3,) or not np.isfinite(t).all():
            raise GeometryError(f"translation must be 3 finite values, got {self.t!r}")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @classmethod
    def _composed(cls, R: FloatArray, t: FloatArray) -> RigidTransform:
        """From the parts of a composition or inverse of valid transforms (fresh float64 arrays,
        R 3x3 and t (3,), owned by the result): proper and finite by construction, so the checks
        of ``__post_init__`` are skipped - a servo period composes a few dozen transforms, and
        the checks were a large part of its cost. Bit-identical to the checked constructor."""
        out = object.__new__(cls)
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(out, "R", R)
        object.__setattr__(out, "t", t)
        return out

    # ------------------------------------------------------------------ constructors
    @classmethod
    def identity(cls) -> RigidTransform:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_translation(cls, t: ArrayLike) -> RigidTransform:
        return cls(np.eye(3), np.asarray(t, dtype=np.float64))

    @classmethod
    def from_matrix(cls, M: ArrayLike) -> RigidTransform:
        """From a 4x4 homogeneous matrix whose last row is [0, 0, 0, 1]."""
        M = np.asarray(M, dtype=np.float64)
        if M.shape != (4, 4):
            raise GeometryError(f"homogeneous matrix must be 4x4, got {M.shape}")
        if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise GeometryError(f"last row of a rigid 4x4 must be [0 0 0 1], got {M[3]}")
        return cls(M[:3, :3], M[:3, 3])

    @classmethod
    def from_quaternion(cls, q_wxyz: ArrayLike, t: ArrayLike = (0.0, 0.0, 0.0)) -> RigidTransform:
        """From a quaternion, scalar first ``[q0, q1, q2, q3]`` (normalised here).

        The matrix is seed 000 eq 16 (the standard Hamilton convention).
        """
        return cls(quaternion_to_matrix(q_wxyz), np.asarray(t, dtype=np.float64))

    @classmethod
    def from_rotvec(cls, rotvec: ArrayLike, t: ArrayLike = (0.0, 0.0, 0.0)) -> RigidTransform:
        """From a rotation vector (axis * angle, rad) — UR's axis-angle pose representation."""
        return cls(rotvec_to_matrix(rotvec), np.asarray(t, dtype=np.float64))

    @classmethod
    def from_euler_zyx(
        cls, psi: float, theta: float, phi: float, t: ArrayLike = (0.0, 0.0, 0.0)
    ) -> RigidTransform:
        """Seed 000 eq 14: ``R = Rz(psi) Ry(theta) Rx(phi)`` (yaw ψ, pitch θ, roll φ; rad)."""
        R = _rot_z(psi) @ _rot_y(theta) @ _rot_x(phi)
        return cls(R, np.asarray(t, dtype=np.float64))

    @classmethod
    def from_euler_xyz(
        cls, alpha: float, beta: float, gamma: float, t: ArrayLike = (0.0, 0.0, 0.0)
    ) -> RigidTransform:
        """Seed 002 eq 23: ``R = R(x, α) R(y, β) R(z, γ)`` (rad)."""
        R = _rot_x(alpha) @ _rot_y(beta) @ _rot_z(gamma)
        return cls(R, np.asarray(t, dtype=np.float64))

    # ------------------------------------------------------------------ conversions
    def as_matrix(self) -> FloatArray:
        """The 4x4 homogeneous matrix (a new, writable array)."""
        M = np.eye(4)
        M[:3, :3] = self.R
        M[:3, 3] = self.t
        return M

    def as_quaternion(self) -> FloatArray:
        """Unit quaternion, scalar first, with q0 >= 0."""
        return matrix_to_quaternion(self.R)

    def as_rotvec(self) -> FloatArray:
        """Rotation vector (axis * angle, rad), angle in [0, pi]."""
        return matrix_to_rotvec(self.R)

    def as_euler_zyx(self) -> tuple[float, float, float]:
        """Inverse of :meth:`from_euler_zyx`: ``(psi, theta, phi)``, theta in [-pi/2, pi/2]."""
        R = self.R
        theta = -math.asin(max(-1.0, min(1.0, float(R[2, 0]))))
        if abs(math.cos(theta)) > 1e-9:
            psi = math.atan2(R[1, 0], R[0, 0])
            phi = math.atan2(R[2, 1], R[2, 2])
        else:  # gimbal lock: only psi - phi (or psi + phi) is defined; put it all in psi
            phi = 0.0
            psi = math.atan2(-R[0, 1], R[1, 1])
        return psi, theta, phi

    def as_euler_xyz(self) -> tuple[float, float, float]:
        """Inverse of :meth:`from_euler_xyz`: ``(alpha, beta, gamma)``, beta in [-pi/2, pi/2]."""
        R = self.R
        beta = math.asin(max(-1.0, min(1.0, float(R[0, 2]))))
        if abs(math.cos(beta)) > 1e-9:
            alpha = math.atan2(-R[1, 2], R[2, 2])
            gamma = math.atan2(-R[0, 1], R[0, 0])
        else:
            alpha = 0.0
            gamma = math.atan2(R[1, 0], R[1, 1])
        return alpha, beta, gamma

    # ------------------------------------------------------------------ algebra
    def inverse(self) -> RigidTransform:
        """The inverse: ``T_a_from_b.inverse()`` is ``T_b_from_a``."""
        Rt = self.R.T
        return RigidTransform._composed(np.ascontiguousarray(Rt), -Rt @ self.t)

    def __matmul__(self, other: RigidTransform) -> RigidTransform:
        """Composition: ``(T_a_from_b @ T_b_from_c)`` is ``T_a_from_c``."""
        if not isinstance(other, RigidTransform):
            return NotImplemented
        return RigidTransform._composed(self.R @ other.R, self.R @ other.t + self.t)

    @overload
    def apply(self, points: FloatArray) -> FloatArray: ...
    @overload
    def apply(self, points: ArrayLike) -> FloatArray: ...
    def apply(self, points: ArrayLike) -> FloatArray:
        """Map points: (3,) -> (3,), (N, 3) -> (N, 3)."""
        arr = np.asarray(points, dtype=np.float64)
        if arr.shape == (3,):
            return self.R @ arr + self.t
        pts = as_points(arr)
        return pts @ self.R.T + self.t

    def apply_vector(self, vectors: ArrayLike) -> FloatArray:
        """Rotate direction vectors (no translation): (3,) or (N, 3)."""
        arr = np.asarray(vectors, dtype=np.float64)
        if arr.shape == (3,):
            return self.R @ arr
        return as_points(arr, "vectors") @ self.R.T

    def rotation_angle_rad(self) -> float:
        """Angle of the rotation part, rad, in [0, pi]."""
        # atan2 of (sin, cos) keeps full precision near 0 and pi, unlike acos of the trace.
        # Plain floats: the same operations in the same order as np.trace and the indexing
        # (bit-identical), without numpy's per-element layers (a bound check per pair).
        (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = self.R.tolist()
        c = (m00 + m11 + m22 - 1.0) / 2.0
        s = 0.5 * math.sqrt((m21 - m12) ** 2 + (m02 - m20) ** 2 + (m10 - m01) ** 2)
        return math.atan2(s, c)

    def translation_norm(self) -> float:
        """|t|, mm: the same dot product np.linalg.norm takes, without its Python layers."""
        return math.sqrt(float(self.t.dot(self.t)))

    def is_close(self, other: RigidTransform, atol_mm: float = 1e-9, atol_rad: float = 1e-9) -> bool:
        """True when both the relative rotation angle and translation difference are within tolerance."""
        d = self.inverse() @ other
        return d.rotation_angle_rad() <= atol_rad and bool(
            np.linalg.norm(self.t - other.t) <= atol_mm
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly: ``{"matrix": 4x4 nested list}``."""
        return {"matrix": self.as_matrix().tolist()}

    def __repr__(self) -> str:
        rv = np.round(self.as_rotvec(), 6).tolist()
        return f"RigidTransform(rotvec_rad={rv}, t_mm={np.round(self.t, 6).tolist()})"


# ---------------------------------------------------------------------- rotation helpers
def quaternion_to_matrix(q_wxyz: ArrayLike) -> FloatArray:
    """Rotation matrix from a quaternion, scalar first (seed 000 eq 16). Normalises ``q``.

    Raises:
        GeometryError: not 4 finite values, or zero norm.
    """
    q = np.asarray(q_wxyz, dtype=np.float64).reshape(-1)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise GeometryError(f"quaternion must be 4 finite values, got {q_wxyz!r}")
    n = float(np.linalg.norm(q))
    if n < 1e-12:
        raise GeometryError("quaternion has zero norm")
    q0, q1, q2, q3 = q / n
    return np.array(
        [
            [q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3, 2 * (q1 * q2 - q0 * q3), 2 * (q1 * q3 + q0 * q2)],
            [2 * (q1 * q2 + q0 * q3), q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3, 2 * (q2 * q3 - q0 * q1)],
            [2 * (q1 * q3 - q0 * q2), 2 * (q2 * q3 + q0 * q1), q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3],
        ]
    )


def matrix_to_quaternion(R: ArrayLike) -> FloatArray:
    """Unit quaternion (scalar first, q0 >= 0) from a rotation matrix (Shepperd's method)."""
    M = np.asarray(R, dtype=np.float64)
    _check_rotation(M)
    # plain floats (the same IEEE operations as on the array's elements, several times faster)
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = M.tolist()
    tr = m00 + m11 + m22
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = np.array([0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s])
    elif m00 > m11 and m00 > m22:
        s = math.sqrt(1.0 + m00 - m11 - m22) * 2.0
        q = np.array([(m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s])
    elif m11 > m22:
        s = math.sqrt(1.0 + m11 - m00 - m22) * 2.0
        q = np.array([(m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s])
    else:
        s = math.sqrt(1.0 + m22 - m00 - m11) * 2.0
        q = np.array([(m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s])
    q /= math.sqrt(float(q.dot(q)))   # np.linalg.norm's own sum, without its Python layers
    if q[0] < 0:
        q = -q
    return q


def rotvec_to_matrix(rotvec: ArrayLike) -> FloatArray:
    """Rodrigues: rotation matrix from axis * angle (rad).

    Raises:
        GeometryError: not 3 finite values, or an angle too large to represent (norm overflows).
    """
    v = np.asarray(rotvec, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise GeometryError(f"rotation vector must be 3 finite values, got {rotvec!r}")
    theta = math.hypot(float(v[0]), float(v[1]), float(v[2]))  # no overflow in the squares
    if not math.isfinite(theta):
        raise GeometryError(f"rotation vector angle overflows a float, got {rotvec!r}")
    if theta < 1e-12:
        return _EYE3.copy()
    k = v / theta
    K = skew(k)
    R: FloatArray = _EYE3 + math.sin(theta) * K + (1.0 - math.cos(theta)) * (K @ K)
    return R


def matrix_to_rotvec(R: ArrayLike) -> FloatArray:
    """Rotation vector (axis * angle, angle in [0, pi]) from a rotation matrix.

    Near pi the axis sign is ambiguous (UR controllers report either sign, ur-rtde.md trap 7);
    compare rotations, not raw vectors.
    """
    q = matrix_to_quaternion(R)
    w = max(-1.0, min(1.0, float(q[0])))
    v = q[1:]
    s = math.sqrt(float(v.dot(v)))   # np.linalg.norm's own sum, without its Python layers
    if s < 1e-12:
        return np.zeros(3)
    angle = 2.0 * math.atan2(s, w)
    return q[1:] / s * angle


def skew(v: ArrayLike) -> FloatArray:
    """The cross-product matrix ``[v]x`` with ``skew(a) @ b == cross(a, b)``."""
    a = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
