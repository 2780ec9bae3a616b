from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from hil.cli import main
from hil.errors import CalibrationError, InputFileError
from hil.vision.calibrate import (
    CalibrationSettings,
    calibrate_from_corners,
    calibrate_from_files,
    find_chessboard,
)
from hil.vision.camera_model import StereoCalibration, load_calibration
from hil.vision.render import RenderOptions, random_board_poses, render_chessboard_pair

COLS, ROWS, SQUARE = 6, 7, 24.0


@pytest.fixture(scope="module")
def rig() -> StereoCalibration:
    """A half-resolution seed-001-like rig with a slight vergence and distortion (fast to render)."""
    K1 = np.array([[700.0, 0.0, 485.0], [0.0, 701.0, 262.0], [0.0, 0.0, 1.0]])
    K2 = np.array([[698.0, 0.0, 478.0], [0.0, 699.5, 274.0], [0.0, 0.0, 1.0]])
    R = cv2.Rodrigues(np.array([0.004, 0.012, 0.002]))[0]
    return StereoCalibration(
        (960, 540),
        K1,
        np.array([-0.08, 0.05, 0.0005, -0.0003, 0.0]),
        K2,
        np.array([-0.07, 0.04, -0.0002, 0.0004, 0.0]),
        R,
        np.array([-119.99, -0.02, -0.47]),
    )


@pytest.fixture(scope="module")
def views(rig: StereoCalibration, tmp_path_factory: pytest.TempPathFactory) -> Path:
    rng = np.random.default_rng(1)
    d = tmp_path_factory.mktemp("boards")
    for i, T in enumerate(
        random_board_poses(rig, 14, rng, COLS, ROWS, SQUARE, distance_mm=(350.0, 600.0), margin_px=20.0)
    ):
        left, right = render_chessboard_pair(rig, T, COLS, ROWS, SQUARE, RenderOptions(noise_sigma=1.5), rng)
        cv2.imwrite(str(d / f"left_{i:02d}.png"), left)
        cv2.imwrite(str(d / f"right_{i:02d}.png"), right)
    return d


