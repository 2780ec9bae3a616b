"""The planimetric method of seed 002 (eqs 3-16): planes probed with a pointer define a frame.

- :func:`fit_plane` — least-squares plane through >= 3 probed points (eqs 3-5 in point-normal
  form ``A(x - x0) + B(y - y0) + C(z - z0) = 0``).
- :func:`intersect_planes` — the point ``P`` common to three planes (eq 6,
  ``P = R^-1 [a_α, b_β, c_γ]^T``).
- :func:`planimetric_frame` — the frame ``O'{x', y', z'}`` (eqs 8-12): ``z'`` along the normal of
  plane α, origin ``O'`` where the line through a probed point ``D`` along that normal meets plane
  α, ``y'`` towards ``P``, ``x' = y' × z'`` (eq 11 writes ``l = m × n``), assembled into
  ``T_measure_from_frame`` (eq 12).

All points in mm in one measuring frame (the optical frame ``M`` in the paper).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.registration import check_point_configuration
from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]

#: Smallest singular value (relative) of the normals matrix below which planes count as dependent.
PLANES_REL_TOL = 1e-6


@dataclass(frozen=True)
class Plane:
    """A plane ``normal · (x - point_mm) = 0``.

    Attributes:
        normal: (3,) unit normal (the paper's ``(A, B, C)`` normalised).
        point_mm: (3,) a point on the plane (the centroid of the fitted points).
        rms_mm: RMS distance of the fitted points from the plane (0 for a constructed plane).
    """

    normal: FloatArray
    point_mm: FloatArray
    rms_mm: float = 0.0

    @property
    def offset_mm(self) -> float:
        """``normal · point`` — the paper's ``a_α = A x_α + B y_α + C z_α`` (eq 7)."""
        return float(self.normal @ self.point_mm)

    def distance_mm(self, points_mm: ArrayLike) -> FloatArray:
        """Signed distances of (N, 3) or (3,) points from the plane, mm (positive along the normal)."""
        pts = np.asarray(points_mm, dtype=np.float64)
        out: FloatArray = (pts - self.point_mm) @ self.normal
        return out


def fit_plane(points_mm: ArrayLike, orient_towards: ArrayLike | None = None) -> Plane:
    """Least-squares plane through probed points (seed 002 eqs 3-5: "no less than three points").

    The normal is the right singular vector of the centred points with the smallest singular
    value (total least squares). Its sign is arbitrary unless ``orient_towards`` (a (3,) direction)
    is given, in which case the normal is flipped to have a non-negative component along it.

    Raises:
        GeometryError: < 3 points, NaN/inf.
        DegenerateConfigurationError: collinear or coincident points (no unique plane).
    """
    pts = check_point_configuration(points_mm, "plane points")
    centroid = pts.mean(axis=0)
    _, sv, Vt = np.linalg.svd(pts - centroid)
    normal = Vt[2].copy()
    if orient_towards is not None:
        hint = np.asarray(orient_towards, dtype=np.float64).reshape(-1)
        if hint.shape != (3,) or not np.all(np.isfinite(hint)):
            raise GeometryError(f"orient_towards must be 3 finite values, got {orient_towards!r}")
        if float(normal @ hint) < 0:
            normal = -normal
    rms = float(sv[2]) / math.sqrt(pts.shape[0]) if sv.shape[0] > 2 else 0.0
    return Plane(normal=normal, point_mm=centroid, rms_mm=rms)


def intersect_planes(alpha: Plane, beta: Plane, gamma: Plane) -> FloatArray:
    """The common point of three planes (seed 002 eq 6): solve ``R P = [a_α, b_β, c_γ]``.

    Raises:
        DegenerateConfigurationError: two planes parallel or all three through one line.
    """
    R = np.vstack([alpha.normal, beta.normal, gamma.normal])
    rhs = np.array([alpha.offset_mm, beta.offset_mm, gamma.offset_mm])
    sv = np.linalg.svd(R, compute_uv=False)
    if sv[2] <= PLANES_REL_TOL * sv[0]:
        raise DegenerateConfigurationError("the three planes do not meet in a single point")
    P: FloatArray = np.linalg.solve(R, rhs)
    return P


def line_plane_intersection(point_mm: ArrayLike, direction: ArrayLike, plane: Plane) -> FloatArray:
    """Where the line ``point + s * direction`` meets ``plane`` (seed 002: ``O'`` from eq 8 and α).

    Raises:
        DegenerateConfigurationError: the line is parallel to the plane.
    """
    p = np.asarray(point_mm, dtype=np.float64).reshape(3)
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    denom = float(plane.normal @ d)
    nd = float(np.linalg.norm(d))
    if nd == 0.0 or abs(denom) <= 1e-12 * nd:
        raise DegenerateConfigurationError("the line is parallel to the plane")
    s = (plane.offset_mm - float(plane.normal @ p)) / denom
    out: FloatArray = p + s * d
    return out


def planimetric_frame(alpha: Plane, point_D_mm: ArrayLike, point_P_mm: ArrayLike) -> RigidTransform:
    """``T_measure_from_frame`` of seed 002 eqs 8-12.

    Args:
        alpha: the reference plane (its normal gives ``z'``, eq 8).
        point_D_mm: a probed point (the cutter end ``D``); ``O'`` is its foot on plane α.
        point_P_mm: the point ``y'`` points to (the three-plane intersection ``P``, eq 6).

    Returns:
        Rigid transform whose columns are the unit axes ``x' = y' × z'``, ``y'`` (``O'P``
        projected onto α), ``z'`` (α's normal), with origin ``O'`` (eq 12).

    Raises:
        DegenerateConfigurationError: ``P`` projects onto ``O'`` (no ``y'`` direction).
    """
    n = alpha.normal / float(np.linalg.norm(alpha.normal))
    O = line_plane_intersection(point_D_mm, n, alpha)
    P = np.asarray(point_P_mm, dtype=np.float64).reshape(3)
    m = P - O
    m = m - float(m @ n) * n  # P lies on α in the paper; project to stay orthogonal under noise
    mn = float(np.linalg.norm(m))
    if mn <= 1e-9 * max(1.0, float(np.linalg.norm(P))):
        raise DegenerateConfigurationError("P coincides with O' on plane α; the y' axis is undefined")
    y = m / mn
    x = np.cross(y, n)  # eq 11: l = m × n
    R = np.column_stack([x / np.linalg.norm(x), y, n])
    return RigidTransform(R, O)
