"""UR pose vectors ``[x, y, z, rx, ry, rz]`` (metres, rotation vector in radians) and 4x4 transforms.

Shared by the controller (its RTDE pose outputs) and the program interpreter (pose arguments of
commands and URScript statements); no controller state here.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hil.geometry.transform import matrix_to_rotvec, rotvec_to_matrix

FloatArray = NDArray[np.float64]


def pose_to_matrix(pose: Any) -> FloatArray:
    """4x4 homogeneous transform of a UR pose (its first 6 values).

    Raises:
        GeometryError: the rotation vector is not 3 finite values, or its angle overflows.
    """
    p = np.asarray(pose, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix(p[3:6])
    T[:3, 3] = p[:3]
    return T


def fast_rotvec(R: FloatArray) -> FloatArray:
    """Rotation vector of a rotation matrix the controller made itself (no validation: hot path)."""
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = (float(R[0, 0] + R[1, 1] + R[2, 2]) - 1.0) / 2.0
    if c < -0.99:  # near pi the axis needs the symmetric part: use the validated path
        return matrix_to_rotvec(R)
    s2 = float(np.linalg.norm(v))  # 2 sin(angle)
    if s2 < 1e-300:
        return np.zeros(3)
    angle = math.atan2(s2 / 2.0, c)
    out: FloatArray = v * (angle / s2)
    return out


def matrix_to_pose(T: FloatArray) -> tuple[float, ...]:
    """UR pose of a 4x4 transform the controller made itself (see :func:`fast_rotvec`)."""
    rv = fast_rotvec(T[:3, :3])
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), float(rv[0]), float(rv[1]), float(rv[2]))
