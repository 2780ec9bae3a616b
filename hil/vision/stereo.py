"""Stereo matching and triangulation of ring detections (seed 001 section 4.1, seed 003 section 4.1).

1. Undistort the detected centres and map them into the rectified pair (rows are epipolar lines).
2. Pair left/right detections by a global assignment (Hungarian, ``linear_sum_assignment``) on a
   cost of the rectified row difference (tolerance in pixels) and, when the marker diameter is
   known, the agreement of the ring's apparent size with the depth implied by the disparity.
3. Perspective-bias correction: under perspective the centre of the fitted ellipse is not the
   image of the circle's centre. The supporting-plane normal of each ring is recovered from its
   outer conic in both views (each view gives two candidates; the common one is the answer);
   the projected centre is then the pole of the plane's vanishing line ``K^-T n`` with respect
   to the conic, in each view. (Alternative: the concentric-conic construction, per view.)
4. Triangulate with the DLT (hil.geometry.triangulation) and check with the skew-ray midpoint:
   a pair whose rays pass further apart than ``max_gap_mm`` is rejected and reported (seed 003).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from hil.geometry.triangulation import triangulate_dlt, triangulate_midpoint
from hil.vision import kernel
from hil.vision.camera_model import StereoCalibration, undistort_pixels
from hil.vision.conics import concentric_center, conic_center, conic_centers
from hil.vision.detect import RingDetection
from hil.vision.ellipse import circle_normals_from_cones, poles_of_lines, vanishing_lines
from hil.vision.frozen import frozen_instance

FloatArray = NDArray[np.float64]
Correction = Literal["normal", "concentric", "none"]

_FORBIDDEN = 1e6


@dataclass(frozen=True)
class StereoParams:
    """epipolar_tol_px: largest rectified row difference of a pair. max_gap_mm: largest distance
    between the two rays (seed 003). outer_diameter_mm: the markers' outer diameter for the size
    check (None disables it); size_tol: allowed relative size error. correction: perspective-bias
    correction ("normal", "concentric" or "none")."""

    epipolar_tol_px: float = 2.0
    max_gap_mm: float = 1.0
    outer_diameter_mm: float | None = 7.0
    size_tol: float = 0.35
    correction: Correction = "normal"


@dataclass(frozen=True, eq=False)
class StereoPoint:
    """A triangulated marker: indices of its left/right detections, the 3D point (optical frame,
    mm, DLT), rectified row difference (px), ray gap (mm), the centres used (undistorted px) and
    the ring's plane normal (optical frame) when it was estimated."""

    left_index: int
    right_index: int
    point_mm: FloatArray
    epipolar_error_px: float
    gap_mm: float
    uv_left_px: FloatArray
    uv_right_px: FloatArray
    normal: FloatArray | None

    def to_dict(self) -> dict[str, object]:
        return {
            "left_index": self.left_index,
            "right_index": self.right_index,
            "point_mm": [float(v) for v in self.point_mm],
            "epipolar_error_px": self.epipolar_error_px,
            "gap_mm": self.gap_mm,
            "normal": None if self.normal is None else [float(v) for v in self.normal],
        }


@dataclass(frozen=True)
class RejectedPair:
    left_index: int
    right_index: int
    reason: str
    gap_mm: float

    def to_dict(self) -> dict[str, object]:
        return {
            "left_index": self.left_index,
            "right_index": self.right_index,
            "reason": self.reason,
            "gap_mm": self.gap_mm,
        }


@dataclass(frozen=True)
class StereoResult:
    points: tuple[StereoPoint, ...]
    rejected: tuple[RejectedPair, ...] = ()
    unmatched_left: tuple[int, ...] = ()
    unmatched_right: tuple[int, ...] = ()
    extra: dict[str, object] = field(default_factory=dict)

    @property
    def points_mm(self) -> FloatArray:
        if not self.points:
            return np.zeros((0, 3))
        return np.stack([p.point_mm for p in self.points])


