"""Synthetic stereo images of ring markers (and chessboards) with ground truth.

Used by the tests, the benchmark and the simulator (which renders every frame), so it is built
for speed: the background (uneven lighting, vignetting, static skin texture and distractors)
and a sensor-noise field are computed once per (calibration, options); a frame is a shifted
window of the cached noisy background plus each marker rendered analytically into a small
supersampled patch (exact ray-plane intersection per sub-sample, box-filter anti-aliasing,
Gaussian defocus blur, fresh Gaussian noise). Lens distortion is exact at pixel corners and
bilinear inside a pixel.

Markers are flat rings (seed 001 section 3.3: outer 7 mm, inner 3 mm) given by their 3D centre
and unit normal in the optical frame; the normal points out of the skin, towards the viewer, so
markers on a plane or on a curved skin patch are just lists of centres and normals.
A dark-on-light marker is a dark ring on the light skin; a light-on-dark marker is a light ring
on a dark backing disc (``backing_ratio`` times the outer diameter).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import VisionError
from hil.geometry.transform import RigidTransform
from hil.vision.camera_model import (
    StereoCalibration,
    distort_pixels,
    pixels_to_normalized,
    project_points,
    undistort_normalized,
)
from hil.vision.conics import circle_image_conic, conic_center, plane_basis

FloatArray = NDArray[np.float64]
U8Image = NDArray[np.uint8]

_NOISE_PAD_PX = 64
_COS24 = np.cos(np.linspace(0, 2 * np.pi, 24, endpoint=False))
_SIN24 = np.sin(np.linspace(0, 2 * np.pi, 24, endpoint=False))


@dataclass(frozen=True, eq=False)
class RingMarker3D:
    """A flat ring marker: centre (mm, optical frame), unit normal (towards the viewer), diameters."""

    center_mm: FloatArray
    normal: FloatArray
    outer_diameter_mm: float = 7.0
    inner_diameter_mm: float = 3.0
    dark_on_light: bool = True
    marker_id: int = 0

    def __post_init__(self) -> None:
        c = np.asarray(self.center_mm, dtype=np.float64).reshape(3)
        n = np.asarray(self.normal, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(n))
        if not (np.all(np.isfinite(c)) and math.isfinite(norm) and norm > 0):
            raise VisionError(f"marker {self.marker_id}: centre/normal must be finite, normal non-zero")
        if not 0 < self.inner_diameter_mm < self.outer_diameter_mm:
            raise VisionError(f"marker {self.marker_id}: need 0 < inner diameter < outer diameter")
        object.__setattr__(self, "center_mm", c)
        object.__setattr__(self, "normal", n / norm)


@dataclass(frozen=True)
class RenderOptions:
    """Image formation settings. Grey levels are 0..255; sizes in pixels.

    noise_sigma: Gaussian sensor noise (grey levels). blur_sigma_px: defocus blur.
    background / foreground: skin and ink grey levels (before lighting).
    vignetting: fractional brightness loss at the image corners. lighting_gradient: fractional
    left-to-right illumination change. texture: amplitude (grey levels) of static low-frequency
    skin texture. distractors: static dark blobs (freckles, filled discs) in the background.
    glare_spots: specular highlights per frame and camera. occluders: bars per frame and camera
    partly covering a random marker (its truth is flagged occluded). supersample: sub-samples per
    pixel side. backing_ratio: backing-disc / outer diameter of light-on-dark markers.
    """

    noise_sigma: float = 2.0
    blur_sigma_px: float = 0.7
    background: float = 200.0
    foreground: float = 40.0
    vignetting: float = 0.15
    lighting_gradient: float = 0.1
    texture: float = 0.0
    distractors: int = 0
    glare_spots: int = 0
    occluders: int = 0
    supersample: int = 4
    backing_ratio: float = 2.0
    seed: int = 12345


@dataclass(frozen=True)
class MarkerTruth:
    """Ground truth of one marker in one stereo pair.

    center_*_px: the projection of the 3D centre (with distortion) — what a detector should find.
    ellipse_center_*_px: the centre of the image ellipse of the outer circle (ideal camera, then
    distorted), which differs from the projected centre under perspective.
    visible_*: fully inside the image and facing the camera. occluded_*: an occluder or a glare
    spot was drawn over it.
    """

    marker_id: int
    center_mm: FloatArray
    center_left_px: FloatArray
    center_right_px: FloatArray
    ellipse_center_left_px: FloatArray
    ellipse_center_right_px: FloatArray
    visible_left: bool
    visible_right: bool
    occluded_left: bool = False
    occluded_right: bool = False


@dataclass(frozen=True)
class RenderedPair:
    """A rendered stereo pair: HxW uint8 mono images and the per-marker truth."""

    left: U8Image
    right: U8Image
    truth: tuple[MarkerTruth, ...] = field(default_factory=tuple)


# ---- cached per (camera, options) --------------------------------------------------------
@dataclass
class _CameraScene:
    gain: NDArray[np.float32]  # illumination gain per pixel
    background: NDArray[np.float32]  # clean background grey levels
    background_u8: U8Image
    noise_pos: U8Image  # positive part of the cached noise field (padded)
    noise_neg: U8Image


_SCENE_CACHE: OrderedDict[tuple[object, ...], _CameraScene] = OrderedDict()


def _scene(K: FloatArray, image_size: tuple[int, int], side: str, options: RenderOptions) -> _CameraScene:
    key = (tuple(np.round(K.ravel(), 9)), image_size, side, options)
    hit = _SCENE_CACHE.get(key)
    if hit is not None:
        _SCENE_CACHE.move_to_end(key)
        return hit
    w, h = image_size
    rng = np.random.default_rng([options.seed, 0 if side == "left" else 1])
    xs = (np.arange(w, dtype=np.float32) - w / 2) / (w / 2)
    ys = (np.arange(h, dtype=np.float32) - h / 2) / (w / 2)
    r2 = xs[None, :] ** 2 + ys[:, None] ** 2
    r2max = 1.0 + (h / w) ** 2
    gain = (1.0 - options.vignetting * r2 / r2max) * (1.0 + options.lighting_gradient * 0.5 * xs[None, :])
    gain = gain.astype(np.float32)
    bg = (options.background * gain).astype(np.float32)
    if options.texture > 0:
        small = rng.standard_normal((h // 32 + 2, w // 32 + 2)).astype(np.float32)
        tex = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
        tex = cv2.GaussianBlur(tex, (0, 0), 12.0)
        tex = (tex * (options.texture / max(float(tex.std()), 1e-6))).astype(np.float32)
        bg += tex
    for _ in range(options.distractors):
        cx, cy = rng.uniform(40, w - 40), rng.uniform(40, h - 40)
        ax, ay = rng.uniform(2.0, 9.0), rng.uniform(2.0, 9.0)
        level = float(rng.uniform(options.foreground, (options.foreground + options.background) / 2))
        kind = rng.integers(0, 3)
        sub = np.zeros((h, w), np.uint8)
        center = (int(cx * 16), int(cy * 16))
        axes = (int(ax * 16), int(ay * 16))
        if kind == 2:  # a single (non-ring) circle outline: must not pass the ring check
            cv2.ellipse(sub, center, axes, float(rng.uniform(0, 180)), 0, 360, 255, 2, cv2.LINE_AA, 4)
        else:  # a filled dark blob (freckle)
            cv2.ellipse(sub, center, axes, float(rng.uniform(0, 180)), 0, 360, 255, -1, cv2.LINE_AA, 4)
        a = sub.astype(np.float32) / 255.0
        bg = bg * (1 - a) + level * gain * a
    bg_u8 = np.clip(np.rint(bg), 0, 255).astype(np.uint8)
    noise = rng.normal(0.0, options.noise_sigma, (h + _NOISE_PAD_PX, w + _NOISE_PAD_PX))
    noise = np.rint(noise)
    scene = _CameraScene(
        gain=gain,
        background=bg,
        background_u8=bg_u8,
        noise_pos=np.clip(noise, 0, 255).astype(np.uint8),
        noise_neg=np.clip(-noise, 0, 255).astype(np.uint8),
    )
    _SCENE_CACHE[key] = scene
    while len(_SCENE_CACHE) > 8:
        _SCENE_CACHE.popitem(last=False)
    return scene


def _noisy_background(scene: _CameraScene, rng: np.random.Generator) -> U8Image:
    h, w = scene.background_u8.shape
    oy, ox = (int(v) for v in rng.integers(0, _NOISE_PAD_PX, size=2))
    img = cv2.add(scene.background_u8, scene.noise_pos[oy : oy + h, ox : ox + w])
    return np.asarray(cv2.subtract(img, scene.noise_neg[oy : oy + h, ox : ox + w]), dtype=np.uint8)


# ---- one marker into one camera ----------------------------------------------------------
def _subsample_normalized(
    K: FloatArray, dist: FloatArray, x0: int, y0: int, pw: int, ph: int, s: int
) -> tuple[FloatArray, FloatArray]:
    """Undistorted normalised coordinates of the s x s sub-samples of each pixel in a patch."""
    gx, gy = np.meshgrid(np.arange(pw + 1) + x0 - 0.5, np.arange(ph + 1) + y0 - 0.5)
    corners = np.stack([gx.ravel(), gy.ravel()], axis=1)
    xy = pixels_to_normalized(corners, K)
    if np.any(dist):
        xy = undistort_normalized(xy, dist)
    X = xy[:, 0].reshape(ph + 1, pw + 1)
    Y = xy[:, 1].reshape(ph + 1, pw + 1)
    f = (np.arange(s) + 0.5) / s

    def interp(A: FloatArray) -> FloatArray:
        rows = A[:-1, None, :] * (1 - f)[None, :, None] + A[1:, None, :] * f[None, :, None]  # (ph, s, pw+1)
        out = rows[:, :, :-1, None] * (1 - f) + rows[:, :, 1:, None] * f  # (ph, s, pw, s)
        return np.asarray(out.reshape(ph * s, pw * s), dtype=np.float64)

    return interp(X), interp(Y)


def _coverage(
    X: FloatArray, Y: FloatArray, c: FloatArray, n: FloatArray, radii_mm: Sequence[float], s: int
) -> list[NDArray[np.float32]]:
    """Per-pixel area fraction inside each radius.

    Each sub-sample intersects its ray with the marker plane (exact, distortion included through
    X, Y); its coverage is a linear ramp of the signed distance to the circle over the sub-sample's
    footprint (|grad rho| per sub-sample step), not a 0/1 test, so the box-filtered pixel value is
    accurate to second order in the sub-sample size; the pixel is the mean of its s x s sub-samples.
    """
    nd = n[0] * X + n[1] * Y + n[2]
    t = float(n @ c) / nd
    px, py, pz = t * X - c[0], t * Y - c[1], t - c[2]
    rho = np.sqrt(px * px + py * py + pz * pz)
    rho[t <= 0] = np.inf
    gy, gx = np.gradient(rho)
    step = np.sqrt(gx * gx + gy * gy)
    step = np.where(np.isfinite(step) & (step > 0), step, np.inf)
    out = []
    ph, pw = X.shape[0] // s, X.shape[1] // s
    for r in radii_mm:
        inside = np.clip(0.5 + (r - rho) / step, 0.0, 1.0).astype(np.float32)
        out.append(inside.reshape(ph, s, pw, s).mean(axis=(1, 3)))
    return out


def _marker_bbox(
    K: FloatArray, dist: FloatArray, c: FloatArray, n: FloatArray, radius_mm: float
) -> FloatArray | None:
    e1, e2 = plane_basis(n)
    pts = c + radius_mm * (_COS24[:, None] * e1 + _SIN24[:, None] * e2)
    if np.any(pts[:, 2] <= 1.0):
        return None
    uv = project_points(pts, K, dist)
    return np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])


def _draw_marker(
    img: U8Image,
    scene: _CameraScene,
    K: FloatArray,
    dist: FloatArray,
    c: FloatArray,
    n: FloatArray,
    m: RingMarker3D,
    opt: RenderOptions,
    rng: np.random.Generator,
    bbox_outer: FloatArray | None = None,
) -> None:
    ro, ri = m.outer_diameter_mm / 2, m.inner_diameter_mm / 2
    rb = ro * opt.backing_ratio if not m.dark_on_light else ro
    bbox = bbox_outer if (m.dark_on_light and bbox_outer is not None) else _marker_bbox(K, dist, c, n, rb)
    if bbox is None:
        return
    h, w = img.shape
    margin = math.ceil(3.5 * opt.blur_sigma_px) + 2
    x0, y0 = max(math.floor(bbox[0]) - margin, 0), max(math.floor(bbox[1]) - margin, 0)
    x1, y1 = min(math.ceil(bbox[2]) + margin + 1, w), min(math.ceil(bbox[3]) + margin + 1, h)
    pw, ph = x1 - x0, y1 - y0
    if pw <= 0 or ph <= 0 or pw * ph > 400 * 400:
        return
    s = max(1, opt.supersample)
    X, Y = _subsample_normalized(K, dist, x0, y0, pw, ph, s)
    gain = scene.gain[y0:y1, x0:x1]
    base = scene.background[y0:y1, x0:x1]
    if m.dark_on_light:
        a_out, a_in = _coverage(X, Y, c, n, (ro, ri), s)
        ring = a_out - a_in
        patch = base * (1 - ring) + (opt.foreground * gain) * ring
        support = a_out
    else:
        a_back, a_out, a_in = _coverage(X, Y, c, n, (rb, ro, ri), s)
        ring = a_out - a_in
        patch = base * (1 - a_back) + (opt.foreground * gain) * a_back
        patch = patch * (1 - ring) + (opt.background * gain) * ring
        support = a_back
    if opt.blur_sigma_px > 0:
        patch = np.asarray(
            cv2.GaussianBlur(patch, (0, 0), opt.blur_sigma_px, borderType=cv2.BORDER_REPLICATE)
        )
        support = np.asarray(
            cv2.GaussianBlur(support, (0, 0), opt.blur_sigma_px, borderType=cv2.BORDER_REPLICATE),
            dtype=np.float32,
        )
    if opt.noise_sigma > 0:
        patch = patch + rng.normal(0.0, opt.noise_sigma, patch.shape).astype(np.float32)
    mask = support > 1e-3
    region = img[y0:y1, x0:x1]
    region[mask] = np.clip(np.rint(patch[mask]), 0, 255).astype(np.uint8)


def _draw_glare(
    img: U8Image, rng: np.random.Generator, near: FloatArray | None
) -> tuple[float, float, float]:
    """A saturated specular highlight; returns (x, y, radius_px) of its visible extent."""
    h, w = img.shape
    if near is not None and rng.random() < 0.5:
        cx, cy = near + rng.normal(0, 4.0, 2)
    else:
        cx, cy = rng.uniform(20, w - 20), rng.uniform(20, h - 20)
    sigma = float(rng.uniform(1.5, 5.0))
    r = int(4 * sigma) + 1
    x0, y0 = int(cx) - r, int(cy) - r
    if x0 < 0 or y0 < 0 or x0 + 2 * r + 1 > w or y0 + 2 * r + 1 > h:
        return float(cx), float(cy), 0.0
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1].astype(np.float32)
    blob = np.exp(-((xx + x0 + r - cx) ** 2 + (yy + y0 + r - cy) ** 2) / (2 * sigma**2)) * 2.0
    blob = np.minimum(blob, 1.0)
    region = img[y0 : y0 + 2 * r + 1, x0 : x0 + 2 * r + 1]
    region[...] = np.clip(region * (1 - blob) + 255.0 * blob, 0, 255).astype(np.uint8)
    return float(cx), float(cy), 2.5 * sigma


def _draw_occluder(
    img: U8Image, uv: FloatArray, size_px: float, rng: np.random.Generator
) -> NDArray[np.float32]:
    """A bar (an instrument, a finger) whose edge passes near the marker centre, covering part of
    it. Returns the bar's corner polygon (4, 2) in pixels."""
    angle = float(rng.uniform(0, np.pi))
    d = np.array([math.cos(angle), math.sin(angle)])
    nrm = np.array([-d[1], d[0]])
    offset = float(rng.uniform(-0.3, 0.3)) * size_px
    width = 1.5 * size_px
    c = uv + nrm * (offset + width / 2)
    half_len = 2.0 * size_px
    pts = np.array(
        [
            c + d * half_len + nrm * width / 2,
            c - d * half_len + nrm * width / 2,
            c - d * half_len - nrm * width / 2,
            c + d * half_len - nrm * width / 2,
        ]
    )
    level = int(rng.uniform(90, 160))
    cv2.fillConvexPoly(img, np.round(pts * 16).astype(np.int32), level, cv2.LINE_AA, 4)
    return pts.astype(np.float32)


