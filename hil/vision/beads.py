"""Bright bead markers on an instrument (seed 004 §II-A): blob detection in a region of interest and
ordering along the instrument, for :func:`hil.geometry.collinear.collinear_pose_stereo`.

Pixels are raw (distorted) image coordinates. Pure CPU, non-blocking.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import VisionError
from hil.geometry.collinear import (
    AxisAgreement,
    CollinearPose,
    Line3D,
    PathError,
    axis_agreement,
    axis_path_error,
    collinear_pose_from_view,
    collinear_pose_stereo,
)
from hil.vision.camera_model import StereoCalibration

FloatArray = NDArray[np.float64]
U8Image = NDArray[np.uint8]

__all__ = ["BeadAxisMeasurement", "bead_centroid", "detect_beads", "measure_bead_axis", "order_along"]


#: where a bead's centroid weights start, as a fraction of the way from its surroundings' grey level
#: up to its peak (see :func:`bead_centroid`)
BEAD_WEIGHT_LEVEL = 0.3


def detect_beads(
    image: U8Image,
    roi: tuple[int, int, int, int],
    count: int,
    *,
    threshold: float = 230.0,
    min_area_px: int = 3,
    max_area_px: int = 2000,
) -> FloatArray:
    """Centres (px, (count, 2)) of the ``count`` largest bright blobs (grey > ``threshold``) inside
    ``roi = (x0, y0, x1, y1)``, each located by :func:`bead_centroid`.

    Raises:
        VisionError: not a 2-D uint8 image, an empty region, or fewer than ``count`` blobs of
            ``min_area_px``..``max_area_px`` pixels.
    """
    if image.ndim != 2 or image.dtype != np.uint8:
        raise VisionError("beads: expected a 2-D uint8 image")
    h, w = image.shape
    x0, y0 = max(0, int(roi[0])), max(0, int(roi[1]))
    x1, y1 = min(w, int(roi[2])), min(h, int(roi[3]))
    if x1 <= x0 or y1 <= y0:
        raise VisionError(f"beads: empty search region {roi}")
    sub = image[y0:y1, x0:x1]
    mask = (sub > threshold).astype(np.uint8)
    _n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(mask)
    areas = stats[1:, cv2.CC_STAT_AREA]
    ok = np.nonzero((areas >= min_area_px) & (areas <= max_area_px))[0]
    if len(ok) < count:
        raise VisionError(f"beads: found {len(ok)} bright blobs, need {count}")
    chosen = ok[np.argsort(-areas[ok], kind="stable")[:count]] + 1
    cents = np.empty((count, 2))
    for i, lab in enumerate(chosen):
        cents[i] = bead_centroid(sub, labels == lab) + np.array([x0, y0], dtype=np.float64)
    return cents


_GROW_3X3 = np.ones((3, 3), np.uint8)
_GROW_5X5 = np.ones((5, 5), np.uint8)


def bead_centroid(image: U8Image, blob: NDArray[np.bool_]) -> FloatArray:
    """Sub-pixel centre (x, y; px of ``image``) of one bright blob given by the mask ``blob``.

    The blob grown by one pixel (its blurred rim included) is weighted by ``max(v - t, 0)`` with
    ``t = B + BEAD_WEIGHT_LEVEL (P - B)``: ``P`` the blob's peak grey level and ``B`` the upper
    quartile of the pixels in the two-pixel ring around it (the surroundings; the upper quartile
    because the instrument's dark shaft runs through part of that ring). The weight is continuous
    in the grey level: sensor noise moving a rim pixel across the level changes the centre by
    almost nothing. (A weight that jumps at a fixed threshold -- 30 grey levels at 230, as this
    function had -- let the noise of one rim pixel move a 5-px bead's centre by ~0.07 px, which
    the stereo axis fit turns into ~1 deg and ~2 mm at the target: false needle alarms.) Falls
    back to the blob's plain centroid when it has no contrast.
    """
    grown = cv2.dilate(blob.astype(np.uint8), _GROW_3X3)
    ring = (cv2.dilate(grown, _GROW_5X5) > 0) & (grown == 0)
    ys, xs = np.nonzero(grown)
    v = image[ys, xs].astype(np.float64)
    peak = float(v.max())
    around = image[ring]
    bg = float(np.percentile(around, 75)) if around.size else float(v.min())
    wts = np.maximum(v - (bg + BEAD_WEIGHT_LEVEL * (peak - bg)), 0.0)
    total = float(wts.sum())
    if not total > 0.0:
        by, bx = np.nonzero(blob)
        return np.array([float(bx.mean()), float(by.mean())])
    return np.array([float(xs @ wts) / total, float(ys @ wts) / total])


def order_along(points_px: FloatArray, start_px: FloatArray, end_px: FloatArray) -> FloatArray:
    """``points_px`` (N, 2) sorted by their coordinate along the image direction ``start -> end``
    (the first is nearest ``start``).

    Raises:
        VisionError: ``start`` and ``end`` coincide.
    """
    d = np.asarray(end_px, dtype=np.float64) - np.asarray(start_px, dtype=np.float64)
    if not np.linalg.norm(d) > 1e-9:
        raise VisionError("beads: the expected instrument direction has no length in the image")
    key = (np.asarray(points_px, dtype=np.float64) - start_px) @ d
    return np.asarray(points_px, dtype=np.float64)[np.argsort(key, kind="stable")]


@dataclass(frozen=True, eq=False)
class BeadAxisMeasurement:
    """An instrument axis measured from its collinear beads (seed 004 §II-A) against a planned path.

    stereo: the two-view estimate (optical frame, direction tip -> hub); mono_left: the single-view
    linear estimate from the left image (optical frame); agreement: the two compared;
    path_error: the stereo axis (oriented, pointing towards the target) against ``entry -> target``
    (deg, mm); beads_left_px / beads_right_px: the detected centres, ordered from the tip.
    """

    stereo: CollinearPose
    mono_left: CollinearPose
    agreement: AxisAgreement
    path_error: PathError
    beads_left_px: FloatArray
    beads_right_px: FloatArray


def measure_bead_axis(
    cal: StereoCalibration,
    left: U8Image,
    right: U8Image,
    expected_start_mm: ArrayLike,
    expected_end_mm: ArrayLike,
    entry_mm: ArrayLike,
    target_mm: ArrayLike,
    positions_mm: Sequence[float],
    *,
    margin_px: int = 40,
    max_mono_stereo_deg: float = 10.0,
) -> BeadAxisMeasurement:
    """Measure an instrument's axis from ``len(positions_mm)`` >= 3 collinear beads in a stereo pair
    and compare it with the plan.

    The beads are searched in the projections of the expected segment (``expected_start_mm`` (hub
    side) -> ``expected_end_mm`` (tip side), optical frame) widened by ``margin_px``, ordered from the
    tip, and fitted with their known axis coordinates ``positions_mm`` (from the tip): the stereo
    estimate (:func:`hil.geometry.collinear.collinear_pose_stereo`) is checked against the left
    view's monocular one (:func:`hil.geometry.collinear.collinear_pose_from_view`,
    :func:`hil.geometry.collinear.axis_agreement`). Pure CPU, a few ms.

    Raises:
        VisionError: beads not found in a view, or the monocular and stereo directions differ by more
            than ``max_mono_stereo_deg``.
        DegenerateConfigurationError: parallel rays / coincident markers.
    """
    a = np.asarray(expected_start_mm, dtype=np.float64).reshape(3)
    b = np.asarray(expected_end_mm, dtype=np.float64).reshape(3)
    s = [float(v) for v in positions_mm]
    found: dict[str, FloatArray] = {}
    for side, img in (("left", left), ("right", right)):
        uv_l, uv_r = cal.project(np.vstack([a, b]))
        uv = uv_l if side == "left" else uv_r
        if not np.all(np.isfinite(uv)):
            raise VisionError(f"beads: the expected instrument is not in front of the {side} camera")
        roi = (
            math.floor(float(uv[:, 0].min())) - margin_px,
            math.floor(float(uv[:, 1].min())) - margin_px,
            math.ceil(float(uv[:, 0].max())) + margin_px,
            math.ceil(float(uv[:, 1].max())) + margin_px,
        )
        found[side] = order_along(detect_beads(img, roi, len(s)), uv[1], uv[0])
    stereo = collinear_pose_stereo(cal, found["left"], found["right"], s)
    mono = collinear_pose_from_view(cal, "left", found["left"], s)
    agree = axis_agreement(stereo, mono)
    if agree.angle_deg > max_mono_stereo_deg:
        raise VisionError(
            f"beads: monocular and stereo axes differ by {agree.angle_deg:.1f} deg "
            f"(limit {max_mono_stereo_deg} deg)"
        )
    towards_target = Line3D(stereo.origin_mm, -stereo.direction)
    pe = axis_path_error(towards_target, entry_mm, target_mm, oriented=True)
    return BeadAxisMeasurement(stereo, mono, agree, pe, found["left"], found["right"])
