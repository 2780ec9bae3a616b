from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.errors import CalibrationError, InputFileError
from hil.vision.camera_model import (
    StereoCalibration,
    distort_normalized,
    load_calibration,
    save_calibration,
    undistort_normalized,
)


def test_synthetic_rig_geometry() -> None:
    cal = StereoCalibration.synthetic()
    assert cal.image_size == (1920, 1080)
    assert cal.baseline_mm == pytest.approx(120.0)
    np.testing.assert_allclose(cal.right_center_mm, [120.0, 0.0, 0.0])
    uv_l, uv_r = cal.project(np.array([[0.0, 0.0, 1000.0]]))
    np.testing.assert_allclose(uv_l[0], [959.5, 539.5])
    # disparity = f B / Z
    assert uv_l[0, 0] - uv_r[0, 0] == pytest.approx(1394.0 * 120.0 / 1000.0)
    np.testing.assert_allclose(cal.T_right_from_left.apply(np.array([[120.0, 0.0, 5.0]]))[0], [0.0, 0.0, 5.0])


def test_projection_matrices_match_project_without_distortion() -> None:
    cal = StereoCalibration.synthetic(f_px=1000.0, baseline_mm=100.0)
    X = np.array([[10.0, -20.0, 800.0], [-50.0, 30.0, 1200.0]])
    uv_l, uv_r = cal.project(X)
    for P, uv in ((cal.P_left(), uv_l), (cal.P_right(), uv_r)):
        h = np.column_stack([X, np.ones(2)]) @ P.T
        np.testing.assert_allclose(h[:, :2] / h[:, 2:], uv, atol=1e-9)


def test_point_behind_camera_is_nan() -> None:
    uv_l, _ = StereoCalibration.synthetic().project(np.array([[0.0, 0.0, -10.0]]))
    assert np.all(np.isnan(uv_l))


def test_rectification_puts_correspondences_on_one_row() -> None:
    cal = StereoCalibration.synthetic(dist=(-0.05, 0.02, 0, 0, 0))
    X = np.array([[30.0, 40.0, 900.0], [-80.0, -60.0, 1100.0]])
    uv_l, uv_r = cal.project(X)
    r = cal.rectification
    a = cv2.undistortPoints(uv_l.reshape(-1, 1, 2), cal.K_left, cal.dist_left, R=r.R1, P=r.P1).reshape(-1, 2)
    b = cv2.undistortPoints(uv_r.reshape(-1, 1, 2), cal.K_right, cal.dist_right, R=r.R2, P=r.P2).reshape(
        -1, 2
    )
    np.testing.assert_allclose(a[:, 1], b[:, 1], atol=1e-3)


@given(
    x=st.floats(-0.6, 0.6),
    y=st.floats(-0.4, 0.4),
    k1=st.floats(-0.2, 0.2),
    k2=st.floats(-0.1, 0.1),
    p1=st.floats(-0.002, 0.002),
    p2=st.floats(-0.002, 0.002),
)
def test_undistort_inverts_distort(x: float, y: float, k1: float, k2: float, p1: float, p2: float) -> None:
    dist = np.array([k1, k2, p1, p2, 0.0])
    xy = np.array([[x, y]])
    back = undistort_normalized(distort_normalized(xy, dist), dist, iterations=60)
    np.testing.assert_allclose(back, xy, atol=1e-9)


def test_save_load_round_trip(tmp_path: Path) -> None:
    cal = StereoCalibration.synthetic(dist=(-0.05, 0.02, 0.001, 0.0, 0.003))
    path = tmp_path / "cal.json"
    save_calibration(cal, path)
    doc = json.loads(path.read_text())
    assert doc["schema"] == "hil.stereo_calibration"
    assert doc["version"] == 1
    assert set(doc["rectification"]) == {"R1", "R2", "P1", "P2", "Q"}
    back = load_calibration(path)
    assert back.image_size == cal.image_size
    for name in ("K_left", "dist_left", "K_right", "dist_right", "R_right_from_left", "t_right_from_left_mm"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cal, name))


def test_shipped_sim_calibration_loads() -> None:
    cal = load_calibration(Path(__file__).parents[2] / "configs" / "calibration" / "sim_stereo.json")
    assert cal.image_size == (1920, 1080)
    assert cal.baseline_mm == pytest.approx(120.0)


def _doc(tmp_path: Path) -> tuple[Path, dict[str, object]]:
    path = tmp_path / "c.json"
    save_calibration(StereoCalibration.synthetic(), path)
    return path, json.loads(path.read_text())


def test_load_missing_file_names_it(tmp_path: Path) -> None:
    with pytest.raises(InputFileError, match="not found") as info:
        load_calibration(tmp_path / "nope.json")
    assert info.value.path.endswith("nope.json")


def test_load_not_json(tmp_path: Path) -> None:
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(InputFileError, match="not valid JSON"):
        load_calibration(p)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.update(version=2), "field 'version' is 2"),
        (lambda d: d.update(schema="other"), "field 'schema'"),
        (lambda d: d["left"].pop("K"), "missing field 'left.K'"),
        (lambda d: d["right"].update(dist=[0, 0, 0]), r"field 'right.dist' must have shape \[5\]"),
        (lambda d: d.update(R_right_from_left=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "not a proper rotation"),
        (lambda d: d["image_size"].update(width=-3), "image_size"),
        (lambda d: d.update(t_right_from_left_mm=["a", 0, 0]), "not a numeric array"),
    ],
)
def test_load_schema_errors_name_file_and_field(tmp_path: Path, mutate: object, message: str) -> None:
    path, doc = _doc(tmp_path)
    mutate(doc)  # type: ignore[operator]
    path.write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match=message) as info:
        load_calibration(path)
    assert str(path) in str(info.value)


def test_constructor_rejects_bad_intrinsics() -> None:
    with pytest.raises(CalibrationError, match="K_left"):
        StereoCalibration(
            (10, 10), np.zeros((3, 3)), np.zeros(5), np.eye(3), np.zeros(5), np.eye(3), np.array([-1.0, 0, 0])
        )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[" * 100_000, "nested too deeply"),
        ("1" * 5000, "not usable JSON"),
    ],
    ids=["deep", "huge_int"],
)
def test_hostile_json_is_a_typed_error(tmp_path: Path, text: str, message: str) -> None:
    """Regressions found by the fuzz suite (tests/fuzz/test_known_bugs.py)."""
    p = tmp_path / "hostile.json"
    p.write_text(text)
    with pytest.raises(InputFileError, match=message):
        load_calibration(p)


def test_number_too_large_for_float_is_a_typed_error(tmp_path: Path) -> None:
    path, doc = _doc(tmp_path)
    doc["left"]["K"][0][0] = 10**400  # type: ignore[index]
    path.write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match=r"left\.K"):
        load_calibration(path)