def _rectify(cal: StereoCalibration, side: str, uv_ideal: FloatArray) -> FloatArray:
    if uv_ideal.shape[0] == 0:
        return uv_ideal
    rect = cal.rectification
    K, R, P = (cal.K_left, rect.R1, rect.P1) if side == "left" else (cal.K_right, rect.R2, rect.P2)
    out = cv2.undistortPoints(uv_ideal.reshape(-1, 1, 2), K, None, R=R, P=P)
    return np.asarray(out.reshape(-1, 2), dtype=np.float64)


def _ideal_with_affines(
    cal: StereoCalibration, side: str, centers_px: FloatArray
) -> tuple[FloatArray, FloatArray | None]:
    """The ideal (undistorted) pixels of the centres (n, 2) and, per centre, the 3x3 affine map
    distorted -> ideal pixels linearised at the centre (n, 3, 3); None for a camera without
    distortion (every map the identity). The second-order error over a ring is far below the
    noise. One undistortion of all points."""
    left = side == "left"
    K, dist = (cal.K_left, cal.dist_left) if left else (cal.K_right, cal.dist_right)
    distorted = cal.constants.distorted_left if left else cal.constants.distorted_right
    n = centers_px.shape[0]
    if not distorted or n == 0:
        return centers_px.astype(np.float64, copy=True), None
    k = kernel.active()
    if k is not None and dist.shape == (5,):
        # the same arithmetic compiled (hil/vision/_kernel.c); OpenCV's where it did not converge
        ideal_c, H_c, ok = np.empty((n, 2)), np.empty((n, 3, 3)), np.empty(n, dtype=bool)
        k.ideal_affines(np.ascontiguousarray(centers_px, np.float64), np.ascontiguousarray(K, np.float64),
                        np.ascontiguousarray(dist, np.float64), ideal_c, H_c, ok)
        if ok.all():
            return ideal_c, H_c
    h = 1.0
    pts = np.concatenate([centers_px, centers_px + np.array([h, 0.0]), centers_px + np.array([0.0, h])])
    ideal = undistort_pixels(pts, K, dist)
    c0, cx, cy = ideal[:n], ideal[n : 2 * n], ideal[2 * n :]
    H = np.zeros((n, 3, 3))
    H[:, :2, 0] = (cx - c0) / h
    H[:, :2, 1] = (cy - c0) / h
    H[:, :2, 2] = c0 - np.einsum("pij,pj->pi", H[:, :2, :2], centers_px)
    H[:, 2, 2] = 1.0
    return np.asarray(c0, dtype=np.float64), H


def _to_ideal_stack(C: FloatArray, H: FloatArray | None) -> FloatArray:
    """Conics (P, 3, 3) in distorted pixels -> ideal pixels through their affine maps ``H``
    (P, 3, 3) (None: identity): ``H^-T C H^-1``, normalised."""
    if H is None:
        return C
    k = kernel.active()
    if k is not None:  # the same arithmetic compiled (hil/vision/_kernel.c)
        out = np.empty_like(C)
        k.conics_to_ideal(np.ascontiguousarray(C, np.float64), np.ascontiguousarray(H, np.float64), out)
        return out
    a, b, c, d = H[:, 0, 0], H[:, 0, 1], H[:, 1, 0], H[:, 1, 1]
    det = a * d - b * c
    Hi = np.zeros_like(H)
    Hi[:, 0, 0], Hi[:, 0, 1], Hi[:, 1, 0], Hi[:, 1, 1] = d / det, -b / det, -c / det, a / det
    tx, ty = H[:, 0, 2], H[:, 1, 2]
    Hi[:, 0, 2] = -(Hi[:, 0, 0] * tx + Hi[:, 0, 1] * ty)
    Hi[:, 1, 2] = -(Hi[:, 1, 0] * tx + Hi[:, 1, 1] * ty)
    Hi[:, 2, 2] = 1.0
    Ci = np.transpose(Hi, (0, 2, 1)) @ C @ Hi
    return np.asarray(Ci / np.sqrt(np.sum(Ci * Ci, axis=(1, 2), keepdims=True)), dtype=np.float64)


