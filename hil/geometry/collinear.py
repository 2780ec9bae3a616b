"""Pose of an instrument carrying collinear markers, and depth by the cross-ratio (seed 004 §II-A).

An instrument (a needle guide, a laparoscopic tool) carries ``n >= 3`` point markers on its axis at
known coordinates ``s_i`` (mm along the axis, e.g. measured from the tip). One calibrated view
fixes the 5 dof of the axis — position and direction, not the roll about it:

- :func:`collinear_pose` — Haralick's linear formulation (seed 004 eqs 1-6): the homogeneous system
  ``[A_r A_t] [r; t] = 0`` minimised under ``r^T r = 1``; ``r`` is the eigenvector of the smallest
  eigenvalue of ``E = A_r^T (I - A_t (A_t^T A_t)^-1 A_t^T) A_r`` (eq 6), ``t = -(A_t^T A_t)^-1 A_t^T
  A_r r``; the twofold sign ambiguity is removed by positive depth. As the paper recommends (end of
  §II-A.1, citing Hartley), the image points are normalised by an affine transform (centroid to the
  origin, mean distance sqrt(2)) and the axis coordinates are centred and scaled. Measured here:
  this lowers the condition number of ``[A_r A_t]`` (about 2x) but, being isotropic, it scales each
  point's two rows uniformly and only moves the axis origin, so eq 6's eigenvector — the estimate —
  is unchanged (tests/pose004: identical to 1e-9 under noise). The method's noise sensitivity for
  close markers is intrinsic to one view (docs/pose004.md), not a conditioning artefact.
- :func:`axis_coordinate_from_cross_ratio` / :func:`tip_to_surface_distance_mm` — seed 004 §II-A.2
  eqs 7-12: a fourth collinear image point (a laser spot on the organ, the tip) is placed on the axis
  by the projective invariance of the cross-ratio; no camera calibration is needed beyond
  undistortion.
- :func:`collinear_pose_stereo` — the same markers triangulated in both views of the stereo rig and
  fitted with their known spacing; :func:`axis_agreement` compares it with the monocular estimate.
- :func:`direction_error_deg` / :func:`axis_path_error` — the measured axis against a planned path.

Also holds :class:`Line3D`, the 3-D line (Plücker) type shared with :mod:`hil.geometry.cylinder`.
All positions in millimetres, image coordinates in pixels, angles in degrees where named ``_deg``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.transform import RigidTransform
from hil.geometry.triangulation import triangulate_dlt

FloatArray = NDArray[np.float64]


class StereoRig(Protocol):
    """What the convenience wrappers need of a calibrated rig (``hil.vision.camera_model.
    StereoCalibration`` satisfies it); geometry does not import the vision layer."""

    @property
    def K_left(self) -> FloatArray: ...
    @property
    def K_right(self) -> FloatArray: ...
    @property
    def R_right_from_left(self) -> FloatArray: ...
    @property
    def t_right_from_left_mm(self) -> FloatArray: ...
    def undistort_points(self, side: str, uv_px: ArrayLike) -> FloatArray: ...
    def camera(self, side: str) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]: ...
    def P_left(self) -> FloatArray: ...
    def P_right(self) -> FloatArray: ...


__all__ = [
    "AxisAgreement",
    "CollinearPose",
    "Line3D",
    "PathError",
    "StereoRig",
    "axis_agreement",
    "axis_coordinate_from_cross_ratio",
    "axis_path_error",
    "collinear_pose",
    "collinear_pose_from_view",
    "collinear_pose_stereo",
    "cross_ratio",
    "direction_error_deg",
    "fit_line_3d",
    "hartley_normalization",
    "image_line_coordinates",
    "tip_to_surface_distance_mm",
]


# ---------------------------------------------------------------------- small validators
def _vec3(v: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise GeometryError(f"{name} must be 3 finite values, got {v!r}")
    return a


def _unit(v: ArrayLike, name: str) -> FloatArray:
    a = _vec3(v, name)
    n = float(np.linalg.norm(a))
    if n < 1e-12:
        raise GeometryError(f"{name} is the zero vector")
    return a / n


def _uv(uv: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(uv, dtype=np.float64)
    if a.ndim == 3 and a.shape[1] == 1:
        a = a[:, 0, :]
    if a.ndim == 1 and a.shape[0] == 2:
        a = a[np.newaxis]
    if a.ndim != 2 or a.shape[1] != 2:
        raise GeometryError(f"{name} must have shape (N, 2), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise GeometryError(f"{name} contains NaN or infinite values")
    return a


def _K(K: ArrayLike) -> FloatArray:
    M = np.asarray(K, dtype=np.float64)
    if M.shape != (3, 3) or not np.all(np.isfinite(M)) or abs(float(np.linalg.det(M))) < 1e-12:
        raise GeometryError("K must be a finite, invertible 3x3 intrinsic matrix")
    return M


def _positions(s: ArrayLike, n: int, name: str = "positions_mm") -> FloatArray:
    a = np.asarray(s, dtype=np.float64).reshape(-1)
    if a.shape != (n,):
        raise GeometryError(f"{name} must hold one axis coordinate per marker ({n}), got {a.shape[0]}")
    if not np.all(np.isfinite(a)):
        raise GeometryError(f"{name} contains NaN or infinite values")
    d = np.abs(a[:, None] - a[None, :])
    np.fill_diagonal(d, np.inf)
    if float(d.min()) < 1e-9:
        raise DegenerateConfigurationError(f"{name}: two markers share the same axis coordinate")
    return a


# ---------------------------------------------------------------------- 3-D line
@dataclass(frozen=True, eq=False)
class Line3D:
    """An infinite 3-D line: a point on it (mm) and a unit direction.

    Plücker coordinates are ``(direction, moment_mm)`` with ``moment = point x direction``
    (independent of the point chosen). Seed 004 §IV writes the moment the other way round,
    ``w = y x OP = -moment``; :mod:`hil.geometry.stereotaxy` uses the paper's sign explicitly.

    Raises:
        GeometryError: non-finite values or a zero direction.
    """

    point_mm: FloatArray
    direction: FloatArray

    def __post_init__(self) -> None:
        p = _vec3(self.point_mm, "point_mm")
        d = _unit(self.direction, "direction")
        p.setflags(write=False)
        d.setflags(write=False)
        object.__setattr__(self, "point_mm", p)
        object.__setattr__(self, "direction", d)

    @classmethod
    def through(cls, a_mm: ArrayLike, b_mm: ArrayLike) -> Line3D:
        """The line through two distinct points, directed from ``a`` to ``b``."""
        a, b = _vec3(a_mm, "a_mm"), _vec3(b_mm, "b_mm")
        if float(np.linalg.norm(b - a)) < 1e-12:
            raise DegenerateConfigurationError("the two points coincide; they define no line")
        return cls(a, b - a)

    @classmethod
    def from_plucker(cls, direction: ArrayLike, moment_mm: ArrayLike) -> Line3D:
        """From Plücker coordinates ``(d, m)`` with ``m = p x d`` (``d`` any non-zero length)."""
        d = _vec3(direction, "direction")
        m = _vec3(moment_mm, "moment_mm")
        nd = float(np.linalg.norm(d))
        if nd < 1e-12:
            raise GeometryError("direction is the zero vector")
        d, m = d / nd, m / nd
        if abs(float(d @ m)) > 1e-6 * max(1.0, float(np.linalg.norm(m))):
            raise GeometryError("Plücker coordinates violate d . m = 0")
        return cls(np.cross(d, m), d)

    @property
    def moment_mm(self) -> FloatArray:
        """``point x direction`` (mm); its norm is the distance from the origin to the line."""
        return np.asarray(np.cross(self.point_mm, self.direction), dtype=np.float64)

    def closest_point_to_origin(self) -> FloatArray:
        return np.asarray(np.cross(self.direction, self.moment_mm), dtype=np.float64)

    def project(self, points_mm: ArrayLike) -> FloatArray:
        """Orthogonal projections of (N, 3) points onto the line, (N, 3)."""
        p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        s = (p - self.point_mm) @ self.direction
        return np.asarray(self.point_mm + s[:, None] * self.direction, dtype=np.float64)

    def distance_to(self, points_mm: ArrayLike) -> FloatArray:
        """Distances (N,) of (N, 3) points to the line, mm."""
        p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        return np.asarray(np.linalg.norm(np.cross(p - self.point_mm, self.direction), axis=1))

    def transformed(self, T: RigidTransform) -> Line3D:
        """The line mapped by ``T`` (``T_b_from_a`` maps a line in frame a into frame b)."""
        return Line3D(T.apply(self.point_mm), T.R @ self.direction)

    def reversed(self) -> Line3D:
        return Line3D(self.point_mm, -self.direction)


def fit_line_3d(points_mm: ArrayLike) -> Line3D:
    """Total-least-squares line through (N >= 2) points: centroid and principal direction.

    The direction is oriented from the first point towards the last.

    Raises:
        GeometryError: fewer than 2 points or non-finite values.
        DegenerateConfigurationError: all points coincide.
    """
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] < 2 or not np.all(np.isfinite(p)):
        raise GeometryError("a line fit needs at least 2 finite points")
    c = p.mean(axis=0)
    _, sv, Vt = np.linalg.svd(p - c)
    if sv[0] < 1e-12:
        raise DegenerateConfigurationError("all points coincide; they define no line")
    d = Vt[0]
    if float((p[-1] - p[0]) @ d) < 0:
        d = -d
    return Line3D(c, d)


# ---------------------------------------------------------------------- pose, seed 004 eqs 1-6
def hartley_normalization(uv_px: ArrayLike) -> FloatArray:
    """The 3x3 affine normalisation of seed 004 §II-A.1 (its ref [16], Hartley): translate the
    centroid of the (N, 2) points to the origin and scale isotropically so that their mean distance
    from it is sqrt(2). Returns ``N`` with ``q_normalised = N q`` (homogeneous)."""
    uv = _uv(uv_px, "uv_px")
    c = uv.mean(axis=0)
    mean_dist = float(np.mean(np.linalg.norm(uv - c, axis=1)))
    if mean_dist < 1e-12:
        raise DegenerateConfigurationError("all image points coincide")
    s = math.sqrt(2.0) / mean_dist
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class CollinearPose:
    """5-dof pose of a marker axis in a camera frame (mm).

    Attributes:
        origin_mm: the 3-D point of axis coordinate 0 (e.g. the tip when ``s`` is measured from it).
        direction: unit vector towards increasing axis coordinate.
        positions_mm: the markers' axis coordinates used (N,).
        markers_mm: the markers' 3-D positions (N, 3), ``origin + s_i * direction``.
        reprojection_px: per-marker image residual (N,) (for the monocular estimate; for the stereo
            one, the mean of the two views).
        condition_number: of the (normalised) linear system ``[A_r A_t]`` on the complement of its
            null direction (largest / fifth singular value); NaN for stereo.
        method: "haralick_normalized", "haralick" or "stereo".
    """

    origin_mm: FloatArray
    direction: FloatArray
    positions_mm: FloatArray
    markers_mm: FloatArray
    reprojection_px: FloatArray
    condition_number: float
    method: str

    @property
    def axis(self) -> Line3D:
        return Line3D(self.origin_mm, self.direction)

    def point_at(self, s_mm: float) -> FloatArray:
        """The 3-D point at axis coordinate ``s_mm`` (same origin as ``positions_mm``)."""
        return np.asarray(self.origin_mm + float(s_mm) * self.direction, dtype=np.float64)

    def transformed(self, T: RigidTransform) -> CollinearPose:
        """The same pose expressed in another frame (``T`` maps this frame into it)."""
        return CollinearPose(
            T.apply(self.origin_mm),
            T.R @ self.direction,
            self.positions_mm,
            T.apply(self.markers_mm),
            self.reprojection_px,
            self.condition_number,
            self.method,
        )


def _project(K: FloatArray, pts: FloatArray) -> FloatArray:
    h = pts @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(h[:, :2] / h[:, 2:3], dtype=np.float64)


def collinear_pose(
    uv_px: ArrayLike, positions_mm: ArrayLike, K: ArrayLike, *, normalize: bool = True
) -> CollinearPose:
    """Position and direction of ``n >= 3`` collinear markers from one ideal (undistorted) view.

    Seed 004 eqs 1-6 (Haralick's linear method): each marker ``P_i = t + s_i r`` projects to
    ``q_i ~ K P_i``; the two rows ``[[1, 0, -u_i], [0, 1, -v_i]] K`` (eq 5) applied to ``s_i r + t``
    vanish. ``r`` is the unit eigenvector of the smallest eigenvalue of ``E`` (eq 6) and ``t`` follows
    linearly. The sign of ``(r, t)`` is fixed by positive depth of the markers' centroid (the paper's
    "third component of t strictly positive").

    With ``normalize`` (default, as the paper advises) the image points go through
    :func:`hartley_normalization` (``K`` becomes ``N K``) and the axis coordinates are centred and
    scaled to unit RMS; for exact data both variants give the same answer.

    Args:
        uv_px: (N, 2) undistorted pixel positions of the markers, in the order of ``positions_mm``.
        positions_mm: (N,) axis coordinates of the markers, distinct (spacing known, seed 004 "λ_i").
        K: 3x3 intrinsics of the ideal camera.

    Returns:
        :class:`CollinearPose` in the camera frame.

    Raises:
        GeometryError: shapes, counts (N >= 3), non-finite values.
        DegenerateConfigurationError: coincident markers/image points, or the markers' centroid
            would be behind the camera for both signs (cannot happen with real data).
    """
    uv = _uv(uv_px, "uv_px")
    n = uv.shape[0]
    if n < 3:
        raise GeometryError(f"collinear pose needs at least 3 markers, got {n}")
    s = _positions(positions_mm, n)
    Kc = _K(K)
    if normalize:
        Nm = hartley_normalization(uv)
        q = np.column_stack([uv, np.ones(n)]) @ Nm.T
        M = Nm @ Kc
        c = float(s.mean())
        sigma = float(np.sqrt(np.mean((s - c) ** 2)))
    else:
        q = np.column_stack([uv, np.ones(n)])
        M = Kc
        c, sigma = float(s[0]), 1.0  # the paper: the first point is the origin, lambda_1 = 0
    mu = (s - c) / sigma
    B = np.empty((n, 2, 3))
    B[:, 0] = M[0] - q[:, :1] * M[2]
    B[:, 1] = M[1] - q[:, 1:2] * M[2]
    A_t = B.reshape(2 * n, 3)
    A_r = (B * mu[:, None, None]).reshape(2 * n, 3)
    sv = np.linalg.svd(np.hstack([A_r, A_t]), compute_uv=False)
    cond = float(sv[0] / sv[4]) if sv[4] > 0 else float("inf")  # the 6th is the solution's null
    Q, Rq = np.linalg.qr(A_t)
    if abs(float(np.linalg.det(Rq))) < 1e-12 * max(1.0, float(np.abs(Rq).max())) ** 3:
        raise DegenerateConfigurationError("the image points do not fix the instrument position")
    QtAr = Q.T @ A_r
    E = A_r.T @ A_r - QtAr.T @ QtAr  # eq 6 without forming the projector
    _, V = np.linalg.eigh(E)
    r = V[:, 0]
    t_n = -np.linalg.solve(Rq, QtAr @ r)  # t = -(A_t^T A_t)^-1 A_t^T A_r r
    centre = sigma * t_n + (float(s.mean()) - c) * r
    if centre[2] < 0:
        r, t_n, centre = -r, -t_n, -centre
    if centre[2] <= 0:
        raise DegenerateConfigurationError("the markers have no solution in front of the camera")
    origin = sigma * t_n - c * r
    markers = origin + s[:, None] * r
    resid = np.linalg.norm(_project(Kc, markers) - uv, axis=1)
    return CollinearPose(
        origin, r, s, markers, resid, cond, "haralick_normalized" if normalize else "haralick"
    )


def collinear_pose_from_view(
    cal: StereoRig, side: str, uv_px: ArrayLike, positions_mm: ArrayLike, *, normalize: bool = True
) -> CollinearPose:
    """:func:`collinear_pose` from a raw (distorted) image of one camera of ``cal``, returned in the
    optical (left camera) frame. ``side`` is "left" or "right".

    Raises:
        GeometryError / DegenerateConfigurationError: as :func:`collinear_pose`.
    """
    uv = cal.undistort_points(side, _uv(uv_px, "uv_px"))
    K, _, R, t = cal.camera(side)
    pose = collinear_pose(uv, positions_mm, K, normalize=normalize)
    T_optical_from_cam = RigidTransform(R, t).inverse()
    return pose.transformed(T_optical_from_cam)


def collinear_pose_stereo(
    cal: StereoRig, uv_left_px: ArrayLike, uv_right_px: ArrayLike, positions_mm: ArrayLike
) -> CollinearPose:
    """The markers triangulated in both views (DLT on undistorted pixels) and fitted with their known
    axis coordinates: least squares ``min sum |P_i - o - s_i r|^2`` with ``r`` then normalised.
    Returned in the optical frame; ``reprojection_px`` is the mean residual of the two views.

    Raises:
        GeometryError: shapes/counts (N >= 2 per view, equal), non-finite values.
        DegenerateConfigurationError: parallel rays, coincident markers.
    """
    uv_l = _uv(uv_left_px, "uv_left_px")
    uv_r = _uv(uv_right_px, "uv_right_px")
    n = uv_l.shape[0]
    if uv_r.shape[0] != n or n < 2:
        raise GeometryError(f"need the same N >= 2 markers in both views, got {n} and {uv_r.shape[0]}")
    s = _positions(positions_mm, n)
    ul = cal.undistort_points("left", uv_l)
    ur = cal.undistort_points("right", uv_r)
    P = triangulate_dlt(cal.P_left(), cal.P_right(), ul, ur)
    sc = s - s.mean()
    r_raw = (sc @ (P - P.mean(axis=0))) / float(sc @ sc)
    nr = float(np.linalg.norm(r_raw))
    if nr < 1e-12:
        raise DegenerateConfigurationError("triangulated markers do not span a direction")
    r = r_raw / nr
    origin = P.mean(axis=0) - float(s.mean()) * r
    markers = origin + s[:, None] * r
    res_l = np.linalg.norm(_project(cal.K_left, markers) - ul, axis=1)
    m_r = markers @ cal.R_right_from_left.T + cal.t_right_from_left_mm
    res_r = np.linalg.norm(_project(cal.K_right, m_r) - ur, axis=1)
    return CollinearPose(origin, r, s, markers, 0.5 * (res_l + res_r), float("nan"), "stereo")


@dataclass(frozen=True)
class AxisAgreement:
    """Two estimates of the same axis compared: angle between directions (deg, oriented) and the
    distance between their marker positions (max over the markers, mm)."""

    angle_deg: float
    max_marker_offset_mm: float
    centroid_offset_mm: float


def axis_agreement(a: CollinearPose, b: CollinearPose) -> AxisAgreement:
    """Compare two :class:`CollinearPose` of the same markers (e.g. monocular vs stereo), same frame.

    Raises:
        GeometryError: the two poses were computed for different marker coordinates.
    """
    if a.positions_mm.shape != b.positions_mm.shape or not np.allclose(a.positions_mm, b.positions_mm):
        raise GeometryError("the two poses use different marker axis coordinates")
    d = np.linalg.norm(a.markers_mm - b.markers_mm, axis=1)
    return AxisAgreement(
        direction_error_deg(a.direction, b.direction),
        float(d.max()),
        float(np.linalg.norm(a.markers_mm.mean(axis=0) - b.markers_mm.mean(axis=0))),
    )


# ---------------------------------------------------------------------- cross-ratio, eqs 7-12
def cross_ratio(a: float, b: float, c: float, d: float) -> float:
    """Cross-ratio ``(a, b; c, d) = ((c - a)(d - b)) / ((c - b)(d - a))`` of four 1-D coordinates
    (invariant under any 1-D homography, hence under perspective projection of a line).

    Raises:
        DegenerateConfigurationError: two of the points coincide.
    """
    den = (c - b) * (d - a)
    if abs(den) < 1e-300 or c == b or d == a:
        raise DegenerateConfigurationError("cross-ratio undefined: two points coincide")
    return (c - a) * (d - b) / den


def image_line_coordinates(uv_px: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Seed 004 eqs 9-11: the image line ``delta`` through (N >= 2) points (total least squares),
    ``[a, b, c]`` with ``a u + b v + c = 0`` and ``a^2 + b^2 = 1``, and each point's 1-D coordinate
    along it (the projection on the direction ``(-b, a)``), so cross-ratios become ratios of
    differences of these coordinates.

    Returns:
        ``(coordinates_px (N,), line (3,))``.
    """
    uv = _uv(uv_px, "uv_px")
    if uv.shape[0] < 2:
        raise GeometryError("an image line needs at least 2 points")
    c0 = uv.mean(axis=0)
    _, sv, Vt = np.linalg.svd(uv - c0)
    if sv[0] < 1e-12:
        raise DegenerateConfigurationError("all image points coincide")
    direction = Vt[0]
    if float((uv[-1] - uv[0]) @ direction) < 0:
        direction = -direction
    a, b = float(direction[1]), float(-direction[0])  # normal (a, b), direction (-b, a)
    line = np.array([a, b, -(a * c0[0] + b * c0[1])])
    return np.asarray((uv - c0) @ direction, dtype=np.float64), line


