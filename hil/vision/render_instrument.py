"""Synthetic images of an instrument: a needle (a finite circular cylinder) carrying collinear bead
markers (seed 004 §II-A's markers on the tool axis, §III's markerless cylinder).

Same conventions as :mod:`hil.vision.render`: optical frame = left camera (mm), exact per
sub-sample ray geometry with lens distortion through :func:`hil.vision.render._subsample_normalized`,
box-filtered coverage with a linear ramp of the signed distance over each sub-sample's footprint,
Gaussian defocus blur, fresh Gaussian noise, grey levels 0..255 in :class:`RenderOptions`.
The instrument is composited onto an existing image (e.g. a :func:`hil.vision.render.render_stereo`
frame), so the simulator can draw ring markers and the instrument in one frame. Occlusion between
the instrument and ring markers is not modelled (the instrument is drawn on top).

Truth returned per camera: the two analytic apparent contour lines and the imaged axis (ideal,
undistorted pixels — what :mod:`hil.geometry.cylinder` consumes), and the projected bead centres
(distorted pixels, as a detector sees them).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import DegenerateConfigurationError, VisionError
from hil.geometry.collinear import Line3D
from hil.geometry.cylinder import contour_lines
from hil.geometry.transform import RigidTransform
from hil.vision.camera_model import StereoCalibration, project_points
from hil.vision.render import RenderedPair, RenderOptions, _subsample_normalized

FloatArray = NDArray[np.float64]
U8Image = NDArray[np.uint8]

__all__ = [
    "BeadMarker3D",
    "Instrument3D",
    "InstrumentTruth",
    "RenderedInstrument",
    "draw_instrument",
    "render_instrument_stereo",
]

_MAX_PATCH_PX = 1200 * 1200


@dataclass(frozen=True, eq=False)
class BeadMarker3D:
    """A spherical bead (or LED) of radius ``radius_mm`` centred at ``center_mm`` (optical frame),
    drawn with grey level ``level`` (255: a lit LED)."""

    center_mm: FloatArray
    radius_mm: float = 2.0
    level: float = 255.0


@dataclass(frozen=True, eq=False)
class Instrument3D:
    """A needle (cylinder of ``radius_mm`` from ``tip_mm`` to ``hub_mm``, optical frame) and beads.

    ``marker_positions_mm`` are the beads' axis coordinates measured from the tip towards the hub
    (the ``s_i`` of :func:`hil.geometry.collinear.collinear_pose`), empty without beads.
    """

    tip_mm: FloatArray
    hub_mm: FloatArray
    radius_mm: float = 0.6
    level: float = 60.0
    markers: tuple[BeadMarker3D, ...] = field(default_factory=tuple)
    marker_positions_mm: tuple[float, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        tip = np.asarray(self.tip_mm, dtype=np.float64).reshape(3)
        hub = np.asarray(self.hub_mm, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(tip)) and np.all(np.isfinite(hub))) or np.linalg.norm(hub - tip) < 1e-6:
            raise VisionError("instrument: tip and hub must be finite and distinct")
        if not self.radius_mm > 0:
            raise VisionError("instrument: radius must be positive")
        object.__setattr__(self, "tip_mm", tip)
        object.__setattr__(self, "hub_mm", hub)

    @classmethod
    def needle_with_beads(
        cls,
        tip_mm: ArrayLike,
        direction: ArrayLike,
        length_mm: float,
        *,
        radius_mm: float = 0.6,
        marker_positions_mm: Sequence[float] = (),
        bead_radius_mm: float = 2.0,
        bead_level: float = 255.0,
        level: float = 60.0,
    ) -> Instrument3D:
        """A needle from ``tip_mm`` along ``direction`` (tip -> hub) with beads at the given axis
        coordinates from the tip."""
        tip = np.asarray(tip_mm, dtype=np.float64).reshape(3)
        d = np.asarray(direction, dtype=np.float64).reshape(3)
        d = d / np.linalg.norm(d)
        beads = tuple(
            BeadMarker3D(tip + float(s) * d, bead_radius_mm, bead_level) for s in marker_positions_mm
        )
        return cls(
            tip, tip + length_mm * d, radius_mm, level, beads, tuple(float(s) for s in marker_positions_mm)
        )

    @property
    def axis(self) -> Line3D:
        """The needle axis, directed from the tip towards the hub."""
        return Line3D(self.tip_mm, self.hub_mm - self.tip_mm)


@dataclass(frozen=True)
class InstrumentTruth:
    """Ground truth of the instrument in one camera (see module docstring)."""

    contour_lines_px: FloatArray  # (2, 3) ideal pixels
    axis_line_px: FloatArray  # (3,) ideal pixels
    tip_px: FloatArray  # (2,) distorted pixels
    hub_px: FloatArray
    marker_px: FloatArray  # (n, 2) distorted pixels
    drawn: bool


@dataclass(frozen=True)
class RenderedInstrument:
    """Images with the instrument drawn, and its truth per camera."""

    left: U8Image
    right: U8Image
    truth_left: InstrumentTruth
    truth_right: InstrumentTruth


def _segment_distance(
    X: FloatArray, Y: FloatArray, a: FloatArray, r: FloatArray, length: float
) -> FloatArray:
    """Distance (mm) from each viewing ray (through the camera centre, direction (X, Y, 1)) to the
    segment ``a + s r``, ``0 <= s <= length`` (``r`` unit); inf where the closest point is behind."""
    kx, ky = X, Y
    kk = kx * kx + ky * ky + 1.0
    b = kx * r[0] + ky * r[1] + r[2]
    ka = kx * a[0] + ky * a[1] + a[2]
    ra = float(r @ a)
    denom = kk - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * ka - kk * ra) / denom  # axis parameter of the closest point between the lines
    s = np.where(np.isfinite(s), s, 0.0)
    s = np.clip(s, 0.0, length)
    px = a[0] + s * r[0]
    py = a[1] + s * r[1]
    pz = a[2] + s * r[2]
    mu = (kx * px + ky * py + pz) / kk  # ray parameter of the point's projection on the ray
    dx, dy, dz = px - mu * kx, py - mu * ky, pz - mu
    dist = np.sqrt(dx * dx + dy * dy + dz * dz)
    return np.where(mu > 0, dist, np.inf)


def _sphere_distance(X: FloatArray, Y: FloatArray, c: FloatArray) -> FloatArray:
    kk = X * X + Y * Y + 1.0
    mu = (X * c[0] + Y * c[1] + c[2]) / kk
    dx, dy, dz = c[0] - mu * X, c[1] - mu * Y, c[2] - mu
    return np.where(mu > 0, np.sqrt(dx * dx + dy * dy + dz * dz), np.inf)


def _ramp(dist: FloatArray, radius: float, s: int) -> NDArray[np.float32]:
    gy, gx = np.gradient(np.where(np.isfinite(dist), dist, 1e9))
    step = np.sqrt(gx * gx + gy * gy)
    step = np.where(np.isfinite(step) & (step > 0) & (step < 1e6), step, np.inf)
    cov = np.clip(0.5 + (radius - dist) / step, 0.0, 1.0)
    cov = np.where(np.isfinite(dist), cov, 0.0).astype(np.float32)
    ph, pw = cov.shape[0] // s, cov.shape[1] // s
    return np.asarray(cov.reshape(ph, s, pw, s).mean(axis=(1, 3)), dtype=np.float32)


@dataclass(frozen=True)
class _Patch:
    """The image region an instrument is drawn in: top-left ``(x0, y0)`` and size ``pw x ph`` (px),
    supersampling ``s`` per pixel side, and ``pad_px`` added around every drawn part's box."""

    x0: int
    y0: int
    pw: int
    ph: int
    s: int
    pad_px: int

    def window(self, u_lo: float, v_lo: float, u_hi: float, v_hi: float) -> tuple[int, int, int, int] | None:
        """A pixel window (patch coordinates) around an image box, clipped to the patch."""
        pad, x0, y0, pw, ph = self.pad_px, self.x0, self.y0, self.pw, self.ph
        bx0 = int(np.clip(math.floor(u_lo) - pad - x0, 0, pw))
        bx1 = int(np.clip(math.ceil(u_hi) + pad + 1 - x0, 0, pw))
        by0 = int(np.clip(math.floor(v_lo) - pad - y0, 0, ph))
        by1 = int(np.clip(math.ceil(v_hi) + pad + 1 - y0, 0, ph))
        return None if bx1 <= bx0 or by1 <= by0 else (bx0, by0, bx1, by1)