def _conic_stacks(
    left: list[RingDetection], right: list[RingDetection], HL: FloatArray | None, HR: FloatArray | None
) -> tuple[FloatArray, FloatArray]:
    """The paired detections' conics in ideal (undistorted) pixels (4P, 3, 3), in the order left
    outer, right outer, left inner, right inner, and the centre weights of the left then the right
    detections (2P, 2), all in one stack."""
    P = len(left)
    dets = left + right
    C = np.array([d.outer.conic for d in dets] + [d.inner.conic for d in dets])
    if HL is not None and HR is not None:
        C = _to_ideal_stack(C, np.concatenate([HL, HR, HL, HR]))
    elif HL is not None or HR is not None:
        for k, H in enumerate((HL, HR, HL, HR)):
            C[k * P : (k + 1) * P] = _to_ideal_stack(C[k * P : (k + 1) * P], H)
    ax = np.array([(d.outer.a_px + d.outer.b_px, d.inner.a_px + d.inner.b_px) for d in dets])
    ax = ax.reshape(2 * P, 2)
    return C, ax / ax.sum(axis=1, keepdims=True)


def _normal_correction(
    cal: StereoCalibration,
    left: list[RingDetection],
    right: list[RingDetection],
    HL: FloatArray | None,
    HR: FloatArray | None,
    UL: FloatArray,
    UR: FloatArray,
) -> list[FloatArray | None]:
    """The plane-normal perspective correction of paired detections (module doc, step 3), for all
    pairs at once: moves the ideal centres ``UL``, ``UR`` (P, 2) in place; returns the normals
    (optical frame; None where a conic gave no normal)."""
    KL, KR, R_rl = cal.K_left, cal.K_right, cal.R_right_from_left
    P = len(left)
    C, w = _conic_stacks(left, right, HL, HR)
    k = kernel.active()
    if k is not None:  # the same arithmetic compiled (hil/vision/_kernel.c), results equal to rounding
        normals, ok_k = np.empty((P, 3)), np.empty(P, dtype=bool)
        c8 = [np.ascontiguousarray(a, np.float64) for a in (C, w, KL, KR, R_rl)]
        k.normal_correction(*c8, UL, UR, normals, ok_k)
        return [normals[i] if ok_k[i] else None for i in range(P)]
    wl, wr = w[:P], w[P:]
    c1, c2, okc = circle_normals_from_cones(np.concatenate([KL.T @ C[:P] @ KL, KR.T @ C[P : 2 * P] @ KR]))
    l1, l2, okL = c1[:P], c2[:P], okc[:P]
    r1, r2, okR = c1[P:] @ R_rl, c2[P:] @ R_rl, okc[P:]  # R_rl^T n: the right candidates in the left frame
    # the best-agreeing pair of candidates (first maximum wins, as in a loop over left then right)
    dots = np.stack([np.sum(a * b, axis=1) for a, b in ((l1, r1), (l1, r2), (l2, r1), (l2, r2))], axis=1)
    best = np.argmax(dots, axis=1)
    n = np.where((best < 2)[:, None], l1, l2) + np.where((best % 2 == 0)[:, None], r1, r2)
    n = n / np.sqrt(np.sum(n * n, axis=1, keepdims=True))
    nR = n @ R_rl.T
    ok = okL & okR
    lL, lR = vanishing_lines(KL, n), vanishing_lines(KR, nR)
    shift = poles_of_lines(C, np.concatenate([lL, lR, lL, lR])) - conic_centers(C)
    dl = wl[:, :1] * shift[:P] + wl[:, 1:] * shift[2 * P : 3 * P]
    dr = wr[:, :1] * shift[P : 2 * P] + wr[:, 1:] * shift[3 * P :]
    UL += np.where(ok[:, None], dl, 0.0)
    UR += np.where(ok[:, None], dr, 0.0)
    return [n[k].copy() if ok[k] else None for k in range(P)]


