"""Ring-marker detection on full frames (seed 001 section 3.3, improved).

Pipeline:
1. Candidates, without a hand-drawn ROI: the frame is downsampled 2x, dark blobs are found by a
   local-mean contrast threshold and connected components (a dark-on-light ring is dark; the
   backing disc of a light-on-dark ring is dark too), and each becomes a full-resolution ROI.
2. Coarse ring structure per ROI, the paper's steps (3x3 median, binarisation with Otsu): a ring
   is a component of either polarity that does not touch the ROI border and holds one hole of
   the right relative size. Its contours give initial outer/inner ellipses.
3. Sub-pixel edge points: intensity profiles along rays from the centre (bicubic samples every
   0.25 px); the outer and inner edges are the mid-level crossings between the ring level and
   the background/hole level.
4. Direct ellipse-specific fit (Fitzgibbon 1999) of each edge, one robust re-fit without points
   beyond 3 MAD, and the ring check: inner and outer ellipses concentric, axis ratio near the
   marker's (3:7), the same eccentricity and orientation, residuals small, the edge found on
   most rays. Glare blobs, freckles, skin texture and partly occluded markers fail it.
5. Centre: the two conic centres weighted by their variance; uncertainty from the residuals.
   ``center_concentric_px`` is the image of the true circle centre from the two concentric conics
   (see :func:`hil.vision.conics.concentric_center`); the stereo stage can instead correct the
   perspective bias with the plane normal (:mod:`hil.vision.stereo`).

:func:`detect_rings_paper` is the seed-001 pipeline as published (on the same candidate ROIs),
kept for comparison.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from hil.errors import VisionError
from hil.vision import kernel
from hil.vision.conics import concentric_center, conic_center
from hil.vision.ellipse import Ellipse, EllipseArrays, fit_conic_paper, fit_ellipse_arrays
from hil.vision.frozen import frozen_instance
from hil.vision.ring_edges import RingEdges, RingSeeds, ring_edges, ring_edges_multi

FloatArray = NDArray[np.float64]
U8Image = NDArray[np.uint8]
Contour = NDArray[np.int32]  # OpenCV contour points (N, 1, 2)


@dataclass(frozen=True)
class DetectParams:
    """Detection settings (pixels and grey levels).

    downsample: factor of the candidate search. min_contrast: grey levels a blob must be darker
    than its surroundings. min_outer_px / max_outer_px: outer diameter range. n_rays: edge rays.
    inner_outer_ratio: inner/outer diameter of the marker (3/7, seed 001). ratio_tol: allowed
    deviation of the measured ratio. max_residual_px: RMS Sampson residual allowed per ellipse.
    min_valid_fraction: fraction of rays on which both edges must be found.
    """

    downsample: int = 2
    min_contrast: float = 25.0
    min_outer_px: float = 5.0
    max_outer_px: float = 150.0
    n_rays: int = 32
    inner_outer_ratio: float = 3.0 / 7.0
    ratio_tol: float = 0.14
    max_residual_px: float = 0.3
    min_valid_fraction: float = 0.85
    concentric_tol: float = 0.08  # centre distance / outer semi-major axis
    eccentricity_tol: float = 0.12  # |b/a outer - b/a inner|


def center_weights(outer: Ellipse, inner: Ellipse) -> tuple[float, float]:
    """Weights of the outer and inner conic centres in a ring's centre: their edge lengths."""
    po, pi = outer.a_px + outer.b_px, inner.a_px + inner.b_px
    return po / (po + pi), pi / (po + pi)


@dataclass(frozen=True, eq=False)
class RingDetection:
    """One ring marker in one image (pixels, the image's own distorted coordinates).

    center_px: best centre (variance-weighted conic centres). center_sigma_px: its 1-sigma
    uncertainty per axis. outer / inner: the fitted ellipses. center_concentric_px: projected
    circle centre from the two concentric conics: see :meth:`center_concentric_px`. residual_px: RMS
    Sampson residual over both edges. dark_on_light: polarity. valid_fraction: rays with both edges.
    """

    center_px: FloatArray
    center_sigma_px: float
    outer: Ellipse
    inner: Ellipse
    residual_px: float
    dark_on_light: bool
    valid_fraction: float

    def center_concentric_px(self) -> FloatArray | None:
        """Projected circle centre from the two concentric conics (None if not computable)."""
        cc = concentric_center(self.outer.conic, self.inner.conic)
        if cc is None or float(np.linalg.norm(cc - self.outer.center_px)) > 0.5 * self.outer.a_px:
            return None
        return cc

    def to_dict(self) -> dict[str, object]:
        cc = self.center_concentric_px()
        return {
            "center_px": [float(v) for v in self.center_px],
            "center_sigma_px": self.center_sigma_px,
            "center_concentric_px": None if cc is None else [float(v) for v in cc],
            "residual_px": self.residual_px,
            "dark_on_light": self.dark_on_light,
            "valid_fraction": self.valid_fraction,
            "outer": self.outer.to_dict(),
            "inner": self.inner.to_dict(),
        }