def _instrument_patch(
    img_shape: tuple[int, ...],
    uv: FloatArray,
    z_min_mm: float,
    K: FloatArray,
    max_radius_mm: float,
    options: RenderOptions,
) -> _Patch | None:
    """The patch around the projected instrument samples ``uv`` (px), with room for its radius
    (seen from ``z_min_mm``, the nearest sample's depth) and the blur; None when outside the image.

    The supersampling is lowered until the patch has at most ``4 * _MAX_PATCH_PX`` subsamples.
    """
    rad_px = float(K[0, 0]) * max_radius_mm / z_min_mm
    margin = math.ceil(rad_px + 3.5 * options.blur_sigma_px) + 3
    h, w = img_shape
    x0 = max(math.floor(float(uv[:, 0].min())) - margin, 0)
    y0 = max(math.floor(float(uv[:, 1].min())) - margin, 0)
    x1 = min(math.ceil(float(uv[:, 0].max())) + margin + 1, w)
    y1 = min(math.ceil(float(uv[:, 1].max())) + margin + 1, h)
    pw, ph = x1 - x0, y1 - y0
    if pw <= 0 or ph <= 0:
        return None
    s = max(1, options.supersample)
    while pw * ph * s * s > _MAX_PATCH_PX * 4 and s > 1:
        s -= 1
    pad = math.ceil(rad_px + 3.5 * options.blur_sigma_px) + 3
    return _Patch(x0, y0, pw, ph, s, pad)