def _concentric_correction(
    left: list[RingDetection],
    right: list[RingDetection],
    HL: FloatArray | None,
    HR: FloatArray | None,
    UL: FloatArray,
    UR: FloatArray,
) -> None:
    """The concentric-conic correction (per view): moves ``UL``, ``UR`` in place."""
    P = len(left)
    C, w = _conic_stacks(left, right, HL, HR)
    CoL, CoR, CiL, CiR = C[:P], C[P : 2 * P], C[2 * P : 3 * P], C[3 * P :]
    wl, wr = w[:P], w[P:]
    for k in range(UL.shape[0]):
        ccl, ccr = concentric_center(CoL[k], CiL[k]), concentric_center(CoR[k], CiR[k])
        if ccl is not None and ccr is not None:
            UL[k] += ccl - (wl[k, 0] * conic_center(CoL[k]) + wl[k, 1] * conic_center(CiL[k]))
            UR[k] += ccr - (wr[k, 0] * conic_center(CoR[k]) + wr[k, 1] * conic_center(CiR[k]))


def _triangulate(PL: FloatArray, PR: FloatArray, UL: FloatArray, UR: FloatArray) -> FloatArray:
    """:func:`hil.geometry.triangulation.triangulate_dlt` by the compiled kernel when it is selected
    (the null vector by one-sided Jacobi rotations instead of LAPACK's SVD: the same points to
    rounding); the numpy function (and its errors) for non-finite input or a point at infinity."""
    k = kernel.active()
    if k is None or not (np.isfinite(UL).all() and np.isfinite(UR).all()):
        return triangulate_dlt(PL, PR, UL, UR)
    pts, ok = np.empty((UL.shape[0], 3)), np.empty(UL.shape[0], dtype=bool)
    k.triangulate_dlt(np.ascontiguousarray(PL, np.float64), np.ascontiguousarray(PR, np.float64),
                      np.ascontiguousarray(UL, np.float64), np.ascontiguousarray(UR, np.float64), pts, ok)
    return pts if ok.all() else triangulate_dlt(PL, PR, UL, UR)


def _ray_gaps(cal: StereoCalibration, UL: FloatArray, UR: FloatArray) -> FloatArray:
    """The skew-ray gap (mm) of each pair (seed 003; :func:`triangulate_midpoint`), by the compiled
    kernel when it is selected and the rays are usable, else by the numpy function (and its errors)."""
    const, R_rl = cal.constants, cal.R_right_from_left
    k = kernel.active()
    if k is not None and np.isfinite(UL).all() and np.isfinite(UR).all():
        gaps, ok = np.empty(UL.shape[0]), np.empty(UL.shape[0], dtype=bool)
        c8 = [np.ascontiguousarray(a, np.float64) for a in (UL, UR, const.K_left_inv, const.K_right_inv, R_rl,
                                                            const.right_center_mm)]
        k.ray_gaps(*c8, gaps, ok)
        if ok.all():
            return gaps
    ones = np.ones((len(UL), 1))
    dirs_l = np.hstack([UL, ones]) @ const.K_left_inv.T
    dirs_r = (np.hstack([UR, ones]) @ const.K_right_inv.T) @ R_rl
    _, gaps = triangulate_midpoint(np.zeros(3), dirs_l, const.right_center_mm, dirs_r)
    return gaps


