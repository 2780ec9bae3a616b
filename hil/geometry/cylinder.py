"""Axis of a cylindrical instrument (needle, guide tube) from its apparent contour (seed 004 §III).

A straight circular cylinder of known radius ``r_c`` seen by a calibrated camera shows two straight
apparent contour lines ``l+`` and ``l-``. Their back-projections are the two planes through the
camera centre tangent to the cylinder; both contain the axis direction. From them the 4 dof of the
axis — its Plücker coordinates ``(r, w)`` (direction, moment) — follow in closed form:

- seed 004 eq 20: ``C = l- l+^T + l+ l-^T`` (rank 2, symmetric) represents the apparent contour;
- eqs 21-22: ``K^T C K = U diag(lambda1, lambda2, 0) U^T``; the null vector of ``K^T C K`` is the
  axis direction ``r``, the eigenvector of the eigenvalue of larger magnitude is the normal of the
  plane through the camera centre and the axis (its image is the axis of the harmonic homology
  relating the apparent lines, Fig. 7), the other eigenvector points to the axis' closest point;
- eq 23: the distance from the camera centre to the axis is ``||w|| = r_c sqrt(1 + |lambda1 /
  lambda2|)``.

Derivation used for the signs: with ``d = ||w||`` and ``sin(phi) = r_c / d`` the tangent-plane normals
are ``n± = cos(phi) w_hat ± sin(phi) c_hat`` (``c_hat`` towards the axis' closest point), so
``n+ n-^T + n- n+^T = 2 (cos^2 phi w_hat w_hat^T - sin^2 phi c_hat c_hat^T)``: the larger eigenvalue
is ``w_hat``'s whenever ``d > sqrt(2) r_c`` (always, in practice), and ``|lambda1/lambda2| =
cot^2 phi`` gives eq 23. The remaining sign (axis through ``+c`` or ``-c``: both project to the same
contour) is fixed by cheirality: the axis' closest point in front of the camera, or a given image
point of the axis in front.

Two views (:func:`cylinder_axis_two_views`): the plane through each camera centre and the axis
(the ``w_hat`` plane) needs no radius; the two planes intersect in the axis. The radius then
follows from each view, which checks the model.

Lines are homogeneous ``(a, b, c)`` with ``a u + b v + c = 0`` in undistorted pixels.
Millimetres in, millimetres out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.collinear import Line3D, StereoRig, direction_error_deg
from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]

__all__ = [
    "CylinderAxis",
    "TwoViewCylinder",
    "contour_lines",
    "cylinder_axis_from_contours",
    "cylinder_axis_from_view",
    "cylinder_axis_two_views",
    "image_line_through",
]


def _line(l: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(l, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise GeometryError(f"{name} must be 3 finite line coefficients (a, b, c), got {l!r}")
    if math.hypot(float(a[0]), float(a[1])) < 1e-12:
        raise GeometryError(f"{name} is the line at infinity, not an image line")
    return a


def _K(K: ArrayLike) -> FloatArray:
    M = np.asarray(K, dtype=np.float64)
    if M.shape != (3, 3) or not np.all(np.isfinite(M)) or abs(float(np.linalg.det(M))) < 1e-12:
        raise GeometryError("K must be a finite, invertible 3x3 intrinsic matrix")
    return M


def image_line_through(p_px: ArrayLike, q_px: ArrayLike) -> FloatArray:
    """The homogeneous image line through two pixels, normalised to ``a^2 + b^2 = 1``.

    Raises:
        DegenerateConfigurationError: the two pixels coincide.
    """
    p = np.r_[np.asarray(p_px, dtype=np.float64).reshape(2), 1.0]
    q = np.r_[np.asarray(q_px, dtype=np.float64).reshape(2), 1.0]
    l = np.cross(p, q)
    n = math.hypot(float(l[0]), float(l[1]))
    if n < 1e-12:
        raise DegenerateConfigurationError("the two pixels coincide; they define no line")
    return np.asarray(l / n, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class CylinderAxis:
    """A cylinder's axis in a camera (or the optical) frame.

    Attributes:
        axis: the axis line; ``axis.point_mm`` is its point closest to the camera centre, its
            direction is a unit vector (a cylinder's axis has no orientation; it is returned with a
            non-negative z component).
        distance_mm: distance from the camera centre to the axis, ``||w||`` (eq 23).
        radius_mm: the radius used (given) or implied.
        axis_image_line: the image of the axis (pixels, ``a^2 + b^2 = 1``).
        eigenvalues: ``(lambda_large, lambda_small)`` of ``K^T C K`` (eq 22), scale-free ratio only.
    """

    axis: Line3D
    distance_mm: float
    radius_mm: float
    axis_image_line: FloatArray
    eigenvalues: tuple[float, float]

    @property
    def direction(self) -> FloatArray:
        return self.axis.direction

    @property
    def plucker(self) -> tuple[FloatArray, FloatArray]:
        """``(direction, moment_mm)`` with ``moment = point x direction``."""
        return self.axis.direction, self.axis.moment_mm

    def transformed(self, T: RigidTransform) -> CylinderAxis:
        """The axis in another frame (``T`` maps this frame into it); the image line is kept."""
        ax = self.axis.transformed(T)
        return CylinderAxis(ax, self.distance_mm, self.radius_mm, self.axis_image_line, self.eigenvalues)


def _canonical_direction(d: FloatArray) -> FloatArray:
    for k in (2, 0, 1):
        if abs(float(d[k])) > 1e-12:
            return d if d[k] > 0 else -d
    return d


def _decompose(l_plus: FloatArray, l_minus: FloatArray, K: FloatArray) -> tuple[FloatArray, float, float]:
    """Eigen-decomposition of ``K^T C K`` (eqs 20-22). Returns ``(U, lam_large, lam_small)`` with
    columns ``U = [w_hat, c_hat, r]``."""
    a = K.T @ l_plus
    b = K.T @ l_minus
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    if float(np.linalg.norm(np.cross(a, b))) < 1e-12:
        raise DegenerateConfigurationError("the two contour lines coincide: the cylinder is at infinity")
    M = np.outer(a, b) + np.outer(b, a)  # K^T C K, eq 20-21
    lam, V = np.linalg.eigh(M)
    order = np.argsort(-np.abs(lam))  # |large|, |small|, ~0
    lam, V = lam[order], V[:, order]
    if abs(float(lam[1])) < 1e-14:
        raise DegenerateConfigurationError("the two contour lines coincide: the cylinder is at infinity")
    return V, float(lam[0]), float(lam[1])


def cylinder_axis_from_contours(
    l_plus: ArrayLike,
    l_minus: ArrayLike,
    K: ArrayLike,
    radius_mm: float,
    *,
    axis_image_point_px: ArrayLike | None = None,
) -> CylinderAxis:
    """The cylinder axis (4 dof) from its two apparent contour lines in one view (seed 004 eqs 20-23).

    Args:
        l_plus, l_minus: the two contour lines (either order, any scale and sign), undistorted pixels.
        K: 3x3 intrinsics of the ideal camera.
        radius_mm: the cylinder's radius (known).
        axis_image_point_px: optional pixel on the imaged axis (e.g. the middle of the detected
            contour segment) used to pick the solution in front of the camera; default: the axis'
            closest point to the camera centre is taken in front (positive z).

    Returns:
        :class:`CylinderAxis` in the camera frame.

    Raises:
        GeometryError: bad shapes, non-finite values, radius <= 0.
        DegenerateConfigurationError: coincident contour lines (no depth).
    """
    lp, lm = _line(l_plus, "l_plus"), _line(l_minus, "l_minus")
    Kc = _K(K)
    r_c = float(radius_mm)
    if not (math.isfinite(r_c) and r_c > 0):
        raise GeometryError(f"radius_mm must be a positive number, got {radius_mm!r}")
    U, lam_l, lam_s = _decompose(lp, lm, Kc)
    w_hat, c_hat, r = U[:, 0], U[:, 1], U[:, 2]
    dist = r_c * math.sqrt(1.0 + abs(lam_l / lam_s))  # eq 23
    c = dist * c_hat
    if axis_image_point_px is not None:
        q = np.r_[np.asarray(axis_image_point_px, dtype=np.float64).reshape(2), 1.0]
        k = np.linalg.solve(Kc, q)
        # mu k = c + sigma r  ->  least squares in (mu, sigma); keep the sign with mu > 0
        A = np.column_stack([k, -r])
        mu = float(np.linalg.lstsq(A, c, rcond=None)[0][0])
        if mu < 0:
            c = -c
    elif c[2] < 0:
        c = -c
    l_axis = np.linalg.solve(Kc.T, w_hat)  # K^-T w_hat
    l_axis = l_axis / math.hypot(float(l_axis[0]), float(l_axis[1]))
    l_axis_px = np.asarray(l_axis, dtype=np.float64)
    return CylinderAxis(Line3D(c, _canonical_direction(r)), dist, r_c, l_axis_px, (lam_l, lam_s))


def cylinder_axis_from_view(
    cal: StereoRig, side: str, l_plus: ArrayLike, l_minus: ArrayLike, radius_mm: float
) -> CylinderAxis:
    """:func:`cylinder_axis_from_contours` for one camera of a rig, returned in the optical frame.
    The lines are in that camera's undistorted pixels."""
    K, _, R, t = cal.camera(side)
    ax = cylinder_axis_from_contours(l_plus, l_minus, K, radius_mm)
    out = ax.transformed(RigidTransform(R, t).inverse())
    return CylinderAxis(
        Line3D(out.axis.point_mm, _canonical_direction(out.axis.direction)),
        out.distance_mm,
        out.radius_mm,
        out.axis_image_line,
        out.eigenvalues,
    )


