"""Single-slice CT stereotactic registration with line fiducials (seed 004 §IV).

A stereotactic frame carries straight rods (line fiducials). One CT slice cuts each rod in a spot.
From the spots' pixel positions and the known rods, the rigid transform between the frame and the
scanner follows linearly, with no iteration and no per-rod unknowns, thanks to the Plücker form:

- imaging model (eqs 27-31): a pixel ``(u, v)`` of the slice is the scanner point
  ``P_s = (s_x u, s_y v, z_slice)`` (mm; orthographic projection onto the cutting plane, scaling
  ``s_x, s_y``, gantry-tilt shear neglected as in the paper); the frame point is
  ``P_f = R P_s + t`` (the paper's ``(R, t)``, here ``T_frame_from_scanner``);
- rod ``j`` (eq 32-33): unit direction ``y_j``, Plücker moment (the paper's sign) ``w_j = y_j x O P``
  for any point P of the rod. A spot lies on its rod iff ``[y_j]x (u_j l1 + v_j l2 + t) = w_j`` with
  ``L = [l1 l2] = [r1 r2] diag(s_x, s_y)`` (eq 29);
- stacked (eq 36): ``A x = b`` with ``A_j = q_j^T (x) [y_j]x`` (3 x 9), ``b_j = w_j``,
  ``x = [l1; l2; t]``; each rod gives rank 2, so 4 rods give rank 8 (one-parameter family, eq 37)
  and 5 or more give rank 9;
- SVD solution (§IV-C steps 1-5): ``A = U D V^T``, ``b' = U^T b``, ``z_i = b'_i / d_i`` for the
  structural rank, the remaining components zero, ``x = V z + mu v_9`` with ``mu`` from the quadratic
  orthonormality relations (eq 30) when the rank is 8; then ``r3 = r1 x r2`` and the rotation is
  corrected by SVD, ``R' = U diag(1, 1, det(U V^T)) V^T``;
- optional Newton refinement (the paper's N-R, its ref [26]): Levenberg-Marquardt on the in-slice
  distances between the measured spots and the rods' intersections with the slice;
- spot relevance (eq 34): ``lambda_j = y_j^T (R P_s + t)`` is the spot's coordinate along its rod
  (from the foot ``O_j`` of the frame origin); a spot outside the rod's bounds
  ``[lambda_min, lambda_max]`` cannot be that rod's image.

When the pixel size is unknown and at least 5 rods are seen, ``|l1|`` and ``|l2|`` estimate it.
Pixel coordinates: ``u`` = column, ``v`` = row, origin at the centre of pixel (0, 0).
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from scipy.optimize import least_squares

from hil.errors import DegenerateConfigurationError, GeometryError, InputFileError
from hil.geometry.transform import RigidTransform, skew

FloatArray = NDArray[np.float64]

FRAME_SCHEMA = "hil.stereotactic_frame"
SPOTS_SCHEMA = "hil.ct_slice_spots"
FILE_VERSION = 1

__all__ = [
    "FRAME_SCHEMA",
    "SPOTS_SCHEMA",
    "PredictedSpot",
    "Rod",
    "SliceSpots",
    "StereotacticFrame",
    "StereotaxyResult",
    "error_box_mm",
    "load_frame",
    "load_spots",
    "predict_spots",
    "register_single_slice",
    "scanner_points_mm",
]


# ---------------------------------------------------------------------- the frame
@dataclass(frozen=True, eq=False)
class Rod:
    """A straight line fiducial between two end points (frame coordinates, mm).

    Derived: ``direction`` (unit ``y_j``, start -> end), ``foot_mm`` (``O_j``, the foot of the frame
    origin on the rod's line), ``w_mm`` (the paper's moment ``y_j x O P``), and the bounds
    ``lambda_min_mm <= lambda <= lambda_max_mm`` of the rod's points measured from ``O_j`` (eq 34).
    """

    rod_id: str
    start_mm: FloatArray
    end_mm: FloatArray

    def __post_init__(self) -> None:
        a = np.asarray(self.start_mm, dtype=np.float64).reshape(-1)
        b = np.asarray(self.end_mm, dtype=np.float64).reshape(-1)
        if a.shape != (3,) or b.shape != (3,) or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            raise GeometryError(f"rod {self.rod_id!r}: end points must be 3 finite values each")
        if float(np.linalg.norm(b - a)) < 1e-6:
            raise GeometryError(f"rod {self.rod_id!r}: start and end coincide")
        object.__setattr__(self, "start_mm", a)
        object.__setattr__(self, "end_mm", b)

    @property
    def direction(self) -> FloatArray:
        d = self.end_mm - self.start_mm
        return np.asarray(d / np.linalg.norm(d), dtype=np.float64)

    @property
    def foot_mm(self) -> FloatArray:
        y = self.direction
        return np.asarray(self.start_mm - float(self.start_mm @ y) * y, dtype=np.float64)

    @property
    def w_mm(self) -> FloatArray:
        return np.asarray(np.cross(self.direction, self.start_mm), dtype=np.float64)

    @property
    def bounds_mm(self) -> tuple[float, float]:
        y = self.direction
        return float(self.start_mm @ y), float(self.end_mm @ y)


@dataclass(frozen=True)
class StereotacticFrame:
    """A named set of rods with unique ids."""

    name: str
    rods: tuple[Rod, ...]

    def __post_init__(self) -> None:
        ids = [r.rod_id for r in self.rods]
        if len(set(ids)) != len(ids):
            raise GeometryError(f"frame {self.name!r}: duplicate rod ids")

    def rod(self, rod_id: str) -> Rod:
        for r in self.rods:
            if r.rod_id == rod_id:
                return r
        raise GeometryError(f"frame {self.name!r} has no rod {rod_id!r}")


@dataclass(frozen=True)
class SliceSpots:
    """Spots of one slice: rod ids, pixel positions (N, 2), and optionally the pixel size and the
    slice position (mm along the scanner's z)."""

    rod_ids: tuple[str, ...]
    uv_px: FloatArray
    pixel_mm: tuple[float, float] | None = None
    slice_z_mm: float = 0.0


def scanner_points_mm(uv_px: ArrayLike, pixel_mm: tuple[float, float], slice_z_mm: float = 0.0) -> FloatArray:
    """Eq 27: slice pixels ``(u, v)`` -> scanner points ``(s_x u, s_y v, z_slice)`` (N, 3), mm."""
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([uv[:, 0] * pixel_mm[0], uv[:, 1] * pixel_mm[1], np.full(len(uv), slice_z_mm)])


# ---------------------------------------------------------------------- result
@dataclass(frozen=True, eq=False)
class StereotaxyResult:
    """A single-slice registration.

    Attributes:
        T_frame_from_scanner: the paper's ``(R, t)``; ``T_scanner_from_frame`` is its inverse.
        pixel_mm: the pixel size used; ``pixel_mm_estimated`` when it came from ``|l1|, |l2|``.
        rank / structural_rank: numerical rank of ``A`` and the rank its structure allows
            (``min(9, 2 n)``); singular_values: of ``A`` (normalised units), descending;
            condition_number: ``d_1 / d_rank``.
        orthonormality_defect: ``||M^T M - I||_F`` of the linear ``M = [r1 r2]`` before the
            rotation correction (0 for exact data; grows with noise).
        residuals_mm: per spot, distance of the mapped spot to its rod (3-D), mm.
        in_slice_residuals_mm: per spot, distance in the slice between the spot and where the rod
            crosses the slice, mm (NaN for a rod parallel to the slice).
        lambdas_mm / within_bounds: eq 34 per spot, and whether it lies on the physical rod.
        method: "plucker_svd" or "plucker_svd+lm"; iterations: of the refinement (0 without).
        warnings: rank, conditioning, relevance and pixel-size notes, plain text.
    """

    T_frame_from_scanner: RigidTransform
    pixel_mm: tuple[float, float]
    pixel_mm_estimated: bool
    rank: int
    structural_rank: int
    singular_values: FloatArray
    condition_number: float
    orthonormality_defect: float
    residuals_mm: FloatArray
    in_slice_residuals_mm: FloatArray
    lambdas_mm: FloatArray
    within_bounds: NDArray[np.bool_]
    method: str
    iterations: int
    warnings: tuple[str, ...]

    @property
    def T_scanner_from_frame(self) -> RigidTransform:
        return self.T_frame_from_scanner.inverse()

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_mm**2)))