def match_and_triangulate(
    cal: StereoCalibration,
    left: list[RingDetection],
    right: list[RingDetection],
    params: StereoParams = StereoParams(),
) -> StereoResult:
    """Pair, correct and triangulate left/right ring detections (see module doc). Pure CPU.

    Raises:
        GeometryError (from the triangulation) only for degenerate input such as parallel rays.
    """
    const = cal.constants
    nl, nr = len(left), len(right)
    if nl == 0 or nr == 0:
        return StereoResult((), (), tuple(range(nl)), tuple(range(nr)))
    cL = np.array([d.center_px for d in left]).reshape(-1, 2)
    cR = np.array([d.center_px for d in right]).reshape(-1, 2)
    iL, HL_all = _ideal_with_affines(cal, "left", cL)
    iR, HR_all = _ideal_with_affines(cal, "right", cR)
    rL, rR = _rectify(cal, "left", iL), _rectify(cal, "right", iR)
    P2 = cal.rectification.P2
    f_rect = float(P2[0, 0])
    fb = abs(float(P2[0, 3]))  # f * baseline (rectified)
    dv = np.abs(rL[:, None, 1] - rR[None, :, 1])
    disp = rL[:, None, 0] - rR[None, :, 0]
    cost = (dv / params.epipolar_tol_px) ** 2
    allowed = (dv <= params.epipolar_tol_px) & (disp > 0)
    if params.outer_diameter_mm is not None:
        z = fb / np.where(disp > 0, disp, 1.0)  # only the pairs with disp > 0 are allowed
        abl = np.array([(d.outer.a_px, d.outer.b_px) for d in left])
        abr = np.array([(d.outer.a_px, d.outer.b_px) for d in right])
        sl, sr = np.sqrt(abl[:, 0] * abl[:, 1]), np.sqrt(abr[:, 0] * abr[:, 1])
        # the ring's major axis ~ its diameter at its depth: D = 2 a Z / f (upper bound under tilt)
        dl = 2.0 * abl[:, 0][:, None] * z / f_rect
        dr = 2.0 * abr[:, 0][None, :] * z / f_rect
        size_err = np.abs(0.5 * (dl + dr) / params.outer_diameter_mm - 1.0)
        allowed &= size_err <= params.size_tol
        cost = cost + (size_err / params.size_tol) ** 2 + np.abs(np.log(sl[:, None] / sr[None, :]))
    cost = np.where(allowed, cost, _FORBIDDEN)
    rows, cols = linear_sum_assignment(cost)
    keep = allowed[rows, cols]
    ia, ib = rows[keep], cols[keep]
    if ia.size == 0:
        return StereoResult((), (), tuple(range(nl)), tuple(range(nr)))
    pairs = list(zip(ia.tolist(), ib.tolist(), strict=True))
    used_l, used_r = set(ia.tolist()), set(ib.tolist())
    UL, UR = iL[ia], iR[ib]  # fancy indexing: copies
    normals: list[FloatArray | None] = [None] * len(pairs)
    HL = None if HL_all is None else HL_all[ia]
    HR = None if HR_all is None else HR_all[ib]
    paired_l, paired_r = [left[a] for a, _ in pairs], [right[b] for _, b in pairs]
    if params.correction == "normal":
        normals = _normal_correction(cal, paired_l, paired_r, HL, HR, UL, UR)
    elif params.correction == "concentric":
        _concentric_correction(paired_l, paired_r, HL, HR, UL, UR)
    pts = _triangulate(const.P_left, const.P_right, UL, UR)
    gaps = _ray_gaps(cal, UL, UR)
    epi = np.abs(_rectify(cal, "left", UL)[:, 1] - _rectify(cal, "right", UR)[:, 1]).tolist()
    gap_list = gaps.tolist()
    good: list[StereoPoint] = []
    rejected: list[RejectedPair] = []
    for k, (a, b) in enumerate(pairs):
        if gap_list[k] > params.max_gap_mm:
            rejected.append(
                RejectedPair(
                    a, b, f"rays pass {gap_list[k]:.3f} mm apart (> {params.max_gap_mm} mm)", gap_list[k]
                )
            )
            continue
        good.append(frozen_instance(StereoPoint, {
            "left_index": a, "right_index": b, "point_mm": pts[k], "epipolar_error_px": epi[k],
            "gap_mm": gap_list[k], "uv_left_px": UL[k], "uv_right_px": UR[k], "normal": normals[k],
        }))
    return StereoResult(
        tuple(good),
        tuple(rejected),
        tuple(i for i in range(nl) if i not in used_l),
        tuple(i for i in range(nr) if i not in used_r),
    )