def contour_lines(K: ArrayLike, axis: Line3D, radius_mm: float) -> tuple[FloatArray, FloatArray]:
    """Forward model: the two apparent contour lines (``a^2 + b^2 = 1``) of a cylinder of axis
    ``axis`` (camera frame) and radius ``radius_mm`` in the ideal camera ``K``: ``l± = K^-T n±`` with
    the tangent-plane normals ``n± = cos(phi) w_hat ± sin(phi) c_hat``, ``sin(phi) = r_c / d``.

    Raises:
        DegenerateConfigurationError: the camera centre is inside (or on) the cylinder.
    """
    Kc = _K(K)
    w = axis.moment_mm
    d = float(np.linalg.norm(w))
    if d <= radius_mm:
        raise DegenerateConfigurationError("the camera centre is inside the cylinder: no apparent contour")
    w_hat = w / d
    c_hat = axis.closest_point_to_origin() / d
    sphi = radius_mm / d
    cphi = math.sqrt(1.0 - sphi * sphi)
    out = []
    for sgn in (1.0, -1.0):
        n = cphi * w_hat + sgn * sphi * c_hat
        l = np.linalg.solve(Kc.T, n)
        out.append(np.asarray(l / math.hypot(float(l[0]), float(l[1])), dtype=np.float64))
    return out[0], out[1]