def _homography_1d(x: FloatArray, y: FloatArray) -> FloatArray:
    """2x2 H (up to scale) with ``y ~ (h00 x + h01) / (h10 x + h11)``, least squares (DLT, normalised)."""
    mx, sx = float(x.mean()), float(np.std(x)) or 1.0
    my, sy = float(y.mean()), float(np.std(y)) or 1.0
    xn, yn = (x - mx) / sx, (y - my) / sy
    A = np.column_stack([xn, np.ones_like(xn), -yn * xn, -yn])
    _, _, Vt = np.linalg.svd(A)
    h = Vt[-1]
    Hn = np.array([[h[0], h[1]], [h[2], h[3]]])
    Tx = np.array([[1 / sx, -mx / sx], [0.0, 1.0]])
    Ty_inv = np.array([[sy, my], [0.0, 1.0]])
    return np.asarray(Ty_inv @ Hn @ Tx, dtype=np.float64)


def axis_coordinate_from_cross_ratio(
    uv_markers_px: ArrayLike, positions_mm: ArrayLike, uv_point_px: ArrayLike
) -> float:
    """Axis coordinate (mm, same origin as ``positions_mm``) of a further image point on the
    instrument's image line — the laser spot on the organ, the tip (seed 004 §II-A.2).

    With 3 markers this is eqs 7-8: ``tau = (p p2 / p1 p2) / (p p3 / p1 p3)`` from the image
    coordinates along the line (eqs 9-12), and with ``l2 = s2 - s1``, ``l3 = s3 - s1`` the 3-D
    coordinate is ``s = s1 + l2 l3 (1 - tau) / (l3 - tau l2)``. With more markers the 1-D homography
    between image and axis coordinates is fitted by least squares (it is exact through 3 points, so
    it reduces to the cross-ratio). Needs undistorted pixels, no other calibration.

    Raises:
        GeometryError: shapes/counts (N >= 3), non-finite values.
        DegenerateConfigurationError: coincident points, or the point maps to infinity (it is the
            vanishing point of the axis).
    """
    uv = _uv(uv_markers_px, "uv_markers_px")
    n = uv.shape[0]
    if n < 3:
        raise GeometryError(f"cross-ratio depth needs at least 3 markers, got {n}")
    s = _positions(positions_mm, n)
    p = _uv(uv_point_px, "uv_point_px")
    coords, _ = image_line_coordinates(np.vstack([uv, p]))
    x, xp = coords[:n], float(coords[n])
    if n == 3:
        # eq 7 with signed image coordinates: tau = ((x2 - xp)/(x2 - x1)) / ((x3 - xp)/(x3 - x1))
        x1, x2, x3 = (float(v) for v in x)
        den = (x3 - xp) * (x2 - x1)
        if abs(den) < 1e-12 or abs(x3 - x1) < 1e-12:
            raise DegenerateConfigurationError("cross-ratio undefined: image points coincide")
        tau = (x2 - xp) * (x3 - x1) / den
        l2, l3 = float(s[1] - s[0]), float(s[2] - s[0])
        den3 = l3 - tau * l2
        if abs(den3) < 1e-12 * max(abs(l3), 1.0):
            raise DegenerateConfigurationError("the point is the vanishing point of the axis")
        return float(s[0] + l2 * l3 * (1.0 - tau) / den3)  # eq 8
    H = _homography_1d(x, s)
    den = float(H[1, 0] * xp + H[1, 1])
    num = float(H[0, 0] * xp + H[0, 1])
    if abs(den) < 1e-12 * max(abs(num), 1.0):
        raise DegenerateConfigurationError("the point is the vanishing point of the axis")
    return num / den