# ---------------------------------------------------------------------- the linear solution
def _nearest_rotation(M: FloatArray) -> FloatArray:
    """Seed 004 §IV-C: ``R' = U diag(1, 1, det(U V^T)) V^T`` from the SVD ``M = U S V^T``."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt))) or 1.0])
    return np.asarray(U @ D @ Vt, dtype=np.float64)


def _solve_mu(a: FloatArray, b: FloatArray) -> float:
    """Step 5: ``mu`` making ``g(mu) = a + mu b`` satisfy ``|g1| = |g2| = 1``, ``g1.g2 = 0`` best
    (least squares over the three quadratic relations: the real root of a cubic)."""
    a1, a2, b1, b2 = a[:3], a[3:6], b[:3], b[3:6]
    # each relation f_k(mu) = c2 mu^2 + c1 mu + c0
    f = [
        (float(b1 @ b1), 2 * float(a1 @ b1), float(a1 @ a1) - 1.0),
        (float(b2 @ b2), 2 * float(a2 @ b2), float(a2 @ a2) - 1.0),
        (float(b1 @ b2), float(a1 @ b2 + a2 @ b1), float(a1 @ a2)),
    ]
    F = np.zeros(5)  # sum_k f_k^2 as a quartic, highest power first
    for c in f:
        F += np.polymul(np.array(c), np.array(c))
    roots = np.roots(np.polyder(F))
    real = [float(r.real) for r in roots if abs(r.imag) < 1e-9 * max(1.0, abs(r))]
    if not real:  # pragma: no cover - a cubic always has a real root
        raise DegenerateConfigurationError("no real solution for the one-parameter family")
    return min(real, key=lambda m: float(np.polyval(F, m)))


def _rods_arrays(rods: Sequence[Rod]) -> tuple[FloatArray, FloatArray]:
    return np.array([r.direction for r in rods]), np.array([r.w_mm for r in rods])


def _linear(
    rods: Sequence[Rod], coords: FloatArray, scale_known: bool, warnings: list[str]
) -> tuple[FloatArray, FloatArray, int, int, FloatArray, float, float]:
    """The SVD solution. ``coords`` (N, 2) are in mm (scale known) or pixels. Returns
    ``(M = [g1 g2] (3, 2), t' (3,), rank, structural_rank, singular values, cond, defect)`` with
    ``P_f = coords_x g1 + coords_y g2 + t'``."""
    n = len(rods)
    Y, W = _rods_arrays(rods)
    c_mean = coords.mean(axis=0)
    rho = float(np.sqrt(np.mean(np.sum((coords - c_mean) ** 2, axis=1)))) or 1.0
    cn = (coords - c_mean) / rho
    A = np.zeros((3 * n, 9))
    for j in range(n):
        Sy = skew(Y[j])
        A[3 * j : 3 * j + 3] = np.hstack([cn[j, 0] * Sy, cn[j, 1] * Sy, Sy])  # q^T (x) [y]x, eq 36
    b = (W / rho).reshape(-1)
    U, d, Vt = np.linalg.svd(A, full_matrices=False)
    structural = min(9, 2 * n)
    tol = 1e-9 * float(d[0])
    rank = int(np.sum(d > tol))
    if rank < structural:
        warnings.append(
            f"rank {rank} < {structural}: the rods' arrangement is partly degenerate for this slice "
            "(e.g. parallel rods)"
            + ("; the one-parameter family is resolved by the orthonormality relations" if rank == 8 else "")
        )
    use = min(rank, structural)
    cond = float(d[0] / d[use - 1]) if use > 0 else float("inf")
    bp = U.T @ b
    z = np.zeros(9)
    z[:use] = bp[:use] / d[:use]
    x0 = Vt.T @ z
    if use == 9:
        x = x0
    elif use == 8 and scale_known:
        x = x0 + _solve_mu(x0, Vt[8]) * Vt[8]
    else:
        need = "5 rods to estimate the pixel size" if (use == 8 and not scale_known) else "4 independent rods"
        raise DegenerateConfigurationError(f"A has rank {use} of 9: the registration needs at least {need}")
    g1, g2, tau = x[:3], x[3:6], x[6:9]
    t_prime = rho * tau - c_mean[0] * g1 - c_mean[1] * g2
    M = np.column_stack([g1, g2])
    if scale_known:
        defect = float(np.linalg.norm(M.T @ M - np.eye(2)))
    else:
        s = np.linalg.norm(M, axis=0)
        defect = float(np.linalg.norm((M / s).T @ (M / s) - np.eye(2)))
    if cond > 1e6:
        warnings.append(f"A is ill-conditioned (condition number {cond:.3g}); the pose is unreliable")
    return M, t_prime, rank, structural, d, cond, defect


def _translation_given_R(rods: Sequence[Rod], P_s: FloatArray, R: FloatArray) -> FloatArray:
    """Least-squares ``t`` of ``[y_j]x (R P_j + t) = w_j`` for a fixed rotation."""
    lhs = np.zeros((3, 3))
    rhs = np.zeros(3)
    for rod, p in zip(rods, P_s, strict=True):
        S = skew(rod.direction)
        lhs += S.T @ S
        rhs += S.T @ (rod.w_mm - S @ (R @ p))
    return np.asarray(np.linalg.solve(lhs, rhs), dtype=np.float64)


# ---------------------------------------------------------------------- residuals and refinement
def _in_slice_residuals(
    rods: Sequence[Rod], P_s: FloatArray, T_frame_from_scanner: RigidTransform
) -> FloatArray:
    """(N, 2) vectors in the slice plane from the measured spot to the rod's crossing point, mm
    (NaN rows for rods within ~3 deg of parallel to the slice)."""
    T_sf = T_frame_from_scanner.inverse()
    out = np.full((len(rods), 2), np.nan)
    for j, (rod, p) in enumerate(zip(rods, P_s, strict=True)):
        a = T_sf.apply(rod.start_mm)
        d = T_sf.R @ rod.direction
        if abs(float(d[2])) < 0.05:
            continue
        s = (float(p[2]) - float(a[2])) / float(d[2])
        out[j] = (a + s * d)[:2] - p[:2]
    return out


def _distances(rods: Sequence[Rod], P_f: FloatArray) -> FloatArray:
    Y, W = _rods_arrays(rods)
    return np.asarray(np.linalg.norm(np.cross(Y, P_f) - W, axis=1), dtype=np.float64)


def _refine(rods: Sequence[Rod], P_s: FloatArray, T0: RigidTransform) -> tuple[RigidTransform, int]:
    """Levenberg-Marquardt on the in-slice residuals (3-D distance for rods parallel to the slice)."""
    Y, W = _rods_arrays(rods)

    def fun(x: FloatArray) -> FloatArray:
        T = RigidTransform.from_rotvec(x[:3]) @ T0
        T = RigidTransform(T.R, T.t + x[3:])
        res = _in_slice_residuals(rods, P_s, T)
        bad = ~np.isfinite(res[:, 0])
        if np.any(bad):
            P_f = T.apply(P_s[bad])
            res[bad] = (np.cross(Y[bad], P_f) - W[bad])[:, :2]
        return np.asarray(res.reshape(-1), dtype=np.float64)

    sol = least_squares(fun, np.zeros(6), method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=400)
    x = np.asarray(sol.x, dtype=np.float64)
    T = RigidTransform.from_rotvec(x[:3]) @ T0
    return RigidTransform(T.R, T.t + x[3:]), int(sol.nfev)


# ---------------------------------------------------------------------- public entry point
def _check_slice_spots(rods: Sequence[Rod], uv_px: ArrayLike) -> tuple[FloatArray, list[str]]:
    """Validate one slice's spots (pixels) against their rods; return ``(uv, rod ids)``.

    Raises:
        GeometryError: not finite (N, 2), a count different from the rods', N < 4, a rod used twice.
    """
    uv = np.asarray(uv_px, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2 or not np.all(np.isfinite(uv)):
        raise GeometryError(f"uv_px must be finite (N, 2) pixel positions, got shape {uv.shape}")
    n = uv.shape[0]
    if len(rods) != n:
        raise GeometryError(f"{n} spots but {len(rods)} rods: give one rod per spot")
    if n < 4:
        raise GeometryError(f"single-slice registration needs at least 4 spots on 4 rods, got {n}")
    ids = [r.rod_id for r in rods]
    if len(set(ids)) != n:
        raise GeometryError("two spots are assigned to the same rod")
    return uv, ids


def _check_pixel_size(pixel_mm: tuple[float, float]) -> tuple[float, float]:
    """``(s_x, s_y)`` mm per pixel as floats.

    Raises:
        GeometryError: either is not a positive finite number.
    """
    sx, sy = float(pixel_mm[0]), float(pixel_mm[1])
    if not (math.isfinite(sx) and math.isfinite(sy) and sx > 0 and sy > 0):
        raise GeometryError(f"pixel size must be two positive numbers, got {pixel_mm!r}")
    return sx, sy


def _rod_bounds_check(
    rods: Sequence[Rod], ids: list[str], P_f: FloatArray, bounds_margin_mm: float, warnings: list[str]
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Eq. 34: position of each spot along its rod (frame mm) and whether it lies within the rod.

    ``P_f`` are the spots in the frame; a spot more than ``bounds_margin_mm`` outside its rod's
    bounds adds a line to ``warnings``. Returns ``(lambdas_mm, within_bounds)``.
    """
    lam = np.array([float(r.direction @ p) for r, p in zip(rods, P_f, strict=True)])
    lo = np.array([min(r.bounds_mm) for r in rods]) - bounds_margin_mm
    hi = np.array([max(r.bounds_mm) for r in rods]) + bounds_margin_mm
    within = (lam >= lo) & (lam <= hi)
    for j in np.flatnonzero(~within):
        warnings.append(
            f"spot {j} (rod {ids[j]!r}) lies {lam[j]:.2f} mm along its rod, outside"
            f" [{lo[j] + bounds_margin_mm:.2f}, {hi[j] - bounds_margin_mm:.2f}]:"
            " not a relevant spot for that rod"
        )
    return lam, within


def register_single_slice(
    rods: Sequence[Rod],
    uv_px: ArrayLike,
    pixel_mm: tuple[float, float] | None,
    *,
    slice_z_mm: float = 0.0,
    refine: bool = False,
    bounds_margin_mm: float = 1.0,
) -> StereotaxyResult:
    """Rigid transform frame <-> scanner from one slice's spots (seed 004 §IV, eqs 27-37).

    Args:
        rods: the rod of each spot, in spot order (correspondences known).
        uv_px: (N, 2) spot centres in pixels (u = column, v = row).
        pixel_mm: ``(s_x, s_y)`` mm per pixel; None estimates it from ``|l1|, |l2|`` (needs N >= 5).
        slice_z_mm: the slice's position along the scanner z axis.
        refine: add the Levenberg-Marquardt refinement (seed 004's Newton-Raphson stage).
        bounds_margin_mm: tolerance of the eq-34 rod-bounds check.

    Returns:
        :class:`StereotaxyResult`; warnings (rank, conditioning, spots off their rods) are reported,
        not raised.

    Raises:
        GeometryError: shapes, counts (N >= 4), non-finite values, bad pixel size.
        DegenerateConfigurationError: the rods cannot fix the pose (rank < 8, or 8 without a
            known pixel size).
    """
    uv, ids = _check_slice_spots(rods, uv_px)
    if pixel_mm is not None:
        sx, sy = _check_pixel_size(pixel_mm)
    warnings: list[str] = []
    scale_known = pixel_mm is not None
    coords = uv * np.array([sx, sy]) if pixel_mm is not None else uv.copy()
    M, _t_linear, rank, structural, d, cond, defect = _linear(rods, coords, scale_known, warnings)
    if scale_known:
        g1, g2 = M[:, 0], M[:, 1]
        est = False
    else:
        sx, sy = float(np.linalg.norm(M[:, 0])), float(np.linalg.norm(M[:, 1]))
        g1, g2 = M[:, 0] / sx, M[:, 1] / sy
        est = True
        warnings.append(f"pixel size estimated from the slice: {sx:.5f} x {sy:.5f} mm")
    R = _nearest_rotation(np.column_stack([g1, g2, np.cross(g1, g2)]))
    P_s = scanner_points_mm(uv, (sx, sy), slice_z_mm)
    T = RigidTransform(R, _translation_given_R(rods, P_s, R))
    method, iterations = "plucker_svd", 0
    if refine:
        T, iterations = _refine(rods, P_s, T)
        method = "plucker_svd+lm"
    P_f = T.apply(P_s)
    resid = _distances(rods, P_f)
    ins = _in_slice_residuals(rods, P_s, T)
    lam, within = _rod_bounds_check(rods, ids, P_f, bounds_margin_mm, warnings)
    return StereotaxyResult(
        T_frame_from_scanner=T,
        pixel_mm=(sx, sy),
        pixel_mm_estimated=est,
        rank=rank,
        structural_rank=structural,
        singular_values=d,
        condition_number=cond,
        orthonormality_defect=defect,
        residuals_mm=resid,
        in_slice_residuals_mm=np.linalg.norm(ins, axis=1),
        lambdas_mm=lam,
        within_bounds=within,
        method=method,
        iterations=iterations,
        warnings=tuple(warnings),
    )


# ---------------------------------------------------------------------- prediction and error box

def robot_from_image_via_frame(
    T_scanner_from_frame: RigidTransform,
    T_robot_from_tcp: RigidTransform,
    T_tcp_from_frame: RigidTransform,
) -> RigidTransform:
    """Image -> robot registration through a rod frame the robot carries during the scan.

    The CT-Bot route of seed 004 (section IV and its introduction): the robot holds the
    stereotactic frame in the scanner, one slice gives ``T_scanner_from_frame``
    (:func:`register_single_slice`), the robot's own kinematics give the tool pose
    ``T_robot_from_tcp`` at scan time, and the frame's mounting on the tool is
    ``T_tcp_from_frame`` (a mechanical calibration). The image (CT) frame is the scanner frame, so
    ``T_robot_from_image = T_robot_from_tcp @ T_tcp_from_frame @ T_frame_from_scanner`` — no skin
    markers and no camera in the chain. All mm.
    """
    return T_robot_from_tcp @ T_tcp_from_frame @ T_scanner_from_frame.inverse()


@dataclass(frozen=True)
class PredictedSpot:
    """Where a rod crosses a slice (pixels) and whether that point is on the physical rod (eq 34)."""

    rod_id: str
    uv_px: tuple[float, float] | None
    lambda_mm: float | None
    on_rod: bool


def predict_spots(
    frame: StereotacticFrame,
    T_scanner_from_frame: RigidTransform,
    pixel_mm: tuple[float, float],
    slice_z_mm: float = 0.0,
) -> list[PredictedSpot]:
    """For a known (or predicted) pose, the spot each rod should make in the slice ``z = slice_z_mm``:
    its pixel position and whether the crossing lies within the rod's bounds (the relevance check of
    seed 004 §IV-B for "any displacement (R, t)"). Rods parallel to the slice give ``uv_px=None``."""
    T_fs = T_scanner_from_frame.inverse()
    out = []
    for rod in frame.rods:
        a = T_scanner_from_frame.apply(rod.start_mm)
        d = T_scanner_from_frame.R @ rod.direction
        if abs(float(d[2])) < 1e-9:
            out.append(PredictedSpot(rod.rod_id, None, None, False))
            continue
        s = (slice_z_mm - float(a[2])) / float(d[2])
        p = a + s * d
        lam = float(rod.direction @ T_fs.apply(p))
        lo, hi = sorted(rod.bounds_mm)
        out.append(
            PredictedSpot(
                rod.rod_id, (float(p[0] / pixel_mm[0]), float(p[1] / pixel_mm[1])), lam, lo <= lam <= hi
            )
        )
    return out


def error_box_mm(
    rods: Sequence[Rod],
    uv_px: ArrayLike,
    pixel_mm: tuple[float, float],
    point_frame_mm: ArrayLike,
    *,
    spot_error_px: float = 0.25,
    slice_z_mm: float = 0.0,
    refine: bool = False,
) -> FloatArray:
    """Half-widths (3,) of the scanner-frame box bounding the position error of a frame point when
    every spot coordinate may be off by up to ``spot_error_px`` (first order, worst case: the sum of
    the absolute sensitivities) — the "error bounding-boxes with an assumed spot location error of
    0.25 pixel" of seed 004 §IV-D. Finite differences over the 2N spot coordinates."""
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    pf = np.asarray(point_frame_mm, dtype=np.float64).reshape(3)

    def mapped(u: FloatArray) -> FloatArray:
        res = register_single_slice(rods, u, pixel_mm, slice_z_mm=slice_z_mm, refine=refine)
        return res.T_scanner_from_frame.apply(pf)

    base = mapped(uv)
    h = 1e-4
    box = np.zeros(3)
    for k in range(uv.size):
        du = np.zeros(uv.size)
        du[k] = h
        box += np.abs((mapped(uv + du.reshape(uv.shape)) - base) / h)
    return np.asarray(box * spot_error_px, dtype=np.float64)


# ---------------------------------------------------------------------- files
class _RodModel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str = Field(min_length=1)
    start_mm: tuple[float, float, float]
    end_mm: tuple[float, float, float]


class _FrameModel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    schema_: Literal["hil.stereotactic_frame"] = Field(alias="schema")
    version: Literal[1]
    name: str = "frame"
    units: Literal["mm"] = "mm"
    description: str = ""
    rods: list[_RodModel] = Field(min_length=1)


class _SpotModel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    rod: str = Field(min_length=1)
    u_px: float
    v_px: float


class _SpotsModel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    schema_: Literal["hil.ct_slice_spots"] = Field(alias="schema")
    version: Literal[1]
    pixel_mm: tuple[float, float] | None = None
    slice_z_mm: float = 0.0
    description: str = ""
    spots: list[_SpotModel] = Field(min_length=1)


def _validation_reason(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors()[:3]:
        loc = ".".join(str(p) for p in err["loc"]) or "<top>"
        parts.append(f"{loc}: {err['msg']}")
    more = len(exc.errors()) - 3
    return "; ".join(parts) + (f" (and {more} more)" if more > 0 else "")


def _read_text(path: str | Path, what: str) -> str:
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise InputFileError(str(path), f"{what} file not found") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(str(path), f"cannot read {what} file: {exc}") from exc


def _json(text: str, path: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(
            path, f"not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})"
        ) from exc


def load_frame(path: str | Path) -> StereotacticFrame:
    """Read a frame definition (JSON, schema ``hil.stereotactic_frame`` version 1; see
    docs/pose004.md). Raises InputFileError naming the file and the field."""
    p = str(path)
    doc = _json(_read_text(path, "frame"), p)
    try:
        model = _FrameModel.model_validate(doc)
    except ValidationError as exc:
        raise InputFileError(p, _validation_reason(exc)) from None
    try:
        rods = tuple(Rod(r.id, np.array(r.start_mm), np.array(r.end_mm)) for r in model.rods)
        return StereotacticFrame(model.name, rods)
    except GeometryError as exc:
        raise InputFileError(p, str(exc)) from None


def _spots_csv(text: str, path: str) -> SliceSpots:
    rows = list(csv.reader(io.StringIO(text)))
    rows = [r for r in rows if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise InputFileError(path, "no rows")
    header = [h.strip() for h in rows[0]]
    if header != ["rod", "u_px", "v_px"]:
        raise InputFileError(path, f"header must be 'rod,u_px,v_px', got {','.join(header)!r}")
    ids: list[str] = []
    uv: list[tuple[float, float]] = []
    for i, r in enumerate(rows[1:], start=2):
        if len(r) != 3:
            raise InputFileError(path, f"row {i}: expected 3 columns, got {len(r)}")
        try:
            u, v = float(r[1]), float(r[2])
        except ValueError:
            raise InputFileError(path, f"row {i}: u_px/v_px are not numbers: {r[1]!r}, {r[2]!r}") from None
        if not r[0].strip():
            raise InputFileError(path, f"row {i}: empty rod id")
        ids.append(r[0].strip())
        uv.append((u, v))
    if not ids:
        raise InputFileError(path, "no spots")
    return SliceSpots(tuple(ids), np.array(uv, dtype=np.float64))


def load_spots(path: str | Path) -> SliceSpots:
    """Read a slice's spots: JSON (schema ``hil.ct_slice_spots`` version 1, may carry ``pixel_mm``
    and ``slice_z_mm``) or CSV with the header ``rod,u_px,v_px``. Raises InputFileError."""
    p = str(path)
    text = _read_text(path, "spots")
    if p.lower().endswith(".csv"):
        spots = _spots_csv(text, p)
    else:
        doc = _json(text, p)
        try:
            model = _SpotsModel.model_validate(doc)
        except ValidationError as exc:
            raise InputFileError(p, _validation_reason(exc)) from None
        spots = SliceSpots(
            tuple(s.rod for s in model.spots),
            np.array([(s.u_px, s.v_px) for s in model.spots], dtype=np.float64),
            model.pixel_mm,
            model.slice_z_mm,
        )
    if not np.all(np.isfinite(spots.uv_px)):
        raise InputFileError(p, "spot coordinates must be finite numbers")
    if spots.pixel_mm is not None and not all(math.isfinite(v) and v > 0 for v in spots.pixel_mm):
        raise InputFileError(p, f"pixel_mm must be two positive numbers, got {list(spots.pixel_mm)}")
    if len(set(spots.rod_ids)) != len(spots.rod_ids):
        raise InputFileError(p, "two spots name the same rod")
    return spots