def validate_image(img: object, name: str = "image", expected_size: tuple[int, int] | None = None) -> U8Image:
    """Check a frame is a non-empty 2D uint8 (grey) array, optionally of ``expected_size`` (w, h).

    Raises:
        VisionError: not an array, empty, colour (H, W, 3), wrong dtype or wrong size.
    """
    if not isinstance(img, np.ndarray):
        raise VisionError(f"{name}: expected a numpy image, got {type(img).__name__}")
    if img.size == 0:
        raise VisionError(f"{name}: image is empty (shape {img.shape})")
    if img.ndim == 3:
        raise VisionError(
            f"{name}: expected a grey image (H, W), got a {img.shape[2]}-channel image {img.shape}; "
            "convert it to grey first"
        )
    if img.ndim != 2:
        raise VisionError(f"{name}: expected a 2-D grey image, got shape {img.shape}")
    if img.dtype != np.uint8:
        raise VisionError(f"{name}: expected 8-bit pixels (uint8), got {img.dtype}")
    if expected_size is not None and (img.shape[1], img.shape[0]) != tuple(expected_size):
        raise VisionError(
            f"{name}: image is {img.shape[1]}x{img.shape[0]} but the calibration is for "
            f"{expected_size[0]}x{expected_size[1]}"
        )
    return img


