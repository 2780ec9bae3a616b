"""A small projective correction of triangulated points: what a stereo calibration that is
slightly off does to 3-D space, and its undoing.

Triangulating with cameras ``P_i`` the pixels that true cameras ``P_i H`` (``H`` a 4x4 matrix
near the identity) made gives ``H X`` instead of ``X``: to first order, small errors in the focal
lengths, principal points and the right camera's pose act on 3-D space as one projective map
(Hartley and Zisserman, *Multiple View Geometry*, 2nd ed., section 10.2: a reconstruction is
determined up to a projective transformation of space). Errors in the focal lengths and principal
points give its affine part (scale and shear); a disparity offset, and one that varies linearly
across the image (the right camera's small rotations), give its last row, ``Z' = Z / (1 + q . X)``.
A rigid part of the error cannot be told from where the camera stands and belongs to the
camera -> robot transform, so the warp here has none: about a centre ``c``,

    W(x) = c + (I + S) (x - c) / (1 + q . (x - c)),   S symmetric (6), q (3),

nine numbers (:func:`warp_matrix`). :class:`ProjectiveCorrection` holds ``W``'s inverse as a
homogeneous 4x4 matrix and applies it to points (mm in, mm out).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import GeometryError

FloatArray = NDArray[np.float64]

#: Number of warp parameters: the six of S (xx, yy, zz, xy, xz, yz), then q (3).
WARP_PARAMETERS = 9


def warp_matrix(center_mm: ArrayLike, params: ArrayLike) -> FloatArray:
    """The 4x4 homogeneous matrix of ``W`` (module doc) for ``params`` = (S_xx, S_yy, S_zz, S_xy,
    S_xz, S_yz, q_x, q_y, q_z) (S unitless, q per mm) about ``center_mm`` (3, mm)."""
    c = np.asarray(center_mm, dtype=np.float64).reshape(3)
    p = np.asarray(params, dtype=np.float64).reshape(WARP_PARAMETERS)
    S = np.array([[p[0], p[3], p[4]], [p[3], p[1], p[5]], [p[4], p[5], p[2]]])
    about = np.eye(4)
    about[:3, :3] += S
    about[3, :3] = p[6:]
    to_c, from_c = np.eye(4), np.eye(4)
    to_c[:3, 3], from_c[:3, 3] = c, -c
    out: FloatArray = to_c @ about @ from_c
    return out


def apply_homography(H: FloatArray, points_mm: ArrayLike) -> FloatArray:
    """``points_mm`` (N, 3) mapped by the homogeneous 4x4 ``H`` (a new (N, 3) array)."""
    P = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    w = P @ H[3, :3] + H[3, 3]
    out: FloatArray = (P @ H[:3, :3].T + H[:3, 3]) / w[:, None]
    return out


@dataclass(frozen=True)
class ProjectiveCorrection:
    """Maps a point triangulated with the stereo calibration (optical frame, mm) to where it is in
    metric space (the same frame, mm), through ``H_metric_from_measured`` (4x4, homogeneous).

    Build with :meth:`undoing` (the inverse of a fitted warp) or :meth:`from_matrix` (a file's).
    Immutable; :meth:`apply` allocates its result and never changes its input.
    """

    H_metric_from_measured: FloatArray

    @classmethod
    def undoing(cls, warp: FloatArray) -> ProjectiveCorrection:
        """The correction that undoes the warp ``warp`` (4x4: metric -> measured).

        Raises:
            GeometryError: ``warp`` is singular.
        """
        try:
            inv = np.linalg.inv(np.asarray(warp, dtype=np.float64))
        except np.linalg.LinAlgError:
            raise GeometryError("the optical warp is singular") from None
        return cls.from_matrix(inv)

    @classmethod
    def from_matrix(cls, H: ArrayLike) -> ProjectiveCorrection:
        """From a 4x4 homogeneous matrix (normalised so that ``H[3, 3] == 1``).

        Raises:
            GeometryError: not 4x4, not finite, or ``H[3, 3]`` zero.
        """
        M = np.array(H, dtype=np.float64)
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise GeometryError("a projective correction must be a finite 4x4 matrix")
        if abs(M[3, 3]) < 1e-12:
            raise GeometryError("a projective correction needs H[3][3] != 0")
        M = M / M[3, 3]
        M.setflags(write=False)
        return cls(M)

    def apply(self, points_mm: ArrayLike) -> FloatArray:
        """The metric positions of ``points_mm`` (N, 3, optical frame, mm): a new (N, 3) array."""
        return apply_homography(self.H_metric_from_measured, points_mm)

    def to_measured(self, points_mm: ArrayLike) -> FloatArray:
        """The inverse: metric points (N, 3, mm) to where the stereo calibration triangulates them
        (a new (N, 3) array; for image-space checks such as the needle's)."""
        undo = np.asarray(np.linalg.inv(self.H_metric_from_measured), dtype=np.float64)
        return apply_homography(undo, points_mm)

    def displacement_mm(self, points_mm: ArrayLike) -> float:
        """The largest distance a point of ``points_mm`` (N, 3) is moved by the correction, mm."""
        P = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        if P.shape[0] == 0:
            return 0.0
        return float(np.max(np.linalg.norm(self.apply(P) - P, axis=1)))

    def as_lists(self) -> list[list[float]]:
        """The matrix as nested lists (a file's ``optical_correction``)."""
        return [[float(v) for v in row] for row in self.H_metric_from_measured]