def tip_to_surface_distance_mm(
    uv_markers_px: ArrayLike, positions_mm: ArrayLike, uv_spot_px: ArrayLike, tip_position_mm: float
) -> float:
    """Seed 004 §II-A.2: distance along the axis from the instrument tip (axis coordinate
    ``tip_position_mm``) to the pointed surface (the laser spot, assumed on the axis).

    Positive when the spot lies beyond the tip (on the side away from the markers); negative means
    the spot is between the tip and the markers (a bad detection, or a spot off the axis).

    Raises:
        as :func:`axis_coordinate_from_cross_ratio`.
    """
    s = np.asarray(positions_mm, dtype=np.float64).reshape(-1)
    s_spot = axis_coordinate_from_cross_ratio(uv_markers_px, s, uv_spot_px)
    tip = float(tip_position_mm)
    away = -1.0 if float(s.mean()) > tip else 1.0  # direction from tip away from the markers
    return (s_spot - tip) * away


# ---------------------------------------------------------------------- against the plan
def direction_error_deg(measured: ArrayLike, planned: ArrayLike, *, oriented: bool = True) -> float:
    """Angle (degrees, in [0, 180]) between a measured axis direction and a planned one.

    With ``oriented=False`` the sign of the axes is ignored (a cylinder's axis has none): the result
    is in [0, 90].

    Raises:
        GeometryError: zero or non-finite vectors.
    """
    a = _unit(measured, "measured")
    b = _unit(planned, "planned")
    ang = math.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), float(a @ b)))
    return min(ang, 180.0 - ang) if not oriented else ang