@dataclass(frozen=True, eq=False)
class TwoViewCylinder:
    """The axis from two views, in the optical (left camera) frame.

    axis: intersection of the two planes (camera centre, imaged axis) — needs no radius.
    plane_angle_deg: angle between those planes; small means the axis is close to an epipolar
        plane and the intersection is ill-conditioned.
    radius_left_mm / radius_right_mm: the radius implied by each view for that axis.
    left / right: the monocular estimates (when a radius was given), in the optical frame.
    mono_angle_deg: angle between the monocular estimates' directions (NaN without a radius).
    """

    axis: Line3D
    plane_angle_deg: float
    radius_left_mm: float
    radius_right_mm: float
    left: CylinderAxis | None
    right: CylinderAxis | None
    mono_angle_deg: float


def _implied_radius(lam_l: float, lam_s: float, dist_mm: float) -> float:
    # sin^2(phi) = |lam_s| / (|lam_s| + |lam_l|), r_c = d sin(phi)
    return dist_mm * math.sqrt(abs(lam_s) / (abs(lam_s) + abs(lam_l)))


def cylinder_axis_two_views(
    cal: StereoRig,
    lines_left: ArrayLike,
    lines_right: ArrayLike,
    radius_mm: float | None = None,
    *,
    min_plane_angle_deg: float = 2.0,
) -> TwoViewCylinder:
    """The cylinder axis from its contour lines in both views of a calibrated rig.

    Args:
        cal: the rig (``hil.vision.camera_model.StereoCalibration``).
        lines_left, lines_right: (2, 3) the two contour lines in each view (undistorted pixels).
        radius_mm: if given, the monocular estimates are also computed and returned.
        min_plane_angle_deg: below this angle between the two axis planes the intersection is
            refused (the axis lies nearly in an epipolar plane).

    Raises:
        GeometryError: bad shapes / values.
        DegenerateConfigurationError: coincident contour lines, or the axis planes are nearly the
            same plane (then use a monocular estimate with a known radius).
    """
    Ll = np.asarray(lines_left, dtype=np.float64).reshape(-1)
    Lr = np.asarray(lines_right, dtype=np.float64).reshape(-1)
    if Ll.shape != (6,) or Lr.shape != (6,):
        raise GeometryError("lines_left and lines_right must each be two lines (2, 3)")
    lines = {
        "left": (_line(Ll[:3], "lines_left[0]"), _line(Ll[3:], "lines_left[1]")),
        "right": (_line(Lr[:3], "lines_right[0]"), _line(Lr[3:], "lines_right[1]")),
    }
    normals: dict[str, FloatArray] = {}
    centres: dict[str, FloatArray] = {}
    lams: dict[str, tuple[float, float]] = {}
    for side in ("left", "right"):
        K, _, R, t = cal.camera(side)
        U, lam_l, lam_s = _decompose(*lines[side], _K(K))
        normals[side] = np.asarray(R.T @ U[:, 0], dtype=np.float64)  # optical frame
        centres[side] = np.asarray(-R.T @ t, dtype=np.float64)
        lams[side] = (lam_l, lam_s)
    nl, nr = normals["left"], normals["right"]
    direction = np.cross(nl, nr)
    sin_a = float(np.linalg.norm(direction))
    plane_angle = math.degrees(math.asin(min(1.0, sin_a)))
    if plane_angle < min_plane_angle_deg:
        raise DegenerateConfigurationError(
            f"the axis planes of the two views meet at {plane_angle:.3f} deg (< {min_plane_angle_deg}):"
            " the axis lies close to an epipolar plane"
        )
    direction = direction / sin_a
    A = np.vstack([nl, nr, direction])
    rhs = np.array([float(nl @ centres["left"]), float(nr @ centres["right"]), 0.0])
    point = np.linalg.solve(A, rhs)
    axis = Line3D(point, _canonical_direction(direction))
    radii = {
        side: _implied_radius(*lams[side], float(axis.distance_to(centres[side])[0]))
        for side in ("left", "right")
    }
    left = right = None
    mono = float("nan")
    if radius_mm is not None:
        left = cylinder_axis_from_view(cal, "left", *lines["left"], radius_mm)
        right = cylinder_axis_from_view(cal, "right", *lines["right"], radius_mm)
        mono = direction_error_deg(left.direction, right.direction, oriented=False)
    return TwoViewCylinder(axis, plane_angle, radii["left"], radii["right"], left, right, mono)