def render_stereo(
    cal: StereoCalibration, markers: Sequence[RingMarker3D], options: RenderOptions, rng: np.random.Generator
) -> RenderedPair:
    """Render ``markers`` into both cameras of ``cal``. Non-blocking, pure CPU (~ms per pair).

    Returns a :class:`RenderedPair`; ``truth`` lists every marker in input order. Randomness
    (noise window, fresh patch noise, glare, occluders) comes from ``rng`` only; the static scene
    (texture, distractors, cached noise field) from ``options.seed``.
    """
    w, h = cal.image_size
    margin_px = 2.0
    out: dict[str, U8Image] = {}
    truth_parts: dict[str, list[tuple[FloatArray, FloatArray, bool, bool]]] = {}
    for side in ("left", "right"):
        K, dist, R, t = cal.camera(side)
        scene = _scene(K, cal.image_size, side, options)
        img = _noisy_background(scene, rng)
        parts: list[tuple[FloatArray, FloatArray, bool, bool]] = []
        visible_uv: list[tuple[FloatArray, float, int]] = []
        for idx, m in enumerate(markers):
            c = R @ m.center_mm + t
            n = R @ m.normal
            facing = c[2] > 0 and float(n @ (-c)) / float(np.linalg.norm(c)) > 0.05
            uv = project_points(c[None, :], K, dist)[0]
            if c[2] > 0:
                Cc = circle_image_conic(K, c, n, m.outer_diameter_mm / 2) if facing else None
                ec_ideal = conic_center(Cc) if Cc is not None else uv
                ec = distort_pixels(ec_ideal[None, :], K, dist)[0]
            else:
                ec = np.full(2, np.nan)
            vis = False
            if facing:
                bbox = _marker_bbox(K, dist, c, n, m.outer_diameter_mm / 2)
                vis = bbox is not None and bool(
                    bbox[0] >= margin_px
                    and bbox[1] >= margin_px
                    and bbox[2] <= w - 1 - margin_px
                    and bbox[3] <= h - 1 - margin_px
                )
                _draw_marker(img, scene, K, dist, c, n, m, options, rng, bbox)
                if vis:
                    size_px = float(K[0, 0]) * m.outer_diameter_mm / float(c[2])
                    visible_uv.append((uv, size_px, idx))
            parts.append((uv, ec, vis, False))
        for _ in range(options.occluders):
            if not visible_uv:
                break
            uv, size_px, idx = visible_uv[int(rng.integers(0, len(visible_uv)))]
            poly = _draw_occluder(img, uv, size_px, rng)
            for uv2, size2, idx2 in visible_uv:
                inside = cv2.pointPolygonTest(poly.reshape(-1, 1, 2), (float(uv2[0]), float(uv2[1])), True)
                if idx2 == idx or inside > -(0.5 * size2 + 2.0):
                    p = parts[idx2]
                    parts[idx2] = (p[0], p[1], p[2], True)
        for _ in range(options.glare_spots):
            near = visible_uv[int(rng.integers(0, len(visible_uv)))][0] if visible_uv else None
            gx, gy, gr = _draw_glare(img, rng, near)
            for uv, size_px, idx in visible_uv:
                if gr > 0 and math.hypot(uv[0] - gx, uv[1] - gy) < gr + 0.6 * size_px:
                    p = parts[idx]
                    parts[idx] = (p[0], p[1], p[2], True)
        out[side] = img
        truth_parts[side] = parts
    truth = tuple(
        MarkerTruth(
            marker_id=m.marker_id,
            center_mm=m.center_mm,
            center_left_px=truth_parts["left"][i][0],
            center_right_px=truth_parts["right"][i][0],
            ellipse_center_left_px=truth_parts["left"][i][1],
            ellipse_center_right_px=truth_parts["right"][i][1],
            visible_left=truth_parts["left"][i][2],
            visible_right=truth_parts["right"][i][2],
            occluded_left=truth_parts["left"][i][3],
            occluded_right=truth_parts["right"][i][3],
        )
        for i, m in enumerate(markers)
    )
    return RenderedPair(left=out["left"], right=out["right"], truth=truth)