@pytest.fixture(scope="module")
def corners(views: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    cl, cr = [], []
    for a, b in zip(sorted(views.glob("left_*.png")), sorted(views.glob("right_*.png")), strict=True):
        ca = find_chessboard(cv2.imread(str(a), cv2.IMREAD_GRAYSCALE), COLS, ROWS)
        cb = find_chessboard(cv2.imread(str(b), cv2.IMREAD_GRAYSCALE), COLS, ROWS)
        assert ca is not None
        assert cb is not None
        cl.append(ca)
        cr.append(cb)
    return cl, cr


def test_recovers_intrinsics_and_baseline(
    rig: StereoCalibration, corners: tuple[list[np.ndarray], list[np.ndarray]]
) -> None:
    res = calibrate_from_corners(*corners, rig.image_size)
    cal = res.calibration
    assert res.pairs_used == 14
    assert res.rejected == ()
    np.testing.assert_allclose(cal.K_left, rig.K_left, rtol=0, atol=2.0)
    np.testing.assert_allclose(cal.K_right, rig.K_right, rtol=0, atol=2.0)
    assert cal.baseline_mm == pytest.approx(rig.baseline_mm, abs=0.3)
    np.testing.assert_allclose(cal.t_right_from_left_mm, rig.t_right_from_left_mm, atol=0.5)
    angle = np.linalg.norm(cv2.Rodrigues(cal.R_right_from_left @ rig.R_right_from_left.T)[0])
    assert angle < 1e-3
    assert res.rms_left < 0.1
    assert res.rms_right < 0.1
    assert res.rms_stereo < 0.1
    # distortion: compare the effect (~3 px there), not the coefficients (they trade off with K)
    x = np.array([[150.0, 100.0, 700.0], [-200.0, -120.0, 600.0]])
    np.testing.assert_allclose(cal.project(x)[0], rig.project(x)[0], atol=1.0)
    assert len(cal.quality["per_view"]) == 14


def test_outlier_view_is_flagged_and_excluded_on_request(
    rig: StereoCalibration, corners: tuple[list[np.ndarray], list[np.ndarray]]
) -> None:
    cl, cr = [c.copy() for c in corners[0]], [c.copy() for c in corners[1]]
    cl[3] = cl[3] + np.random.default_rng(0).normal(0.0, 2.0, cl[3].shape)
    names = [f"view{i}" for i in range(len(cl))]
    flagged = calibrate_from_corners(cl, cr, rig.image_size, names=names)
    assert flagged.rejected == ()
    assert flagged.pairs_used == 14
    assert [v["view"] for v in flagged.per_view if v["outlier"]] == ["view3"]
    assert all(v["used"] for v in flagged.per_view)
    assert flagged.calibration.quality["outlier_views"] == ["view3"]
    excl = CalibrationSettings(exclude_outliers=True)
    res = calibrate_from_corners(cl, cr, rig.image_size, excl, names=names)
    assert [v for v, _ in res.rejected] == ["view3"]
    assert "far above the median" in res.rejected[0][1]
    assert res.pairs_used == 13
    assert [v["view"] for v in res.per_view if not v["used"]] == ["view3"]
    assert res.per_view[3]["rms_stereo_px"] is None
    assert res.summary()["views_left_out"] == [{"view": "view3", "reason": res.rejected[0][1]}]
    assert res.calibration.baseline_mm == pytest.approx(rig.baseline_mm, abs=0.3)


def test_accepts_opencv_corner_shape(
    rig: StereoCalibration, corners: tuple[list[np.ndarray], list[np.ndarray]]
) -> None:
    cl = [c.reshape(-1, 1, 2) for c in corners[0]]
    res = calibrate_from_corners(cl, corners[1], rig.image_size)
    assert res.pairs_used == 14


def test_bad_corner_input(rig: StereoCalibration, corners: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    with pytest.raises(CalibrationError, match="only 2 pair"):
        calibrate_from_corners(corners[0][:2], corners[1][:2], rig.image_size)
    with pytest.raises(CalibrationError, match="left views but"):
        calibrate_from_corners(corners[0][:6], corners[1][:5], rig.image_size)
    with pytest.raises(CalibrationError, match=r"shape \(42, 2\)"):
        calibrate_from_corners([c[:-1] for c in corners[0]], corners[1], rig.image_size)


def test_settings_validation() -> None:
    with pytest.raises(CalibrationError, match="square size"):
        CalibrationSettings(square_mm=-1.0)


def test_cli_calibrate(
    views: Path, tmp_path: Path, rig: StereoCalibration, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "cal.json"
    code = main(
        [
            "calibrate",
            "--left",
            str(views / "left_*.png"),
            "--right",
            str(views / "right_*.png"),
            "--board",
            "6x7",
            "--square",
            "24",
            "--out",
            str(out),
        ]
    )
    captured = capsys.readouterr()
    assert code == 0
    summary = json.loads(captured.out)
    assert summary["pairs_found"] == 14
    assert summary["pairs_used"] == 14
    assert summary["baseline"] == pytest.approx(rig.baseline_mm, abs=0.3)
    assert set(summary) >= {"rms_left", "rms_right", "rms_stereo", "T", "rejected_views"}
    assert "calibrate:" in captured.err
    assert load_calibration(out).image_size == (960, 540)


def test_cli_calibrate_errors(views: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["calibrate", "--out", str(tmp_path / "c.json")]
    assert main([*args, "--left", str(tmp_path / "none_*.png"), "--right", str(views / "right_*.png")]) == 2
    assert "no left images match" in capsys.readouterr().err
    assert main([*args, "--left", str(views / "left_0*.png"), "--right", str(views / "right_*.png")]) == 2
    err = capsys.readouterr().err
    assert "right_10.png: 10 left images but 14 right images" in err
    assert len(err.strip().splitlines()) == 1
    assert (
        main(
            [
                *args,
                "--left",
                str(views / "left_*.png"),
                "--right",
                str(views / "right_*.png"),
                "--board",
                "8x9",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "left_02.png: the 8x9 board was not found in any image of the first 3 pair(s)" in err
    assert "check --board" in err
    with pytest.raises(SystemExit):
        main([*args, "--left", "a", "--right", "b", "--board", "six"])


def test_calibrate_image_size_mismatch(views: Path, tmp_path: Path) -> None:
    for i, p in enumerate(sorted(views.glob("left_*.png"))[:3]):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(tmp_path / f"l{i}.png"), img)
        cv2.imwrite(str(tmp_path / f"r{i}.png"), img if i != 1 else img[:-2])
    with pytest.raises(CalibrationError, match=r"r1\.png: image is 960x538 but .*l1\.png is 960x540"):
        calibrate_from_files(str(tmp_path / "l*.png"), str(tmp_path / "r*.png"))


def test_unreadable_image(tmp_path: Path) -> None:
    (tmp_path / "l0.png").write_bytes(b"not a png")
    (tmp_path / "r0.png").write_bytes(b"")
    with pytest.raises(InputFileError, match="not an image"):
        calibrate_from_files(str(tmp_path / "l*.png"), str(tmp_path / "r*.png"))
