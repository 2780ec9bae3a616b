"""Detection of a needle's two apparent contour lines (silhouette edges) in an image.

The input to :mod:`hil.geometry.cylinder` (seed 004 §III): the two straight image lines bounding a
cylindrical instrument. Steps:

1. Canny edges in the region of interest; the strongest straight edge (``cv2.HoughLines``) gives
   the needle's image direction ``t`` and normal ``n``;
2. edge pixels within ``max_width_px`` of it whose gradient is within ~25 deg of ``±n`` are split by
   the sign of ``gradient . n``: for a dark needle on a light background the gradient points away
   from the needle on both sides, so the sign tells the two sides apart (inverted for a bright one);
3. each edge pixel is moved to the sub-pixel maximum of the gradient magnitude along ``n``
   (parabola through three samples), the points are undistorted, and each side is fitted with a
   total-least-squares line, twice, dropping points farther than ``3 x`` the robust spread (this also
   drops the edges of beads threaded on the needle).

Returns lines in undistorted (ideal) pixels, ``a u + b v + c = 0`` with ``a^2 + b^2 = 1``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import DegenerateConfigurationError, GeometryError, VisionError
from hil.geometry.collinear import PathError, axis_path_error
from hil.geometry.cylinder import TwoViewCylinder, cylinder_axis_two_views
from hil.vision.camera_model import StereoCalibration, undistort_pixels

FloatArray = NDArray[np.float64]

__all__ = [
    "NeedleAxisMeasurement",
    "NeedleContours",
    "detect_needle_contours",
    "fit_line_tls",
    "measure_needle_axis",
]


@dataclass(frozen=True)
class NeedleContours:
    """The two contour lines of a needle (ideal pixels), with fit statistics.

    lines_px: (2, 3), the first on the ``-n`` side. axis_hint_px: the middle of the detected
    segment (ideal pixels), a point on the imaged axis (for cheirality in
    :func:`hil.geometry.cylinder.cylinder_axis_from_contours`). n_points / rms_px per line.
    width_px: distance between the two lines at the middle of the segment.
    """

    lines_px: FloatArray
    axis_hint_px: FloatArray
    n_points: tuple[int, int]
    rms_px: tuple[float, float]
    width_px: float


def fit_line_tls(points_px: ArrayLike, weights: ArrayLike | None = None) -> FloatArray:
    """Total-least-squares line through (N >= 2) points: ``(a, b, c)``, ``a^2 + b^2 = 1``.

    Raises:
        VisionError: fewer than 2 points, or all coincide.
    """
    p = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if len(p) < 2:
        raise VisionError("a line fit needs at least 2 points")
    wts = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    c = (p * wts[:, None]).sum(axis=0) / wts.sum()
    d = (p - c) * np.sqrt(wts)[:, None]
    _, sv, Vt = np.linalg.svd(d, full_matrices=False)
    if sv[0] < 1e-12:
        raise VisionError("all points coincide")
    n = Vt[1]
    return np.array([n[0], n[1], -float(n @ c)])


def _subpixel_along(
    mag: NDArray[np.float32], xs: NDArray[np.intp], ys: NDArray[np.intp], n: FloatArray
) -> FloatArray:
    """Move integer edge pixels to the parabola peak of the gradient magnitude along ``n``."""

    def sample(off: float) -> FloatArray:
        x = (xs + off * n[0]).astype(np.float32)
        y = (ys + off * n[1]).astype(np.float32)
        v = cv2.remap(
            mag, x.reshape(1, -1), y.reshape(1, -1), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        return np.asarray(v, dtype=np.float64).reshape(-1)

    m0, mm, mp = sample(0.0), sample(-1.0), sample(1.0)
    den = mm - 2 * m0 + mp
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den < 0, 0.5 * (mm - mp) / den, 0.0)
    off = np.clip(off, -1.0, 1.0)
    return np.column_stack([xs + off * n[0], ys + off * n[1]])


def _robust_fit(pts: FloatArray, wts: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    keep = np.ones(len(pts), bool)
    line = fit_line_tls(pts, wts)
    for _ in range(3):
        r = np.abs(pts @ line[:2] + line[2])
        mad = float(np.median(r[keep])) * 1.4826 + 1e-3
        keep = r <= max(3.0 * mad, 0.3)
        if keep.sum() < 10:
            raise VisionError("too few edge points on one side of the needle")
        line = fit_line_tls(pts[keep], wts[keep])
    r = pts[keep] @ line[:2] + line[2]
    return line, keep, float(np.sqrt(np.mean(r * r)))


def detect_needle_contours(
    image: NDArray[np.uint8],
    K: FloatArray,
    dist: FloatArray,
    *,
    roi: tuple[int, int, int, int] | None = None,
    polarity: Literal["dark", "bright"] = "dark",
    max_width_px: float = 25.0,
    canny_low: float = 20.0,
    canny_high: float = 60.0,
) -> NeedleContours:
    """Find the two silhouette edges of a needle in ``image`` (HxW uint8).

    Args:
        K, dist: the camera's intrinsics and distortion (lines are returned undistorted).
        roi: ``(x0, y0, x1, y1)`` pixels to search (e.g. around the needle's expected projection);
            default the whole image. Other long straight edges inside it confuse the detector.
        polarity: "dark" needle on a lighter background, or "bright".
        max_width_px: upper bound of the needle's apparent width.

    Raises:
        VisionError: bad image, no straight edge, or too few points on a side.
    """
    if image.ndim != 2 or image.dtype != np.uint8 or image.size == 0:
        raise VisionError("detect_needle_contours needs a non-empty HxW uint8 image")
    h, w = image.shape
    x0, y0, x1, y1 = roi if roi is not None else (0, 0, w, h)
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(w, x1), min(h, y1)
    if x1 - x0 < 8 or y1 - y0 < 8:
        raise VisionError(f"region of interest {roi} is empty or too small")
    sub = image[y0:y1, x0:x1]
    smooth = cv2.GaussianBlur(sub, (0, 0), 1.0)
    edges = cv2.Canny(smooth, canny_low, canny_high, L2gradient=True)
    found = cv2.HoughLines(edges, 1, np.pi / 720, threshold=30)
    if found is None or len(found) == 0:
        raise VisionError("no straight edge found")
    rho, theta = (float(v) for v in np.asarray(found).reshape(-1, 2)[0])
    n = np.array([math.cos(theta), math.sin(theta)])
    gx = cv2.Sobel(smooth.astype(np.float32), cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(smooth.astype(np.float32), cv2.CV_32F, 0, 1, ksize=3)
    mag = np.asarray(cv2.magnitude(gx, gy), dtype=np.float32)
    ys, xs = np.nonzero(edges)
    d = xs * n[0] + ys * n[1] - rho
    gdot = (gx[ys, xs] * n[0] + gy[ys, xs] * n[1]) / np.maximum(mag[ys, xs], 1e-6)
    sel = (np.abs(d) <= max_width_px) & (np.abs(gdot) > math.cos(math.radians(25)))
    sign = np.sign(gdot) * (1.0 if polarity == "dark" else -1.0)
    lines = []
    npts = []
    rms = []
    for side in (-1.0, 1.0):
        m = sel & (sign == side)
        if m.sum() < 10:
            raise VisionError("too few edge points on one side of the needle")
        p = _subpixel_along(mag, xs[m], ys[m], n) + np.array([x0, y0])
        p = undistort_pixels(p, K, dist)
        line, keep, r = _robust_fit(p, mag[ys[m], xs[m]].astype(np.float64))
        lines.append(line)
        npts.append(int(keep.sum()))
        rms.append(r)
    # middle of the detected segment, on the axis between the two lines
    origin = np.array([x0, y0], dtype=np.float64)
    pts_all = undistort_pixels(np.column_stack([xs[sel], ys[sel]]).astype(np.float64) + origin, K, dist)
    tdir = np.array([-lines[0][1], lines[0][0]])
    proj = pts_all @ tdir
    mid_t = 0.5 * (float(proj.min()) + float(proj.max()))
    foot = -lines[0][2] * lines[0][:2] + mid_t * tdir
    off1 = float(foot @ lines[1][:2] + lines[1][2])
    hint = foot - 0.5 * off1 * lines[1][:2]
    return NeedleContours(np.vstack(lines), hint, (npts[0], npts[1]), (rms[0], rms[1]), abs(off1))


@dataclass(frozen=True)
class NeedleAxisMeasurement:
    """A needle (or guide tube) axis measured in both views and compared with a planned path.

    axis: :class:`hil.geometry.cylinder.TwoViewCylinder` (optical frame); path_error: direction
    error (deg, unoriented) and entry/target offsets (mm) of the measured axis against the path;
    contours_left / contours_right: the detections.
    """

    axis: TwoViewCylinder
    path_error: PathError
    contours_left: NeedleContours
    contours_right: NeedleContours


def _roi_around(
    cal: StereoCalibration, side: str, a_mm: FloatArray, b_mm: FloatArray, margin_px: int
) -> tuple[int, int, int, int]:
    uv_l, uv_r = cal.project(np.vstack([a_mm, b_mm]))
    uv = uv_l if side == "left" else uv_r
    if not np.all(np.isfinite(uv)):
        raise VisionError(f"the expected needle segment is not in front of the {side} camera")
    w, h = cal.image_size
    x0 = int(max(0, math.floor(float(uv[:, 0].min())) - margin_px))
    y0 = int(max(0, math.floor(float(uv[:, 1].min())) - margin_px))
    x1 = int(min(w, math.ceil(float(uv[:, 0].max())) + margin_px))
    y1 = int(min(h, math.ceil(float(uv[:, 1].max())) + margin_px))
    return x0, y0, x1, y1


def measure_needle_axis(
    cal: StereoCalibration,
    left: NDArray[np.uint8],
    right: NDArray[np.uint8],
    expected_start_mm: ArrayLike,
    expected_end_mm: ArrayLike,
    entry_mm: ArrayLike,
    target_mm: ArrayLike,
    *,
    radius_mm: float | None = None,
    margin_px: int = 40,
    polarity: Literal["dark", "bright"] = "dark",
) -> NeedleAxisMeasurement:
    """Measure a visible needle / guide-tube axis in a stereo pair and compare it with the plan.

    The search regions are the projections of the expected segment (``expected_start_mm`` ->
    ``expected_end_mm``, optical frame: e.g. the planned guide axis over the visible needle length,
    moved by the current patient motion) widened by ``margin_px``. The axis comes from the two
    views' contour lines (seed 004 §III, radius-free plane intersection), then
    :func:`hil.geometry.collinear.axis_path_error` against ``entry_mm -> target_mm`` (optical frame).
    Pure CPU, a few tens of ms for two ROIs.

    Raises:
        VisionError: the needle is not found in a view (regions empty, too few edge points).
        DegenerateConfigurationError: the axis lies near an epipolar plane (the two views' axis
            planes coincide) — the check cannot be made from this rig pose.
    """
    a = np.asarray(expected_start_mm, dtype=np.float64).reshape(3)
    b = np.asarray(expected_end_mm, dtype=np.float64).reshape(3)
    det = {}
    for side, img in (("left", left), ("right", right)):
        K, dist, _, _ = cal.camera(side)
        det[side] = detect_needle_contours(
            img, K, dist, roi=_roi_around(cal, side, a, b, margin_px), polarity=polarity
        )
    try:
        axis = cylinder_axis_two_views(cal, det["left"].lines_px, det["right"].lines_px, radius_mm)
    except GeometryError as exc:
        if isinstance(exc, DegenerateConfigurationError):
            raise
        raise VisionError(f"needle contours are not usable: {exc}") from exc
    pe = axis_path_error(axis.axis, entry_mm, target_mm, oriented=False)
    return NeedleAxisMeasurement(axis, pe, det["left"], det["right"])
