"""The instrument renderer and the needle contour detector, closed loop with seed 004 §II-A / §III."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from hil.errors import VisionError
from hil.geometry.collinear import (
    Line3D,
    axis_path_error,
    collinear_pose_from_view,
    collinear_pose_stereo,
    direction_error_deg,
)
from hil.geometry.cylinder import cylinder_axis_from_contours, cylinder_axis_two_views
from hil.geometry.transform import RigidTransform
from hil.vision.camera_model import StereoCalibration
from hil.vision.lines import NeedleContours, detect_needle_contours, fit_line_tls, measure_needle_axis
from hil.vision.render import RenderOptions, markers_on_patch, render_stereo
from hil.vision.render_instrument import (
    Instrument3D,
    InstrumentTruth,
    RenderedInstrument,
    draw_instrument,
    render_instrument_stereo,
)

CAL = StereoCalibration.synthetic()
RADIUS = 0.6
POSITIONS = (40.0, 70.0, 100.0)


@pytest.fixture(scope="module")
def rendered() -> tuple[Instrument3D, RenderedInstrument]:
    inst = Instrument3D.needle_with_beads(
        [30.0, 20.0, 450.0], [0.3, -0.5, 0.4], 120.0, radius_mm=RADIUS, marker_positions_mm=POSITIONS
    )
    return inst, render_instrument_stereo(CAL, inst, RenderOptions(), np.random.default_rng(0))


def _roi(tr: InstrumentTruth) -> tuple[int, int, int, int]:
    e = np.vstack([tr.tip_px, tr.hub_px])
    return int(e[:, 0].min()) - 40, int(e[:, 1].min()) - 40, int(e[:, 0].max()) + 40, int(e[:, 1].max()) + 40


def _detect(r: RenderedInstrument) -> dict[str, NeedleContours]:
    out = {}
    for side, img, tr in (("left", r.left, r.truth_left), ("right", r.right, r.truth_right)):
        K, dist, _, _ = CAL.camera(side)
        out[side] = detect_needle_contours(img, K, dist, roi=_roi(tr))
    return out


def _beads(img: np.ndarray, roi: tuple[int, int, int, int], n: int) -> np.ndarray:
    """Centroids of the n largest saturated blobs (lit beads), ordered from the tip."""
    x0, y0, x1, y1 = roi
    sub = img[y0:y1, x0:x1].astype(np.float64)
    mask = (sub > 230).astype(np.uint8)
    _k, labels, stats, _ = cv2.connectedComponentsWithStats(mask)
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA])[:n] + 1
    cents = []
    for lab in order:
        ys, xs = np.nonzero(labels == lab)
        wts = sub[ys, xs] - 200.0
        cents.append([x0 + float(xs @ wts) / wts.sum(), y0 + float(ys @ wts) / wts.sum()])
    return np.array(cents)


def _order_from(points: np.ndarray, start: np.ndarray) -> np.ndarray:
    return points[np.argsort(np.linalg.norm(points - start, axis=1))]


def test_rendered_contours_sit_at_half_coverage() -> None:
    """Independent renderer check: on the analytic contour lines the grey level is midway between
    the background and the needle (noise-free, no vignetting)."""
    opts = RenderOptions(noise_sigma=0.0, vignetting=0.0, lighting_gradient=0.0, blur_sigma_px=0.7)
    inst = Instrument3D([20.0, -10.0, 400.0], [60.0, 50.0, 480.0], radius_mm=1.0, level=60.0)
    r = render_instrument_stereo(CAL, inst, opts, np.random.default_rng(1))
    tr = r.truth_left
    assert tr.drawn
    img = r.left.astype(np.float32)
    for line in tr.contour_lines_px:
        for f in np.linspace(0.2, 0.8, 7):
            p = tr.tip_px + f * (tr.hub_px - tr.tip_px)
            foot = p - (p @ line[:2] + line[2]) * line[:2]
            v = cv2.getRectSubPix(img, (1, 1), (float(foot[0]), float(foot[1])))[0, 0]
            assert abs(float(v) - 130.0) < 8.0  # (200 + 60) / 2, +- rounding and bilinear sampling


def test_contour_detection_matches_truth(rendered: tuple[Instrument3D, RenderedInstrument]) -> None:
    _, r = rendered
    det = _detect(r)
    for side, tr in (("left", r.truth_left), ("right", r.truth_right)):
        d = det[side]
        assert min(d.n_points) > 100
        assert max(d.rms_px) < 0.2
        for line in d.lines_px:
            for p in (tr.tip_px, tr.hub_px):
                foot = p - (p @ line[:2] + line[2]) * line[:2]
                dev = min(abs(float(foot @ m[:2] + m[2])) for m in tr.contour_lines_px)
                assert dev < 0.25, (side, dev)
        assert abs(float(d.axis_hint_px @ tr.axis_line_px[:2] + tr.axis_line_px[2])) < 0.5


def test_needle_axis_from_rendered_images(rendered: tuple[Instrument3D, RenderedInstrument]) -> None:
    """Two views: the axis within 0.1 deg and 0.2 mm; the radius implied within 10 %. One view:
    the depth (distance to the axis) within 10 %, the direction only loosely (seed 004 §III's method
    is ill-conditioned for a needle this thin — see docs/pose004.md)."""
    inst, r = rendered
    det = _detect(r)
    tv = cylinder_axis_two_views(CAL, det["left"].lines_px, det["right"].lines_px, RADIUS)
    assert direction_error_deg(tv.axis.direction, inst.axis.direction, oriented=False) < 0.1
    assert float(inst.axis.distance_to(tv.axis.point_mm)[0]) < 0.2
    assert abs(tv.radius_left_mm / RADIUS - 1.0) < 0.1
    assert abs(tv.radius_right_mm / RADIUS - 1.0) < 0.1
    K = CAL.K_left
    mono = cylinder_axis_from_contours(
        *det["left"].lines_px, K, RADIUS, axis_image_point_px=det["left"].axis_hint_px
    )
    true_d = float(np.linalg.norm(inst.axis.moment_mm))
    assert abs(mono.distance_mm / true_d - 1.0) < 0.10
    assert direction_error_deg(mono.direction, inst.axis.direction, oriented=False) < 30.0
    # against the plan: the planned path is the true axis (entry at the tip, target 80 mm beyond)
    entry = inst.tip_mm
    target = inst.tip_mm - 80.0 * inst.axis.direction
    pe = axis_path_error(tv.axis, entry, target, oriented=False)
    assert pe.direction_error_deg < 0.1
    assert pe.entry_offset_mm < 0.2


def test_beads_give_collinear_pose(rendered: tuple[Instrument3D, RenderedInstrument]) -> None:
    inst, r = rendered
    uv = {}
    for side, img, tr in (("left", r.left, r.truth_left), ("right", r.right, r.truth_right)):
        got = _order_from(_beads(img, _roi(tr), 3), tr.tip_px)
        assert np.max(np.linalg.norm(got - tr.marker_px, axis=1)) < 0.3
        uv[side] = got
    s = np.array(POSITIONS)
    st = collinear_pose_stereo(CAL, uv["left"], uv["right"], s)
    assert direction_error_deg(st.direction, inst.axis.direction) < 0.5
    assert float(np.linalg.norm(st.point_at(0.0) - inst.tip_mm)) < 1.0
    mono = collinear_pose_from_view(CAL, "left", uv["left"], s)
    assert direction_error_deg(mono.direction, inst.axis.direction) < 10.0
    assert float(Line3D(inst.tip_mm, inst.axis.direction).distance_to(mono.markers_mm).max()) < 15.0


def test_composes_onto_ring_marker_frame() -> None:
    markers = markers_on_patch(np.array([[-60.0, 40.0, 500.0], [80.0, -50.0, 520.0]]))
    base = render_stereo(CAL, markers, RenderOptions(), np.random.default_rng(3))
    inst = Instrument3D([0.0, 0.0, 450.0], [20.0, 30.0, 420.0])
    r = render_instrument_stereo(CAL, inst, RenderOptions(), np.random.default_rng(4), base=base)
    assert r.truth_left.drawn
    assert r.truth_right.drawn
    changed = np.argwhere(r.left != base.left)
    assert len(changed) > 50
    # only pixels near the needle changed; the ring markers are untouched
    for t in base.truth:
        u, v = (round(x) for x in t.center_left_px)
        assert np.array_equal(r.left[v - 8 : v + 9, u - 8 : u + 9], base.left[v - 8 : v + 9, u - 8 : u + 9])


def test_behind_camera_draws_nothing() -> None:
    img = np.full((1080, 1920), 200, np.uint8)
    inst = Instrument3D([0.0, 0.0, -100.0], [0.0, 10.0, -200.0])
    K, dist, R, t = CAL.camera("left")
    assert draw_instrument(img, K, dist, R, t, inst, RenderOptions(), np.random.default_rng(0)) is False
    assert np.all(img == 200)


def test_detector_errors_and_tls() -> None:
    K, dist, _, _ = CAL.camera("left")
    with pytest.raises(VisionError):
        detect_needle_contours(np.full((100, 100), 200, np.uint8), K, dist)
    with pytest.raises(VisionError):
        detect_needle_contours(np.zeros((10, 10, 3), np.uint8), K, dist)
    line = fit_line_tls([[0.0, 1.0], [2.0, 3.0], [4.0, 5.0]])
    assert math.isclose(abs(line[0]), math.sqrt(0.5))
    assert abs(float(np.array([1.0, 2.0, 1.0]) @ line)) < 1e-12
    with pytest.raises(VisionError):
        fit_line_tls([[1.0, 1.0]])


def test_distorted_camera_lines_are_undistorted() -> None:
    cal = StereoCalibration.synthetic(dist=[-0.12, 0.05, 0.0, 0.0, 0.0])
    inst = Instrument3D([-120.0, -60.0, 430.0], [-10.0, 40.0, 470.0], radius_mm=0.8)
    r = render_instrument_stereo(cal, inst, RenderOptions(), np.random.default_rng(5))
    K, dist, _, _ = cal.camera("left")
    d = detect_needle_contours(r.left, K, dist, roi=_roi(r.truth_left))
    tr = r.truth_left
    ideal = cal.undistort_points("left", np.vstack([tr.tip_px, tr.hub_px]))
    for line in d.lines_px:
        for p in ideal:
            foot = p - (p @ line[:2] + line[2]) * line[:2]
            assert min(abs(float(foot @ m[:2] + m[2])) for m in tr.contour_lines_px) < 0.3


def test_measure_needle_axis_against_a_tilted_plan(rendered: tuple[Instrument3D, RenderedInstrument]) -> None:
    """The in-loop check: the expected segment is off by 3 mm, the plan is tilted 1.5 deg about the
    tip; the measured direction error is the tilt, the entry offset ~0."""
    inst, r = rendered
    d = inst.axis.direction
    tilt = RigidTransform.from_rotvec(
        np.cross(d, [0.0, 0.0, 1.0]) / np.linalg.norm(np.cross(d, [0, 0, 1])) * math.radians(1.5)
    )
    target = inst.tip_mm - 80.0 * (tilt.R @ d)
    shift = np.array([3.0, 0.0, 0.0])
    m = measure_needle_axis(
        CAL, r.left, r.right, inst.tip_mm + shift, inst.hub_mm + shift, inst.tip_mm, target, radius_mm=RADIUS
    )
    assert abs(m.path_error.direction_error_deg - 1.5) < 0.1
    assert m.path_error.entry_offset_mm < 0.2
    assert m.path_error.within(2.0, 3.0)
    assert not m.path_error.within(1.0, 3.0)
    far = np.array([400.0, 300.0, 0.0])
    with pytest.raises(VisionError):
        measure_needle_axis(CAL, r.left, r.right, inst.tip_mm + far, inst.hub_mm + far, inst.tip_mm, target)
