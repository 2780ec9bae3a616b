"""Two-view triangulation: linear DLT and the skew-line midpoint of seed 003 section 4.1.

Seed 003 section 4.1: the two back-projected rays of a marker rarely intersect; take the shortest
segment between them (perpendicular to both), accept its midpoint as the marker when its length
(the "gap") is below a threshold, and treat a larger gap as a calibration or matching problem.
:func:`triangulate_midpoint` returns the gap so the caller can apply that rule.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import DegenerateConfigurationError, GeometryError

FloatArray = NDArray[np.float64]


def _uv(arr: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(arr, dtype=np.float64)
    if a.ndim == 1 and a.shape[0] == 2:
        a = a[np.newaxis]
    if a.ndim == 3 and a.shape[1] == 1 and a.shape[2] == 2:  # OpenCV (N, 1, 2)
        a = a[:, 0, :]
    if a.ndim != 2 or a.shape[1] != 2:
        raise GeometryError(f"{name} must have shape (N, 2), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise GeometryError(f"{name} contains NaN or infinite values")
    return a


def _proj(P: ArrayLike, name: str) -> FloatArray:
    M = np.asarray(P, dtype=np.float64)
    if M.shape != (3, 4) or not np.all(np.isfinite(M)):
        raise GeometryError(f"{name} must be a finite 3x4 projection matrix, got shape {M.shape}")
    return M


def triangulate_dlt(
    P_left: ArrayLike, P_right: ArrayLike, uv_left: ArrayLike, uv_right: ArrayLike
) -> FloatArray:
    """Linear (DLT) triangulation of N correspondences (Hartley & Zisserman 12.2).

    Args:
        P_left, P_right: 3x4 projection matrices mapping homogeneous points (mm) to pixels.
        uv_left, uv_right: (N, 2) undistorted pixel coordinates (OpenCV's (N, 1, 2) accepted).

    Returns:
        (N, 3) points in the frame of the projection matrices, mm.

    Raises:
        GeometryError: bad shapes, NaN/inf, different counts.
        DegenerateConfigurationError: a point triangulates to infinity (parallel rays).
    """
    PL = _proj(P_left, "P_left")
    PR = _proj(P_right, "P_right")
    a = _uv(uv_left, "uv_left")
    b = _uv(uv_right, "uv_right")
    if a.shape[0] != b.shape[0]:
        raise GeometryError(f"uv_left has {a.shape[0]} points but uv_right has {b.shape[0]}")
    n = a.shape[0]
    if n == 0:
        return np.zeros((0, 3))
    A = np.empty((n, 4, 4))
    A[:, 0] = a[:, :1] * PL[2] - PL[0]
    A[:, 1] = a[:, 1:] * PL[2] - PL[1]
    A[:, 2] = b[:, :1] * PR[2] - PR[0]
    A[:, 3] = b[:, 1:] * PR[2] - PR[1]
    A /= np.linalg.norm(A, axis=2, keepdims=True)  # row equilibration for conditioning
    _, _, Vt = np.linalg.svd(A)
    X = Vt[:, -1, :]
    w = X[:, 3]
    scale = np.linalg.norm(X[:, :3], axis=1)
    if np.any(np.abs(w) <= 1e-12 * scale):
        raise DegenerateConfigurationError("a correspondence triangulates to a point at infinity")
    out: FloatArray = X[:, :3] / w[:, None]
    return out


def triangulate_midpoint(
    origin_a: ArrayLike, dirs_a: ArrayLike, origin_b: ArrayLike, dirs_b: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Midpoints of the shortest segments between ray pairs and their lengths (seed 003 §4.1).

    Lines ``L1(s) = o_a + s u`` and ``L2(t) = o_b + t v``; the connecting vector
    ``V = L1(s) - L2(t)`` is perpendicular to ``u`` and ``v``, which gives two linear equations
    in ``s, t`` (the paper's eq 4); the marker is the midpoint of the segment and the gap ``|V|``.
    Treated as infinite lines (no check that the point is in front of the cameras).

    Args:
        origin_a, origin_b: (3,) ray origins (camera centres), mm.
        dirs_a, dirs_b: (N, 3) ray directions (any non-zero length) for N ray pairs.

    Returns:
        ``(points (N, 3), gap_mm (N,))``.

    Raises:
        GeometryError: bad shapes, NaN/inf, zero directions.
        DegenerateConfigurationError: a pair of rays is parallel (no unique closest points).
    """
    oa = np.asarray(origin_a, dtype=np.float64).reshape(-1)
    ob = np.asarray(origin_b, dtype=np.float64).reshape(-1)
    if oa.shape != (3,) or ob.shape != (3,) or not (np.all(np.isfinite(oa)) and np.all(np.isfinite(ob))):
        raise GeometryError("ray origins must be 3 finite values each")
    u = np.asarray(dirs_a, dtype=np.float64)
    v = np.asarray(dirs_b, dtype=np.float64)
    if u.ndim == 1:
        u = u[np.newaxis]
    if v.ndim == 1:
        v = v[np.newaxis]
    if u.ndim != 2 or u.shape[1] != 3 or v.shape != u.shape:
        raise GeometryError(f"ray directions must be two (N, 3) arrays of equal N, not {u.shape}, {v.shape}")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(v))):
        raise GeometryError("ray directions contain NaN or infinite values")
    nu = np.linalg.norm(u, axis=1)
    nv = np.linalg.norm(v, axis=1)
    if np.any(nu == 0.0) or np.any(nv == 0.0):
        raise GeometryError("a ray direction is the zero vector")
    u = u / nu[:, None]
    v = v / nv[:, None]
    w0 = oa - ob
    b = np.sum(u * v, axis=1)
    d = u @ w0
    e = v @ w0
    denom = 1.0 - b * b
    if np.any(denom <= 1e-12):
        raise DegenerateConfigurationError("a pair of rays is parallel; they have no unique closest points")
    s = (b * e - d) / denom
    t = (e - b * d) / denom
    pa = oa + s[:, None] * u
    pb = ob + t[:, None] * v
    gap = np.linalg.norm(pa - pb, axis=1)
    return 0.5 * (pa + pb), gap
