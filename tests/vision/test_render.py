from __future__ import annotations

import numpy as np
import pytest

from hil.errors import VisionError
from hil.vision.camera_model import StereoCalibration
from hil.vision.render import (
    RenderOptions,
    RingMarker3D,
    chessboard_corners_mm,
    markers_on_patch,
    random_marker_layout,
    render_stereo,
)


def test_truth_is_the_projection_of_the_centres(cal: StereoCalibration) -> None:
    rng = np.random.default_rng(1)
    markers = random_marker_layout(rng, 6)
    pair = render_stereo(cal, markers, RenderOptions(), rng)
    uv_l, uv_r = cal.project(np.array([m.center_mm for m in markers]))
    assert [t.marker_id for t in pair.truth] == [m.marker_id for m in markers]
    np.testing.assert_allclose([t.center_left_px for t in pair.truth], uv_l)
    np.testing.assert_allclose([t.center_right_px for t in pair.truth], uv_r)
    assert pair.left.shape == (1080, 1920)
    assert pair.left.dtype == np.uint8


def test_marker_is_drawn_where_the_truth_says(cal: StereoCalibration) -> None:
    rng = np.random.default_rng(2)
    m = RingMarker3D(np.array([0.0, 0.0, 900.0]), np.array([0.0, 0.0, -1.0]), marker_id=5)
    pair = render_stereo(cal, [m], RenderOptions(noise_sigma=0.0), rng)
    u, v = np.round(pair.truth[0].center_left_px).astype(int)
    ring_radius_px = 1394.0 * 2.5 / 900.0  # mid-ring radius
    assert pair.left[v, u] > 150  # light hole
    assert pair.left[v, int(u + ring_radius_px)] < 90  # dark ring
    assert pair.left[v, int(u + 3 * ring_radius_px)] > 150  # light skin


def test_light_on_dark_has_a_dark_backing(cal: StereoCalibration) -> None:
    rng = np.random.default_rng(2)
    m = RingMarker3D(np.array([0.0, 0.0, 900.0]), np.array([0.0, 0.0, -1.0]), dark_on_light=False)
    pair = render_stereo(cal, [m], RenderOptions(noise_sigma=0.0), rng)
    u, v = np.round(pair.truth[0].center_left_px).astype(int)
    r = 1394.0 * 2.5 / 900.0
    assert pair.left[v, u] < 90
    assert pair.left[v, int(u + r)] > 150
    assert pair.left[v, int(u + 1.8 * r)] < 90


def test_same_rng_same_images(cal: StereoCalibration) -> None:
    markers = random_marker_layout(np.random.default_rng(3), 4)
    a = render_stereo(cal, markers, RenderOptions(glare_spots=2), np.random.default_rng(9))
    b = render_stereo(cal, markers, RenderOptions(glare_spots=2), np.random.default_rng(9))
    np.testing.assert_array_equal(a.left, b.left)
    np.testing.assert_array_equal(a.right, b.right)


def test_visibility_flags(cal: StereoCalibration) -> None:
    rng = np.random.default_rng(4)
    facing_away = RingMarker3D(np.array([0.0, 0.0, 900.0]), np.array([0.0, 0.0, 1.0]), marker_id=0)
    outside_right = RingMarker3D(np.array([-560.0, 0.0, 900.0]), np.array([0.0, 0.0, -1.0]), marker_id=1)
    pair = render_stereo(cal, [facing_away, outside_right], RenderOptions(), rng)
    assert not pair.truth[0].visible_left
    assert not pair.truth[0].visible_right
    assert pair.truth[1].visible_left
    assert not pair.truth[1].visible_right


def test_occluders_flag_the_marker(cal: StereoCalibration) -> None:
    rng = np.random.default_rng(5)
    markers = random_marker_layout(rng, 3)
    pair = render_stereo(cal, markers, RenderOptions(occluders=1), rng)
    assert sum(t.occluded_left for t in pair.truth) == 1
    assert sum(t.occluded_right for t in pair.truth) == 1


def test_ellipse_centre_truth_differs_from_projected_centre_under_tilt(cal: StereoCalibration) -> None:
    c = np.array([150.0, 100.0, 400.0])
    m = markers_on_patch([c], [[0.6, 0.0, -0.8]])[0]
    t = render_stereo(cal, [m], RenderOptions(), np.random.default_rng(0)).truth[0]
    assert np.linalg.norm(t.ellipse_center_left_px - t.center_left_px) > 0.02


def test_bad_marker_rejected() -> None:
    with pytest.raises(VisionError, match="inner diameter"):
        RingMarker3D(
            np.zeros(3) + 1, np.array([0.0, 0.0, -1.0]), outer_diameter_mm=3.0, inner_diameter_mm=7.0
        )
    with pytest.raises(VisionError, match="normal"):
        RingMarker3D(np.array([0.0, 0.0, 1.0]), np.zeros(3))


def test_chessboard_corner_order() -> None:
    c = chessboard_corners_mm(3, 2, 10.0)
    np.testing.assert_array_equal(c[:4], [[0, 0, 0], [10, 0, 0], [20, 0, 0], [0, 10, 0]])