# ---- 1. candidates -----------------------------------------------------------------------
def find_candidates(img: U8Image, params: DetectParams = DetectParams()) -> list[tuple[int, int, int, int]]:
    """Full-resolution ROIs (x0, y0, x1, y1) of dark blobs that may hold a ring, largest first."""
    h, w = img.shape
    f = max(1, params.downsample)
    small: U8Image = (
        np.asarray(cv2.resize(img, (w // f, h // f), interpolation=cv2.INTER_AREA), dtype=np.uint8)
        if f > 1
        else img
    )
    k = max(7, int(params.max_outer_px / f / 3) | 1)
    diff = cv2.subtract(local_mean(small, k), small)
    thr = params.min_contrast * 0.6
    _, mask = cv2.threshold(diff, thr, 255, cv2.THRESH_BINARY)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    boxes: list[tuple[int, int, int, int]] = []
    min_s, max_s = params.min_outer_px / f * 0.6, params.max_outer_px / f * 2.2
    rects = [cv2.boundingRect(c) for c in contours]
    # a large blob (a bar, a shadow, dark texture) may have swallowed rings touching it: split it
    # at a higher contrast level and keep both the blob and its parts as candidates
    for x, y, bw, bh in list(rects):
        if max(bw, bh) > 4 * min_s + 8:
            sub = np.ascontiguousarray(diff[y : y + bh, x : x + bw])
            for level in (2.0 * thr, 3.5 * thr):
                _, m2 = cv2.threshold(sub, level, 255, cv2.THRESH_BINARY)
                parts, _ = cv2.findContours(m2, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
                for c in parts:
                    px, py, pw, ph = cv2.boundingRect(c)
                    if (pw, ph) != (bw, bh):
                        rects.append((px + x, py + y, pw, ph))
    rects.sort(key=lambda r: -r[2] * r[3])
    for x, y, bw, bh in rects:
        if not (min_s <= bw <= max_s and min_s <= bh <= max_s) or bw * bh < 3:
            continue
        if max(bw, bh) > 3 * min(bw, bh) + 2:
            continue
        cx, cy = (x + bw / 2) * f, (y + bh / 2) * f
        # a smaller blob concentric with a kept one (the hole of a light-on-dark ring) is the same
        if any(
            abs(cx - (b[0] + b[2]) / 2) + abs(cy - (b[1] + b[3]) / 2) < 0.2 * (b[2] - b[0] + b[3] - b[1])
            for b in boxes
        ):
            continue
        half = max(bw, bh) * f * 0.5 * 1.35 + 4
        x0, y0 = max(int(cx - half), 0), max(int(cy - half), 0)
        x1, y1 = min(math.ceil(cx + half), w), min(math.ceil(cy + half), h)
        boxes.append((x0, y0, x1, y1))
    return boxes


#: below this box side (px) :func:`local_mean` blurs at full resolution: the half-resolution
#: estimate pays for its resize and upsampling only on a large box
_HALF_RES_MIN_BOX = 13


def local_mean(img: U8Image, k: int) -> U8Image:
    """The local mean grey level around each pixel of ``img`` over about a ``k`` x ``k`` box, the
    background a dark blob is measured against (same shape and type as ``img``).

    For ``k`` >= 13 it is computed at half resolution: a 2x2 area average, a (k // 2 | 1)-wide box
    and a Gaussian 2x upsampling (``cv2.pyrUp``), i.e. a box of about ``k`` px smoothed a little
    further. OpenCV's box filter costs ~0.8 ms on a 960x540 image with a 25-px box and one thread,
    this 0.35-0.45 ms (docs/benchmarks.md); the mean is a threshold's reference, not a measurement
    (sub-pixel centres come from the rays of :mod:`hil.vision.ring_edges` on the full-resolution
    image), so the extra smoothing changes which pixels pass only at the margin of the contrast
    threshold."""
    h, w = img.shape
    if k < _HALF_RES_MIN_BOX or h < 2 * k or w < 2 * k:
        return np.asarray(cv2.blur(img, (k, k)), dtype=np.uint8)
    # even sides: OpenCV's 2x2 area average takes its fast path only for an exact factor of 2
    half = cv2.resize(img[: h // 2 * 2, : w // 2 * 2], (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    mean_half = cv2.blur(half, (k // 2 | 1, k // 2 | 1))
    return np.asarray(cv2.pyrUp(mean_half, dstsize=(w, h)), dtype=np.uint8)


# ---- 2. coarse ring structure ------------------------------------------------------------
def _coarse_rings(roi: U8Image, params: DetectParams) -> Iterator[tuple[Contour, Contour, bool]]:
    """Initial (outer contour, inner contour, dark_on_light) ring hypotheses in a ROI, best first
    (lazily): the paper's 3x3 median + Otsu, then raw pixels with the threshold moved towards
    either level (a 3x3 median can close a 2-px hole; a touching freckle can merge at Otsu's level)."""
    med = _median3(roi)
    otsu, dark = cv2.threshold(med, 0, 255, cv2.THRESH_BINARY_INV | cv2.THRESH_OTSU)
    found = _ring_in_mask(np.asarray(dark, dtype=np.uint8), params)
    if found is not None:
        yield found
    lo, hi = float(roi.min()), float(roi.max())
    for t in (otsu, otsu - 0.4 * (otsu - lo), otsu + 0.4 * (hi - otsu)):
        _, dark = cv2.threshold(roi, t, 255, cv2.THRESH_BINARY_INV)
        found = _ring_in_mask(np.asarray(dark, dtype=np.uint8), params)
        if found is not None:
            yield found


#: OpenCV's 3x3 median of 8-bit images takes its vectorised path from a width of ~66 px; on the
#: narrower ROIs of ring candidates the scalar path costs ~6x more (10 us for 26 x 26 px)
_MEDIAN_MIN_WIDTH = 80


def _median3(roi: U8Image) -> U8Image:
    """``cv2.medianBlur(roi, 3)`` (border replicated), pixel for pixel: a ROI narrower than
    ``_MEDIAN_MIN_WIDTH`` is first padded on the right with copies of its last column, which is
    what the replicated border gives its last column anyway, and the result cut back."""
    w = roi.shape[1]
    if w >= _MEDIAN_MIN_WIDTH:
        return np.asarray(cv2.medianBlur(roi, 3), dtype=np.uint8)
    padded = cv2.copyMakeBorder(roi, 0, 0, 0, _MEDIAN_MIN_WIDTH - w, cv2.BORDER_REPLICATE)
    return np.ascontiguousarray(cv2.medianBlur(padded, 3)[:, :w])


def _ring_in_mask(dark: U8Image, params: DetectParams) -> tuple[Contour, Contour, bool] | None:
    """The ring in a binary ROI: a component (dark first, then bright) not touching the border
    with exactly one hole of plausible relative size and nothing inside that hole (which rules
    out the backing disc of a light-on-dark marker, whose hole holds the ring's own hole)."""
    h, w = dark.shape
    for dark_on_light in (True, False):
        mask = dark if dark_on_light else cv2.bitwise_not(dark)
        contours, hier_raw = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
        if len(contours) == 0:
            continue
        hier: list[list[int]] = np.asarray(hier_raw, dtype=np.int64).reshape(-1, 4).tolist()
        tops = [i for i in range(len(contours)) if hier[i][3] == -1]
        rects = {i: cv2.boundingRect(contours[i]) for i in tops}
        best: tuple[float, Contour, Contour] | None = None
        for i in tops:
            cnt = contours[i]
            x, y, bw, bh = rects[i]
            if len(cnt) < 8 or x == 0 or y == 0 or x + bw >= w or y + bh >= h:
                continue
            child = hier[i][2]
            holes = []
            while child != -1:
                if len(contours[child]) >= 5:
                    holes.append(contours[child])
                child = hier[child][0]
            if len(holes) != 1:
                continue
            area_o, area_i = cv2.contourArea(cnt), cv2.contourArea(holes[0])
            if area_o <= 0:
                continue
            ratio = math.sqrt(max(area_i, 0.0) / area_o)
            if not 0.15 < ratio < 0.75:
                continue
            hx, hy, hw, hh = cv2.boundingRect(holes[0])
            if any(
                j != i
                and rects[j][0] >= hx
                and rects[j][1] >= hy
                and rects[j][0] + rects[j][2] <= hx + hw
                and rects[j][1] + rects[j][3] <= hy + hh
                for j in tops
            ):
                continue
            if best is None or area_o > best[0]:
                best = (
                    area_o,
                    np.asarray(cnt),
                    np.asarray(holes[0]),
                )
        if best is not None:
            return best[1], best[2], dark_on_light
    return None


def _initial_ellipse(pts: Contour) -> tuple[FloatArray, float, float, float]:
    (cx, cy), (d1, d2), ang = cv2.fitEllipse(pts)
    a, b = d1 / 2.0, d2 / 2.0
    angle = math.radians(ang)
    if b > a:
        a, b, angle = b, a, angle + math.pi / 2
    return np.array([cx, cy]), a, b, angle


# ---- 3.+4. sub-pixel edges, fits, ring check ------------------------------------------------
_SeedRow = tuple[float, float, float, float, float, float, float, float, bool]


def _seed_row(
    x0: int, y0: int, outer_pts: Contour, inner_pts: Contour, dark_on_light: bool, params: DetectParams
) -> _SeedRow | None:
    """:func:`seed_from_contours` as one row: origin x, y, outer a, b, angle, inner a, b, angle,
    polarity."""
    c0, ao, bo, ango = _initial_ellipse(outer_pts)
    _, ai, bi, angi = _initial_ellipse(inner_pts)
    if not params.min_outer_px <= 2 * ao <= params.max_outer_px:
        return None
    # outer contour pixels lie ~0.5 px inside the edge, hole pixels ~0.5 px outside it
    return (float(c0[0] + x0), float(c0[1] + y0), ao + 0.5, bo + 0.5, ango,
            max(ai - 0.5, 0.8), max(bi - 0.5, 0.8), angi, dark_on_light)


def _seeds_of_rows(rows: Sequence[_SeedRow]) -> RingSeeds:
    if not rows:
        return RingSeeds.stack([])
    v = np.array([r[:8] for r in rows], dtype=np.float64)
    return RingSeeds(v[:, 0:2], v[:, 2:5], v[:, 5:8], np.array([r[8] for r in rows], dtype=bool))


def seed_from_contours(
    x0: int, y0: int, outer_pts: Contour, inner_pts: Contour, dark_on_light: bool, params: DetectParams
) -> RingSeeds | None:
    """The ray seed of one coarse ring hypothesis of a ROI at (x0, y0): origin at the outer
    contour's ellipse centre, radii of the contours' ellipses (None: outer size out of range)."""
    row = _seed_row(x0, y0, outer_pts, inner_pts, dark_on_light, params)
    return None if row is None else _seeds_of_rows([row])


def edges_of(img: U8Image, seeds: RingSeeds, params: DetectParams) -> RingEdges:
    """:func:`hil.vision.ring_edges.ring_edges` with the detection settings."""
    return ring_edges(img, seeds, params.n_rays, params.min_contrast, params.min_valid_fraction)


def fit_rings(edges: RingEdges, params: DetectParams) -> list[RingDetection | None]:
    """Robust ellipse fits of every ring's two edges in one batch, then the ring check and the
    centre estimate, all rings at once; None for a ring whose edges failed (``edges.ok`` False)
    or that is not a ring marker.

    Ring check: both fits real ellipses with RMS residual <= ``max_residual_px``, concentric
    (centre distance <= ``concentric_tol`` x outer a + 0.15 px), inner/outer size ratio within
    ``ratio_tol`` of the marker's, equal eccentricity (|b/a| difference <= ``eccentricity_tol``).
    Centre: the two conic centres weighted by edge length (the number of independent edge pixels;
    the per-point residuals understate the inner edge's pixel-grid bias); its uncertainty from the
    circle-fit variance 2 sigma^2 / N per axis of each ellipse.
    """
    idx = np.nonzero(edges.ok)[0]
    out: list[RingDetection | None] = [None] * int(edges.ok.size)
    if idx.size == 0:
        return out
    m = idx.size
    f = fit_ellipse_arrays(
        np.concatenate([edges.xo[idx], edges.xi[idx]]),
        np.concatenate([edges.yo[idx], edges.yi[idx]]),
        np.concatenate([edges.mo[idx], edges.mi[idx]]),
    )
    kern = kernel.active()
    check = _ring_check(f, m, params) if kern is None else _ring_check_kernel(kern, f, m, params)
    ok, center, sigma, resid = check
    keep = np.nonzero(ok)[0]
    outers, inners = f.ellipses(keep), f.ellipses(keep + m)
    rows = idx[keep]
    centers = center[keep]
    sig, res = sigma[keep].tolist(), resid[keep].tolist()
    dol, frac = edges.dark_on_light[rows].tolist(), edges.frac[rows].tolist()
    for k, j in enumerate(rows.tolist()):
        out[j] = frozen_instance(RingDetection, {
            "center_px": centers[k], "center_sigma_px": sig[k], "outer": outers[k], "inner": inners[k],
            "residual_px": res[k], "dark_on_light": dol[k], "valid_fraction": frac[k],
        })
    return out


_RingCheck = tuple[NDArray[np.bool_], FloatArray, FloatArray, FloatArray]


def _ring_check(f: EllipseArrays, m: int, params: DetectParams) -> _RingCheck:
    """The ring check and centre of :func:`fit_rings` (numpy reference): m rings whose outer
    ellipses are rows ``0..m-1`` of ``f`` and inner ellipses rows ``m..2m-1``. Returns ok (m,),
    centres (m, 2) px, their sigma (m,) px and the RMS residual over both edges (m,) px."""
    o, i = slice(0, m), slice(m, 2 * m)
    ao, bo, ai, bi = f.a_px[o], f.b_px[o], f.a_px[i], f.b_px[i]
    ro, ri = f.residual_rms_px[o], f.residual_rms_px[i]
    co, ci = f.center_px[o], f.center_px[i]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.sqrt(ai * bi / (ao * bo))
        ecc = np.abs(bo / ao - bi / ai)
    sep = np.hypot(co[:, 0] - ci[:, 0], co[:, 1] - ci[:, 1])
    ok = (
        f.good[o] & f.good[i]
        & (ro <= params.max_residual_px) & (ri <= params.max_residual_px)
        & (sep <= params.concentric_tol * ao + 0.15)
        & (np.abs(ratio - params.inner_outer_ratio) <= params.ratio_tol)
        & (ecc <= params.eccentricity_tol)
    )
    po, pi = ao + bo, ai + bi
    wo, wi = po / (po + pi), pi / (po + pi)
    center = wo[:, None] * co + wi[:, None] * ci
    no, ni = f.n_points[o], f.n_points[i]
    var_o = 2.0 * np.maximum(ro, 0.01) ** 2 / np.maximum(no, 1)
    var_i = 2.0 * np.maximum(ri, 0.01) ** 2 / np.maximum(ni, 1)
    sigma = np.sqrt(wo * wo * var_o + wi * wi * var_i)
    resid = np.sqrt((ro**2 * no + ri**2 * ni) / np.maximum(no + ni, 1))
    return ok, center, sigma, resid


def _ring_check_kernel(k: Any, f: EllipseArrays, m: int, params: DetectParams) -> _RingCheck:
    """:func:`_ring_check` by the compiled kernel (hil/vision/_kernel.c; the same arithmetic)."""
    ok, center, sigma, resid = np.empty(m, dtype=bool), np.empty((m, 2)), np.empty(m), np.empty(m)
    k.ring_check(f.a_px, f.b_px, f.center_px, f.residual_rms_px, f.n_points, f.good,
                 float(params.max_residual_px), float(params.concentric_tol), float(params.inner_outer_ratio),
                 float(params.ratio_tol), float(params.eccentricity_tol), ok, center, sigma, resid)
    return ok, center, sigma, resid


def _refine_hypotheses(
    img: U8Image, box: tuple[int, int, int, int], hyps: Iterator[tuple[Contour, Contour, bool]],
    params: DetectParams,
) -> RingDetection | None:
    """The remaining ring hypotheses of one ROI, one by one, until one passes."""
    x0, y0 = box[0], box[1]
    for outer_pts, inner_pts, dol in hyps:
        seed = seed_from_contours(x0, y0, outer_pts, inner_pts, dol, params)
        if seed is None:
            continue
        det = fit_rings(edges_of(img, seed, params), params)[0]
        if det is not None:
            return det
    return None


def refine_in_box(img: U8Image, box: tuple[int, int, int, int], params: DetectParams) -> RingDetection | None:
    """The ring in one ROI (x0, y0, x1, y1) of a full frame, found as in full-frame detection
    (every coarse hypothesis in turn until one passes); a ring touching the ROI border is not
    found. None when there is none.

    A ROI without the contrast the candidate search needs (:func:`_holds_contrast`) is rejected
    before the coarse step: thresholding sensor noise gives hundreds of specks, and their contours
    cost ~1 ms for a 40 x 40 px window of flat skin (a tracked marker hidden by a hand)."""
    x0, y0, x1, y1 = box
    roi = img[y0:y1, x0:x1]
    if roi.shape[0] < 6 or roi.shape[1] < 6 or not _holds_contrast(roi, params):
        return None
    return _refine_hypotheses(img, box, _coarse_rings(roi, params), params)


def _holds_contrast(roi: U8Image, params: DetectParams) -> bool:
    """Whether ``roi`` can hold a ring that :func:`find_candidates` would see: its candidates are
    pixels of the image reduced by ``params.downsample`` (area average) at least 0.6 x
    ``min_contrast`` darker than their local mean, and a ring inside the ROI (not touching its
    border) has its background there too, so the reduced ROI's grey range must reach that level.
    A necessary condition, not a sufficient one."""
    f = max(1, params.downsample)
    h, w = roi.shape
    small = (
        roi
        if f == 1 or h < 2 * f or w < 2 * f
        else cv2.resize(roi, (w // f, h // f), interpolation=cv2.INTER_AREA)
    )
    lo, hi, _, _ = cv2.minMaxLoc(small)
    return bool(hi - lo >= 0.6 * params.min_contrast)


def detect_rings(
    img: object, params: DetectParams = DetectParams(), name: str = "image"
) -> list[RingDetection]:
    """Find every ring marker in a full grey frame. Pure CPU, a few ms per 1920x1080 frame.

    The first ring hypothesis of every candidate is fitted in one batch (the same fits as one by
    one, with far fewer numpy calls); candidates failing it try their other hypotheses one by one.
    Returns the detections sorted by image row then column.

    Raises:
        VisionError: the image is not a non-empty 2-D uint8 array.
    """
    return detect_rings_multi([(img, name)], params)[0]


_Pending = tuple[tuple[int, int, int, int], Iterator[tuple[Contour, Contour, bool]]]


@dataclass
class FrameSearch:
    """A full-frame search of one (validated) frame in progress: the candidate ROIs with a usable
    first coarse hypothesis (and their remaining hypotheses, lazily) and the ray seeds of those
    first hypotheses, to be fitted -- possibly in one batch with other rings -- and handed to
    :func:`finish_search`."""

    frame: U8Image
    pending: list[_Pending]
    seeds: RingSeeds


def begin_search(frame: U8Image, params: DetectParams = DetectParams()) -> FrameSearch:
    """Candidates and first coarse hypotheses of a full-frame search (see :func:`detect_rings`)."""
    pending: list[_Pending] = []
    rows: list[_SeedRow] = []
    for box in find_candidates(frame, params):
        x0, y0, x1, y1 = box
        if y1 - y0 < 6 or x1 - x0 < 6:
            continue
        hyps = _coarse_rings(frame[y0:y1, x0:x1], params)
        for outer_pts, inner_pts, dol in hyps:
            row = _seed_row(x0, y0, outer_pts, inner_pts, dol, params)
            if row is not None:
                pending.append((box, hyps))
                rows.append(row)
                break
    return FrameSearch(frame, pending, _seeds_of_rows(rows))


def finish_search(
    search: FrameSearch, first_fits: Sequence[RingDetection | None], params: DetectParams = DetectParams()
) -> list[RingDetection]:
    """The detections of a full-frame search from the fits of its first hypotheses (one per seed,
    in order, as :func:`fit_rings` returns them): a candidate whose first hypothesis failed tries
    its other hypotheses one by one; duplicates are dropped; sorted by image row then column."""
    found: list[RingDetection | None] = []
    for (box, hyps), det in zip(search.pending, first_fits, strict=True):
        if det is None:  # the remaining hypotheses of this candidate, one by one
            det = _refine_hypotheses(search.frame, box, hyps, params)
        found.append(det)
    return _deduplicated(found)


def detect_rings_multi(
    images: Sequence[tuple[object, str]], params: DetectParams = DetectParams()
) -> list[list[RingDetection]]:
    """:func:`detect_rings` of several frames (e.g. both of a stereo pair, given with their names
    for the errors), with the first hypotheses of all of them fitted in one batch.

    Raises:
        VisionError: an image is not a non-empty 2-D uint8 array.
    """
    searches = [begin_search(validate_image(img, name), params) for img, name in images]
    dets = fit_rings(
        ring_edges_multi([(sr.frame, sr.seeds) for sr in searches], params.n_rays, params.min_contrast,
                         params.min_valid_fraction),
        params,
    )
    out: list[list[RingDetection]] = []
    start = 0
    for sr in searches:
        out.append(finish_search(sr, dets[start : start + sr.seeds.count], params))
        start += sr.seeds.count
    return out


def _deduplicated(found: list[RingDetection | None]) -> list[RingDetection]:
    """The detections without None and without one within half a kept ring's minor axis of it,
    sorted by row (rounded) then column."""
    out: list[tuple[float, float, RingDetection]] = []
    for det in found:
        if det is None:
            continue
        x, y = det.center_px.tolist()
        if any(math.sqrt((x - ox) ** 2 + (y - oy) ** 2) < 0.5 * o.outer.b_px for ox, oy, o in out):
            continue
        out.append((x, y, det))
    out.sort(key=lambda t: (round(t[1]), t[0]))
    return [d for _, _, d in out]


# ---- the seed-001 pipeline as published, for comparison ------------------------------------
def detect_rings_paper(img: object, params: DetectParams = DetectParams()) -> list[FloatArray]:
    """Seed 001 section 3.3.1-3.3.2 on the same candidate ROIs: 3x3 median, binarisation (Otsu),
    Canny edges of the binary image, least-squares conic of all edge points (eqs 13-16) and its
    centre (eq 17). Returns the centres (pixels); no ring check beyond a valid ellipse."""
    frame = validate_image(img)
    out: list[FloatArray] = []
    for x0, y0, x1, y1 in find_candidates(frame, params):
        roi = _median3(frame[y0:y1, x0:x1])
        _, binary = cv2.threshold(roi, 0, 255, cv2.THRESH_BINARY_INV | cv2.THRESH_OTSU)
        edges = cv2.Canny(binary, 50, 150)
        ys, xs = np.nonzero(edges)
        if xs.size < 6:
            continue
        C = fit_conic_paper(xs.astype(np.float64) + x0, ys.astype(np.float64) + y0)
        if C is None:
            continue
        out.append(conic_center(C))
    return out
