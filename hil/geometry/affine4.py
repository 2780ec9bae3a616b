"""Four-marker affine frames (seed 000 eqs 2-12) — an alternative to least-squares registration.

Seed 000 builds, from four markers ``M0..M3``, an "affine coordinate system" whose axes are the
edge vectors ``M1-M0, M2-M0, M3-M0`` and whose origin is ``M0`` (eqs 2, 4, 7, 9):

    T_space_from_affine = [[M1-M0, M2-M0, M3-M0, M0], [0, 0, 0, 1]]   (columns)

A point with affine coordinates ``a`` is ``T a`` in that space (eq 3). Doing this with the same
four markers in two spaces and chaining gives the point mapping between the spaces (eqs 6, 11,
12): ``T_fixed_from_moving = T_fixed_from_affine @ inv(T_moving_from_affine)``. (The paper writes
the chain with inverses in other places, e.g. ``T3 = T2^-1 T1^-1``; the chain above is the one
consistent with its eq 3, ``P_image = T1 P_affine``.)

Limits — read before using it: the result is a general affine map. It is exact only when the four
markers form a rigid, noise-free body; it interpolates the four points exactly (FRE is always 0),
so it cannot report its own error, and localisation noise turns into shear and scale that grow
with the distance of a target from the markers. Least-squares rigid registration
(:mod:`hil.geometry.registration`) averages the noise instead; the tests show the affine frames'
target error exceeding Horn's under noise. Kept for fidelity to the paper and for comparison.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.transform import RigidTransform, as_points

FloatArray = NDArray[np.float64]

#: Smallest / largest singular value of the edge matrix below which four points count as coplanar.
COPLANAR_REL_TOL = 1e-6


def affine_frame(points_mm: ArrayLike, name: str = "points") -> FloatArray:
    """The 4x4 ``T_space_from_affine`` of seed 000 eq 2 from exactly four points ``M0..M3``.

    Raises:
        GeometryError: not exactly 4 finite points.
        DegenerateConfigurationError: the four points are coplanar (or collinear/coincident).
    """
    pts = as_points(points_mm, name)
    if pts.shape[0] != 4:
        raise GeometryError(f"{name}: the four-marker frame needs exactly 4 points, not {pts.shape[0]}")
    E = (pts[1:] - pts[0]).T  # columns M1-M0, M2-M0, M3-M0
    sv = np.linalg.svd(E, compute_uv=False)
    if sv[0] == 0.0 or sv[2] <= COPLANAR_REL_TOL * sv[0]:
        raise DegenerateConfigurationError(f"{name}: the four points are coplanar; they span no affine frame")
    T = np.eye(4)
    T[:3, :3] = E
    T[:3, 3] = pts[0]
    return T


@dataclass(frozen=True)
class AffineRegistration:
    """Result of :func:`register_affine4`.

    Attributes:
        matrix_fixed_from_moving: 4x4 affine map (not in general a rigid transform).
        nearest_rigid: the rigid transform closest to it (polar decomposition of the linear part,
            same translation) — what a caller that needs a rotation should use.
        residuals_mm: (4,) distances between mapped moving and fixed points (0 up to rounding).
        fre_rms_mm: RMS of the residuals (0 up to rounding: the method interpolates).
        method: ``"affine4"``.
    """

    matrix_fixed_from_moving: FloatArray
    nearest_rigid: RigidTransform
    residuals_mm: FloatArray
    fre_rms_mm: float
    method: str = "affine4"

    def apply(self, points_mm: ArrayLike) -> FloatArray:
        """Map (3,) or (N, 3) moving-frame points with the affine matrix."""
        arr = np.asarray(points_mm, dtype=np.float64)
        M = self.matrix_fixed_from_moving
        if arr.shape == (3,):
            out: FloatArray = M[:3, :3] @ arr + M[:3, 3]
            return out
        return as_points(arr) @ M[:3, :3].T + M[:3, 3]


def register_affine4(fixed: ArrayLike, moving: ArrayLike) -> AffineRegistration:
    """Map MOVING into FIXED through the four-marker affine frames (seed 000 eqs 2-12).

    Args:
        fixed: (4, 3) markers ``M0..M3`` in the FIXED frame, mm.
        moving: (4, 3) the same markers, same order, in the MOVING frame, mm.

    Raises:
        GeometryError: not exactly 4 finite points in each.
        DegenerateConfigurationError: coplanar markers in either set.
    """
    T_fixed_from_affine = affine_frame(fixed, "fixed")
    T_moving_from_affine = affine_frame(moving, "moving")
    M = T_fixed_from_affine @ np.linalg.inv(T_moving_from_affine)
    M[3] = [0.0, 0.0, 0.0, 1.0]
    U, _, Vt = np.linalg.svd(M[:3, :3])
    d = 1.0 if np.linalg.det(U @ Vt) >= 0 else -1.0
    R = U @ np.diag([1.0, 1.0, d]) @ Vt
    nearest = RigidTransform(R, M[:3, 3])
    f = as_points(fixed)
    m = as_points(moving)
    mapped = m @ M[:3, :3].T + M[:3, 3]
    residuals = np.linalg.norm(mapped - f, axis=1)
    fre = math.sqrt(float(np.mean(residuals**2)))
    M.setflags(write=False)
    residuals.setflags(write=False)
    return AffineRegistration(M, nearest, residuals, fre)