# ---- marker layouts ----------------------------------------------------------------------
def markers_on_patch(
    centers_mm: ArrayLike,
    normals: ArrayLike | None = None,
    *,
    dark_on_light: bool = True,
    outer_diameter_mm: float = 7.0,
    inner_diameter_mm: float = 3.0,
) -> list[RingMarker3D]:
    """Markers at ``centers_mm`` (N, 3) with ``normals`` (N, 3) (default: facing the left camera)."""
    c = np.asarray(centers_mm, dtype=np.float64).reshape(-1, 3)
    if normals is None:
        nrm = -c / np.linalg.norm(c, axis=1, keepdims=True)
    else:
        nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    return [
        RingMarker3D(c[i], nrm[i], outer_diameter_mm, inner_diameter_mm, dark_on_light, i)
        for i in range(len(c))
    ]


def random_marker_layout(
    rng: np.random.Generator,
    count: int = 8,
    distance_mm: float = 1000.0,
    spread_mm: float = 120.0,
    max_tilt_deg: float = 45.0,
    min_separation_mm: float = 20.0,
    curvature_radius_mm: float | None = 250.0,
) -> list[RingMarker3D]:
    """``count`` markers on a curved skin patch (a cylinder of ``curvature_radius_mm``, None = plane)
    about ``distance_mm`` in front of the rig, tilted up to ``max_tilt_deg`` overall."""
    T = RigidTransform.from_rotvec(
        rng.normal(0.0, 1.0, 3) * np.deg2rad(max_tilt_deg) / 2.5, (60.0, 0.0, distance_mm)
    )
    pts: list[FloatArray] = []
    tries = 0
    while len(pts) < count and tries < 10000:
        tries += 1
        p = rng.uniform(-spread_mm / 2, spread_mm / 2, 2)
        if all(np.linalg.norm(p - q) >= min_separation_mm for q in pts):
            pts.append(p)
    markers = []
    for i, (x, y) in enumerate(pts):
        if curvature_radius_mm is None:
            local, nl = np.array([x, y, 0.0]), np.array([0.0, 0.0, -1.0])
        else:
            a = x / curvature_radius_mm
            local = np.array([curvature_radius_mm * math.sin(a), y, curvature_radius_mm * (1 - math.cos(a))])
            nl = np.array([-math.sin(a), 0.0, -math.cos(a)])
        markers.append(RingMarker3D(T.apply(local[None, :])[0], T.R @ nl, marker_id=i))
    return markers