def _shaft_coverage(
    patch: _Patch,
    K: FloatArray,
    dist: FloatArray,
    a: FloatArray,
    b: FloatArray,
    radius_mm: float,
    seg_px: float,
) -> NDArray[np.float32]:
    """Coverage (0..1, ph x pw) of the shaft from tip ``a`` to hub ``b`` (camera frame, mm).

    Drawn in chunks of ~64 px (``seg_px``: the projected length) so that only a band around the
    needle is evaluated; every chunk uses the distance to the whole segment, so the chunks join
    seamlessly (max over overlaps).
    """
    length = float(np.linalg.norm(b - a))
    r = (b - a) / length
    shaft = np.zeros((patch.ph, patch.pw), np.float32)
    n_chunks = max(1, math.ceil(seg_px / 64.0))
    fs = np.linspace(0.0, 1.0, n_chunks + 1)
    for f0, f1 in itertools.pairwise(fs):
        ends = np.array([a + f0 * (b - a), a + f1 * (b - a)])
        if np.any(ends[:, 2] <= 1.0):
            ends = ends[ends[:, 2] > 1.0]
            if len(ends) == 0:
                continue
        e_uv = project_points(ends, K, dist)
        win = patch.window(
            float(e_uv[:, 0].min()), float(e_uv[:, 1].min()), float(e_uv[:, 0].max()), float(e_uv[:, 1].max())
        )
        if win is None:
            continue
        bx0, by0, bx1, by1 = win
        X, Y = _subsample_normalized(K, dist, patch.x0 + bx0, patch.y0 + by0, bx1 - bx0, by1 - by0, patch.s)
        cov = _ramp(_segment_distance(X, Y, a, r, length), radius_mm, patch.s)
        shaft[by0:by1, bx0:bx1] = np.maximum(shaft[by0:by1, bx0:bx1], cov)
    return shaft


def _bead_layers(
    patch: _Patch, K: FloatArray, dist: FloatArray, beads: list[tuple[FloatArray, BeadMarker3D]]
) -> list[tuple[NDArray[np.float32], float]]:
    """Coverage (0..1, ph x pw) and grey level of each bead in front of the camera and in the patch;
    ``beads`` pairs each bead's centre (camera frame, mm) with the bead."""
    layers: list[tuple[NDArray[np.float32], float]] = []
    for c, m in beads:
        if c[2] <= 1.0:
            continue
        uc = project_points(c[None, :], K, dist)[0]
        rb = float(K[0, 0]) * m.radius_mm / float(c[2])
        win = patch.window(float(uc[0] - rb), float(uc[1] - rb), float(uc[0] + rb), float(uc[1] + rb))
        if win is None:
            continue
        bx0, by0, bx1, by1 = win
        X, Y = _subsample_normalized(K, dist, patch.x0 + bx0, patch.y0 + by0, bx1 - bx0, by1 - by0, patch.s)
        alpha_b = np.zeros((patch.ph, patch.pw), np.float32)
        alpha_b[by0:by1, bx0:bx1] = _ramp(_sphere_distance(X, Y, c), m.radius_mm, patch.s)
        layers.append((alpha_b, m.level))
    return layers


def _composite(
    img: U8Image,
    patch: _Patch,
    layers: list[tuple[NDArray[np.float32], float]],
    options: RenderOptions,
    rng: np.random.Generator,
) -> bool:
    """Blend the coverage ``layers`` (blurred, in order) over the patch of ``img`` (in place), with
    noise where anything is drawn; True when any pixel changed."""
    y0, y1, x0, x1 = patch.y0, patch.y0 + patch.ph, patch.x0, patch.x0 + patch.pw
    base = img[y0:y1, x0:x1].astype(np.float32)
    out = base
    support = np.zeros((patch.ph, patch.pw), np.float32)
    for alpha, level in layers:
        if options.blur_sigma_px > 0:
            alpha = np.asarray(
                cv2.GaussianBlur(alpha, (0, 0), options.blur_sigma_px, borderType=cv2.BORDER_REPLICATE),
                dtype=np.float32,
            )
        out = out * (1 - alpha) + np.float32(level) * alpha
        support = np.maximum(support, alpha)
    if options.noise_sigma > 0:
        out = out + rng.normal(0.0, options.noise_sigma, out.shape).astype(np.float32) * support
    mask = support > 1e-3
    region = img[y0:y1, x0:x1]
    region[mask] = np.clip(np.rint(out[mask]), 0, 255).astype(np.uint8)
    return bool(np.any(mask))


