from __future__ import annotations

import numpy as np
import pytest

from hil.errors import VisionError
from hil.vision.camera_model import StereoCalibration
from hil.vision.detect import detect_rings
from hil.vision.pipeline import locate_markers
from hil.vision.render import (
    RenderedPair,
    RenderOptions,
    RingMarker3D,
    markers_on_patch,
    random_marker_layout,
    render_stereo,
)
from hil.vision.stereo import StereoParams, match_and_triangulate


def _errors(points: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.array([np.min(np.linalg.norm(truth - p, axis=1)) for p in points])


def test_triangulates_every_marker(
    cal: StereoCalibration, scene: tuple[list[RingMarker3D], RenderedPair]
) -> None:
    markers, pair = scene
    res = match_and_triangulate(cal, detect_rings(pair.left), detect_rings(pair.right))
    truth = np.array([m.center_mm for m in markers])
    assert len(res.points) == len(markers)
    assert res.rejected == ()
    err = _errors(res.points_mm, truth)
    assert float(np.sqrt(np.mean(err**2))) < 0.2
    for p in res.points:
        assert p.epipolar_error_px < 0.2
        assert p.gap_mm < 0.05
        assert p.normal is not None
    # every point pairs the detections of the same marker
    dl, dr = detect_rings(pair.left), detect_rings(pair.right)
    for p in res.points:
        j = int(np.argmin(np.linalg.norm(truth - p.point_mm, axis=1)))
        assert np.linalg.norm(dl[p.left_index].center_px - pair.truth[j].center_left_px) < 0.2
        assert np.linalg.norm(dr[p.right_index].center_px - pair.truth[j].center_right_px) < 0.2


def test_marker_seen_by_one_camera_only(cal: StereoCalibration) -> None:
    rng = np.random.default_rng(3)
    markers = random_marker_layout(rng, 5)
    only_left = RingMarker3D(np.array([-560.0, 0.0, 900.0]), np.array([0.5, 0.0, -0.87]), marker_id=5)
    pair = render_stereo(cal, [*markers, only_left], RenderOptions(), rng)
    assert pair.truth[5].visible_left
    assert not pair.truth[5].visible_right
    res = locate_markers(cal, pair.left, pair.right)
    uv = pair.truth[5].center_left_px
    k = [i for i, d in enumerate(res.detections_left) if np.linalg.norm(d.center_px - uv) < 0.3]
    assert len(k) == 1
    assert k[0] in res.stereo.unmatched_left
    assert all(p.left_index != k[0] for p in res.stereo.points)
    assert len(res.stereo.points) >= 3
    err = _errors(res.points_mm, np.array([m.center_mm for m in markers]))
    assert np.all(err < 0.3)


def test_same_row_markers_are_paired_globally(cal: StereoCalibration) -> None:
    """Three markers on one epipolar line at different depths: rows alone cannot pair them; the
    size/depth term and the global assignment must."""
    centres = np.array([[-60.0, 0.0, 700.0], [0.0, 0.0, 1000.0], [70.0, 0.0, 1300.0]])
    markers = markers_on_patch(centres)
    pair = render_stereo(cal, markers, RenderOptions(), np.random.default_rng(4))
    res = locate_markers(cal, pair.left, pair.right)
    assert len(res.stereo.points) == 3
    assert np.all(_errors(res.points_mm, centres) < 0.5)


def test_wrong_calibration_is_caught_by_the_ray_gap(
    cal: StereoCalibration, scene: tuple[list[RingMarker3D], RenderedPair]
) -> None:
    _, pair = scene
    R = cal.R_right_from_left
    tilt = np.array(
        [[1.0, 0.0, 0.0], [0.0, np.cos(0.004), -np.sin(0.004)], [0.0, np.sin(0.004), np.cos(0.004)]]
    )
    bad = StereoCalibration(
        cal.image_size,
        cal.K_left,
        cal.dist_left,
        cal.K_right,
        cal.dist_right,
        tilt @ R,
        cal.t_right_from_left_mm,
    )
    res = match_and_triangulate(
        bad,
        detect_rings(pair.left),
        detect_rings(pair.right),
        StereoParams(epipolar_tol_px=10.0, max_gap_mm=0.5),
    )
    assert len(res.rejected) >= 6
    assert all("rays pass" in r.reason and r.gap_mm > 0.5 for r in res.rejected)


def test_perspective_correction_removes_the_bias_at_close_range(cal: StereoCalibration) -> None:
    rng = np.random.default_rng(8)
    errs: dict[str, list[float]] = {"normal": [], "none": [], "concentric": []}
    for _ in range(4):
        markers = random_marker_layout(
            rng, 6, distance_mm=420.0, spread_mm=60.0, max_tilt_deg=60.0, min_separation_mm=14.0
        )
        pair = render_stereo(cal, markers, RenderOptions(noise_sigma=0.5), rng)
        dl, dr = detect_rings(pair.left), detect_rings(pair.right)
        truth = np.array([m.center_mm for m in markers])
        for corr in errs:
            res = match_and_triangulate(cal, dl, dr, StereoParams(correction=corr))  # type: ignore[arg-type]
            errs[corr].extend(_errors(res.points_mm, truth))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errs.items()}
    assert rms["normal"] < 0.85 * rms["none"]


def test_locate_identifies_a_marker_set(
    cal: StereoCalibration, scene: tuple[list[RingMarker3D], RenderedPair]
) -> None:
    markers, pair = scene
    rng = np.random.default_rng(5)
    order = rng.permutation(len(markers))
    model = np.array([markers[i].center_mm for i in order]) + np.array([3.0, -2.0, 1.0])
    res = locate_markers(cal, pair.left, pair.right, model_mm=model)
    assert res.match is not None
    assert res.match_error is None
    assert len(res.match.model_to_measured) == len(markers)
    for k, j in res.match.model_to_measured.items():
        np.testing.assert_allclose(res.points_mm[j], markers[order[k]].center_mm, atol=0.3)
    doc = res.to_dict()
    assert set(doc["identification"]) >= {"model_to_point", "fre_rms_mm", "T_optical_from_model"}  # type: ignore[arg-type]


def test_locate_reports_when_identification_is_impossible(cal: StereoCalibration) -> None:
    rng = np.random.default_rng(6)
    markers = random_marker_layout(rng, 2)
    pair = render_stereo(cal, markers, RenderOptions(), rng)
    res = locate_markers(cal, pair.left, pair.right, model_mm=np.eye(3) * 50.0)
    assert res.match is None
    assert res.match_error is not None
    assert "fewer" in res.match_error


def test_locate_rejects_wrong_image_size(cal: StereoCalibration) -> None:
    img = np.zeros((540, 960), np.uint8)
    with pytest.raises(VisionError, match="left image: image is 960x540"):
        locate_markers(cal, img, img)