# ---- chessboard (calibration tests) -------------------------------------------------------
_UNDIST_CACHE: OrderedDict[tuple[object, ...], tuple[NDArray[np.float32], NDArray[np.float32]]] = (
    OrderedDict()
)


def _undistorted_grid(
    K: FloatArray, dist: FloatArray, image_size: tuple[int, int]
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    key = (tuple(np.round(K.ravel(), 9)), tuple(np.round(dist, 12)), image_size)
    hit = _UNDIST_CACHE.get(key)
    if hit is not None:
        return hit
    w, h = image_size
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xy = pixels_to_normalized(np.stack([gx.ravel(), gy.ravel()], axis=1), K)
    if np.any(dist):
        xy = undistort_normalized(xy, dist, iterations=10)
    res = (xy[:, 0].reshape(h, w).astype(np.float32), xy[:, 1].reshape(h, w).astype(np.float32))
    _UNDIST_CACHE[key] = res
    while len(_UNDIST_CACHE) > 2:
        _UNDIST_CACHE.popitem(last=False)
    return res


def chessboard_corners_mm(cols: int, rows: int, square_mm: float) -> FloatArray:
    """Inner-corner positions (cols*rows, 3) on the board plane z = 0, row-major (OpenCV order)."""
    gx, gy = np.meshgrid(np.arange(cols), np.arange(rows))
    return np.stack([gx.ravel() * square_mm, gy.ravel() * square_mm, np.zeros(cols * rows)], axis=1)


_TEX_CACHE: OrderedDict[tuple[object, ...], NDArray[np.float32]] = OrderedDict()


def _board_texture(
    cols: int,
    rows: int,
    square_mm: float,
    tex_per_mm: float,
    dark_level: float,
    light_level: float,
    sigma_tex: float,
) -> NDArray[np.float32]:
    key = (cols, rows, square_mm, tex_per_mm, dark_level, light_level, sigma_tex)
    hit = _TEX_CACHE.get(key)
    if hit is not None:
        return hit
    lo = -2.0 * square_mm
    tw, th = int((cols + 3) * square_mm * tex_per_mm), int((rows + 3) * square_mm * tex_per_mm)
    sq_i = np.floor(((np.arange(tw) + 0.5) / tex_per_mm + lo) / square_mm).astype(int)[None, :]
    sq_j = np.floor(((np.arange(th) + 0.5) / tex_per_mm + lo) / square_mm).astype(int)[:, None]
    on_board = (sq_i >= -1) & (sq_i <= cols - 1) & (sq_j >= -1) & (sq_j <= rows - 1)
    dark = on_board & ((sq_i + sq_j) % 2 == 0)
    tex = np.where(dark, dark_level, light_level).astype(np.float32)
    tex = np.asarray(cv2.GaussianBlur(tex, (0, 0), sigma_tex), dtype=np.float32)
    _TEX_CACHE[key] = tex
    while len(_TEX_CACHE) > 16:
        _TEX_CACHE.popitem(last=False)
    return tex


def render_chessboard(
    K: FloatArray,
    dist: FloatArray,
    image_size: tuple[int, int],
    T_cam_from_board: RigidTransform,
    cols: int,
    rows: int,
    square_mm: float,
    options: RenderOptions,
    rng: np.random.Generator,
) -> U8Image:
    """Render a chessboard with ``cols`` x ``rows`` inner corners (squares of ``square_mm``, one
    square of white margin) seen by a camera (K, dist). Anti-aliased by pre-filtering the board
    texture to the local pixel footprint; blur and noise as ``options``."""
    X, Y = _undistorted_grid(K, np.asarray(dist, dtype=np.float64), image_size)
    R, t = T_cam_from_board.R, T_cam_from_board.t
    # board plane (z = 0) -> normalised image: H = [r1 r2 t]; pixels -> board mm through H^-1
    Hi = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t])).astype(np.float32)
    den = Hi[2, 0] * X + Hi[2, 1] * Y + Hi[2, 2]
    s = den
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / den
    bx = (Hi[0, 0] * X + Hi[0, 1] * Y + Hi[0, 2]) * inv
    by = (Hi[1, 0] * X + Hi[1, 1] * Y + Hi[1, 2]) * inv
    tex_per_mm = 8.0
    lo = -2.0 * square_mm
    mm_per_px = float(t[2]) / float(K[0, 0])
    sigma_tex = round(max(0.5 * mm_per_px * tex_per_mm, 0.5) * 4) / 4
    tex = _board_texture(
        cols, rows, square_mm, tex_per_mm, float(options.foreground), float(options.background), sigma_tex
    )
    mapx = ((bx - lo) * tex_per_mm - 0.5).astype(np.float32)
    mapy = ((by - lo) * tex_per_mm - 0.5).astype(np.float32)
    bad = ~np.isfinite(mapx) | ~np.isfinite(mapy) | (s <= 0)
    mapx[bad], mapy[bad] = -10.0, -10.0
    img = np.asarray(
        cv2.remap(
            tex,
            mapx,
            mapy,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=float(options.background) * 0.8,
        ),
        dtype=np.float32,
    )
    if options.blur_sigma_px > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), options.blur_sigma_px), dtype=np.float32)
    if options.noise_sigma > 0:
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(options.noise_sigma)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def random_board_poses(
    cal: StereoCalibration,
    count: int,
    rng: np.random.Generator,
    cols: int = 6,
    rows: int = 7,
    square_mm: float = 24.0,
    distance_mm: tuple[float, float] = (450.0, 800.0),
    max_tilt_deg: float = 35.0,
    margin_px: float = 40.0,
) -> list[RigidTransform]:
    """``count`` poses T_optical_from_board of a chessboard fully visible (with margin) in both
    cameras of ``cal``, at random distance, position and tilt. For calibration tests."""
    w, h = cal.image_size
    corners = chessboard_corners_mm(cols, rows, square_mm)
    mid = np.array([(cols - 1) * square_mm / 2, (rows - 1) * square_mm / 2, 0.0])
    poses: list[RigidTransform] = []
    for _ in range(count * 200):
        if len(poses) == count:
            break
        z = float(rng.uniform(*distance_mm))
        centre = np.array(
            [
                rng.uniform(-0.3, 0.3) * z * w / (2 * cal.K_left[0, 0]) + cal.baseline_mm / 2,
                rng.uniform(-0.3, 0.3) * z * h / (2 * cal.K_left[1, 1]),
                z,
            ]
        )
        tilt = np.zeros(3)
        tilt[:2] = rng.uniform(-1.0, 1.0, 2) * np.deg2rad(max_tilt_deg)
        tilt[2] = rng.uniform(-0.4, 0.4)
        R = RigidTransform.from_rotvec(tilt).R
        T = RigidTransform(R, centre - R @ mid)
        uv_l, uv_r = cal.project(T.apply(corners))
        uv = np.vstack([uv_l, uv_r])
        if (
            np.all(np.isfinite(uv))
            and uv[:, 0].min() > margin_px
            and uv[:, 1].min() > margin_px
            and uv[:, 0].max() < w - margin_px
            and uv[:, 1].max() < h - margin_px
        ):
            poses.append(T)
    if len(poses) < count:
        raise VisionError(f"could not place {count} chessboard views in both images")
    return poses


def render_chessboard_pair(
    cal: StereoCalibration,
    T_optical_from_board: RigidTransform,
    cols: int,
    rows: int,
    square_mm: float,
    options: RenderOptions,
    rng: np.random.Generator,
) -> tuple[U8Image, U8Image]:
    """Both views of a chessboard at ``T_optical_from_board``."""
    left = render_chessboard(
        cal.K_left, cal.dist_left, cal.image_size, T_optical_from_board, cols, rows, square_mm, options, rng
    )
    T_r = cal.T_right_from_left @ T_optical_from_board
    right = render_chessboard(
        cal.K_right, cal.dist_right, cal.image_size, T_r, cols, rows, square_mm, options, rng
    )
    return left, right