def draw_instrument(
    img: U8Image,
    K: FloatArray,
    dist: FloatArray,
    R_cam_from_optical: FloatArray,
    t_cam_from_optical_mm: FloatArray,
    instrument: Instrument3D,
    options: RenderOptions,
    rng: np.random.Generator,
) -> bool:
    """Composite ``instrument`` onto ``img`` (HxW uint8, modified in place) seen by the camera
    ``(K, dist, R, t)``. Returns False when nothing of it is in front of the camera / in the image.
    Pure CPU, non-blocking; ~10-100 ms for a needle spanning a few hundred pixels at supersample 4."""
    R = np.asarray(R_cam_from_optical, dtype=np.float64)
    t = np.asarray(t_cam_from_optical_mm, dtype=np.float64)
    a = R @ instrument.tip_mm + t
    b = R @ instrument.hub_mm + t
    beads = [(R @ m.center_mm + t, m) for m in instrument.markers]
    # bounding box: sample the segment (with radius) and the beads
    samples = [a + f * (b - a) for f in np.linspace(0.0, 1.0, 33)] + [c for c, _ in beads]
    pts = np.array([p for p in samples if p[2] > 1.0])
    if len(pts) == 0:
        return False
    uv = project_points(pts, K, dist)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if len(uv) == 0:
        return False
    max_radius_mm = max([instrument.radius_mm] + [m.radius_mm for _, m in beads])
    patch = _instrument_patch(img.shape, uv, float(pts[:, 2].min()), K, max_radius_mm, options)
    if patch is None:
        return False
    seg_px = float(np.linalg.norm(uv[-1] - uv[0])) if len(uv) > 1 else 0.0
    shaft = _shaft_coverage(patch, K, dist, a, b, instrument.radius_mm, seg_px)
    layers = [(shaft, instrument.level), *_bead_layers(patch, K, dist, beads)]
    return _composite(img, patch, layers, options, rng)


def _truth(
    K: FloatArray, dist: FloatArray, R: FloatArray, t: FloatArray, inst: Instrument3D, drawn: bool
) -> InstrumentTruth:
    T = RigidTransform(R, t)
    axis_cam = inst.axis.transformed(T)
    try:
        lp, lm = contour_lines(K, axis_cam, inst.radius_mm)
        lines = np.vstack([lp, lm])
    except DegenerateConfigurationError:  # camera inside the cylinder: no contour
        lines = np.full((2, 3), np.nan)
    w_hat = axis_cam.moment_mm
    l_axis = np.linalg.solve(K.T, w_hat)
    l_axis = l_axis / math.hypot(float(l_axis[0]), float(l_axis[1]))
    ends = project_points(np.vstack([T.apply(inst.tip_mm), T.apply(inst.hub_mm)]), K, dist)
    mk = (
        project_points(np.array([T.apply(m.center_mm) for m in inst.markers]), K, dist)
        if inst.markers
        else np.zeros((0, 2))
    )
    return InstrumentTruth(lines, np.asarray(l_axis, dtype=np.float64), ends[0], ends[1], mk, drawn)


def render_instrument_stereo(
    cal: StereoCalibration,
    instrument: Instrument3D,
    options: RenderOptions,
    rng: np.random.Generator,
    *,
    base: RenderedPair | None = None,
) -> RenderedInstrument:
    """Draw ``instrument`` into both views of ``cal``: onto copies of ``base``'s images (a
    :func:`hil.vision.render.render_stereo` frame) or onto plain backgrounds of
    ``options.background`` with sensor noise."""
    w, h = cal.image_size
    images: dict[str, U8Image] = {}
    truths: dict[str, InstrumentTruth] = {}
    for side in ("left", "right"):
        K, dist, R, t = cal.camera(side)
        if base is not None:
            img = (base.left if side == "left" else base.right).copy()
        else:
            bg = np.full((h, w), options.background, np.float32)
            if options.noise_sigma > 0:
                bg += rng.normal(0.0, options.noise_sigma, bg.shape).astype(np.float32)
            img = np.clip(np.rint(bg), 0, 255).astype(np.uint8)
        drawn = draw_instrument(img, K, dist, R, t, instrument, options, rng)
        images[side] = img
        truths[side] = _truth(K, dist, R, t, instrument, drawn)
    return RenderedInstrument(images["left"], images["right"], truths["left"], truths["right"])