@dataclass(frozen=True)
class PathError:
    """A measured axis against a planned path (entry -> target), same frame, mm and degrees.

    direction_error_deg: angle between the axis and the path direction (entry -> target).
    entry_offset_mm / target_offset_mm: distance of the planned entry / target to the axis line.
    """

    direction_error_deg: float
    entry_offset_mm: float
    target_offset_mm: float

    def within(self, max_angle_deg: float, max_offset_mm: float) -> bool:
        return (
            self.direction_error_deg <= max_angle_deg
            and self.entry_offset_mm <= max_offset_mm
            and self.target_offset_mm <= max_offset_mm
        )


def axis_path_error(
    axis: Line3D, entry_mm: ArrayLike, target_mm: ArrayLike, *, oriented: bool = True
) -> PathError:
    """Direction error (degrees) and lateral offsets (mm) of a measured axis against the planned path.

    ``oriented``: the axis direction must point from entry to target (True for a marker axis whose
    direction is known; False for a cylinder axis).

    Raises:
        GeometryError / DegenerateConfigurationError: non-finite input, entry == target.
    """
    e, t = _vec3(entry_mm, "entry_mm"), _vec3(target_mm, "target_mm")
    path = Line3D.through(e, t)
    d = axis.distance_to(np.vstack([e, t]))
    return PathError(
        direction_error_deg(axis.direction, path.direction, oriented=oriented), float(d[0]), float(d[1])
    )
