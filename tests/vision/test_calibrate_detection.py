"""Board detection on hard images (issue 17): a 640x512 stereo set of 9x6 boards in which some
views have uneven lighting, blur and noise so that the classic detector with its quick pre-check
misses the board while OpenCV's default flags or the SB detector find it. ``hil calibrate`` must
use every pair plain OpenCV would. Images are rendered into tmp_path."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from hil.cli import main
from hil.errors import CalibrationError
from hil.vision.calibrate import (
    BoardDetection,
    CalibrationSettings,
    _pair_reason,
    calibrate_from_files,
    detect_chessboard,
)
from hil.vision.camera_model import StereoCalibration
from hil.vision.render import RenderOptions, random_board_poses, render_chessboard_pair

COLS, ROWS, SQUARE = 9, 6, 20.0
N_PAIRS = 10
HARD = (1, 4, 6, 8)  # pairs whose left and right views get uneven lighting
FAST_FLAGS = (cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_FAST_CHECK, cv2.CALIB_CB_FAST_CHECK)


def _uneven_light(img: np.ndarray, rng: np.random.Generator, centre: tuple[float, float]) -> np.ndarray:
    """A lamp off to one side: gain from 0.25 to 1.2 across the image, defocus, sensor noise."""
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((xx - centre[0] * w) / (0.35 * w)) ** 2 + ((yy - centre[1] * h) / (0.35 * h)) ** 2
    gain = 0.25 + 0.95 * np.exp(-r2)
    f = cv2.GaussianBlur(img.astype(np.float32) * gain + 20.0, (0, 0), 1.6)
    f += rng.standard_normal(f.shape).astype(np.float32) * 4.0
    return np.clip(f, 0, 255).astype(np.uint8)


def _noisy(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return np.clip(img.astype(np.float32) + rng.standard_normal(img.shape) * 1.5, 0, 255).astype(np.uint8)


def _fast_finds(img: np.ndarray) -> bool:
    return any(cv2.findChessboardCorners(img, (COLS, ROWS), flags=f)[0] for f in FAST_FLAGS)


def _opencv_finds(img: np.ndarray) -> bool:
    """Plain OpenCV as a user would call it: default flags, or the SB detector."""
    size = (COLS, ROWS)
    return bool(cv2.findChessboardCorners(img, size)[0] or cv2.findChessboardCornersSB(img, size)[0])


@pytest.fixture(scope="module")
def rig640() -> StereoCalibration:
    K1 = np.array([[560.0, 0.0, 322.0], [0.0, 561.0, 254.0], [0.0, 0.0, 1.0]])
    K2 = np.array([[558.0, 0.0, 318.0], [0.0, 559.5, 259.0], [0.0, 0.0, 1.0]])
    R = cv2.Rodrigues(np.array([0.004, 0.012, 0.002]))[0]
    return StereoCalibration(
        (640, 512), K1, np.array([-0.1, 0.06, 0.0005, -0.0003, 0.0]),
        K2, np.array([-0.09, 0.05, -0.0002, 0.0004, 0.0]), R, np.array([-80.0, -0.02, -0.47]),
    )


@pytest.fixture(scope="module")
def hard_set(rig640: StereoCalibration, tmp_path_factory: pytest.TempPathFactory) -> Path:
    rng = np.random.default_rng(5)
    d = tmp_path_factory.mktemp("hard_boards")
    poses = random_board_poses(
        rig640, 40, rng, COLS, ROWS, SQUARE, distance_mm=(350.0, 700.0), margin_px=15.0
    )
    opts = RenderOptions(noise_sigma=0.0, blur_sigma_px=0.5)
    written, k = 0, 0
    while written < N_PAIRS:
        left, right = render_chessboard_pair(rig640, poses[k], COLS, ROWS, SQUARE, opts, rng)
        k += 1
        if written in HARD:
            left = _uneven_light(left, rng, (0.8, 0.3))
            right = _uneven_light(right, rng, (0.75, 0.3))
            if _fast_finds(left) and _fast_finds(right):
                continue  # this pose is not hard enough under that light: the next one
        else:
            left, right = _noisy(left, rng), _noisy(right, rng)
        cv2.imwrite(str(d / f"left_{written:02d}.png"), left)
        cv2.imwrite(str(d / f"right_{written:02d}.png"), right)
        written += 1
    return d


def _grey(p: Path) -> np.ndarray:
    img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    assert img is not None
    return img


def test_the_set_reproduces_the_failure(hard_set: Path) -> None:
    """The precondition, checked with OpenCV directly: in each hard pair the fast flags miss the
    board in at least one view, and plain OpenCV (default flags or SB) finds it in both views."""
    for i in HARD:
        left, right = _grey(hard_set / f"left_{i:02d}.png"), _grey(hard_set / f"right_{i:02d}.png")
        assert not (_fast_finds(left) and _fast_finds(right)), i
        assert _opencv_finds(left), i
        assert _opencv_finds(right), i


def test_cascade_finds_what_opencv_finds(hard_set: Path) -> None:
    used = []
    for p in sorted(hard_set.glob("*.png")):
        img = _grey(p)
        det = detect_chessboard(img, COLS, ROWS)
        assert (det.corners is not None) == _opencv_finds(img), p.name
        assert det.tried[0] == "fast"
        used.append(det.detector)
    assert {"robust", "sb"} & set(used)  # the hard views needed a later detector
    assert "fast" in used


def test_calibrate_uses_every_pair_plain_opencv_would(hard_set: Path, rig640: StereoCalibration) -> None:
    expected = sum(
        _opencv_finds(_grey(hard_set / f"left_{i:02d}.png"))
        and _opencv_finds(_grey(hard_set / f"right_{i:02d}.png"))
        for i in range(N_PAIRS)
    )
    assert expected == N_PAIRS
    res = calibrate_from_files(
        str(hard_set / "left_*.png"), str(hard_set / "right_*.png"),
        CalibrationSettings(board_cols=COLS, board_rows=ROWS, square_mm=SQUARE),
    )
    assert res.pairs_found == expected
    assert res.pairs_used == expected
    assert res.missing == ()
    assert res.calibration.baseline_mm == pytest.approx(rig640.baseline_mm, abs=0.5)
    assert len(res.detections) == 2 * N_PAIRS
    hard_files = {f"left_{i:02d}.png" for i in HARD} | {f"right_{i:02d}.png" for i in HARD}
    assert any(Path(r["file"]).name in hard_files and r["detector"] != "fast" for r in res.detections)


def test_cli_summary_fields(hard_set: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cal.json"
    code = main([
        "calibrate", "--left", str(hard_set / "left_*.png"), "--right", str(hard_set / "right_*.png"),
        "--board", f"{COLS}x{ROWS}", "--square", str(SQUARE), "--out", str(out), "--exclude-outliers",
    ])
    assert code == 0
    s = json.loads(capsys.readouterr().out)
    assert set(s) >= {
        "pairs_found", "pairs_used", "rms_left", "rms_right", "rms_stereo", "baseline", "per_view",
        "views_left_out", "detections", "out",
    }
    assert s["pairs_found"] == N_PAIRS
    assert len(s["per_view"]) == N_PAIRS
    fields = {"view", "rms_left_px", "rms_right_px", "rms_stereo_px", "outlier", "used"}
    assert set(s["per_view"][0]) == fields
    assert s["pairs_used"] == sum(v["used"] for v in s["per_view"])
    assert len(s["views_left_out"]) == N_PAIRS - s["pairs_used"]


def test_colour_and_grey_mixed_names_the_file(hard_set: Path, tmp_path: Path) -> None:
    for i in range(3):
        left, right = _grey(hard_set / f"left_{i:02d}.png"), _grey(hard_set / f"right_{i:02d}.png")
        cv2.imwrite(str(tmp_path / f"l{i}.png"), left)
        cv2.imwrite(str(tmp_path / f"r{i}.png"), cv2.cvtColor(right, cv2.COLOR_GRAY2BGR) if i == 2 else right)
    msg = r"r2\.png: a colour \(3 channels\) image, but .*l0\.png is grey"
    with pytest.raises(CalibrationError, match=msg):
        calibrate_from_files(str(tmp_path / "l*.png"), str(tmp_path / "r*.png"))


def test_board_partly_out_of_view_is_left_out_naming_the_file() -> None:
    settings = CalibrationSettings(board_cols=COLS, board_rows=ROWS)
    inside = np.column_stack([np.linspace(50, 300, COLS * ROWS), np.linspace(60, 200, COLS * ROWS)])
    at_edge = inside.copy()
    at_edge[0] = (1.0, 100.0)
    ok = BoardDetection(inside, "fast", ("fast",), 3.0)
    cut = BoardDetection(at_edge, "sb", ("fast", "robust", "sb"), 90.0)
    lost = BoardDetection(None, None, ("fast", "robust", "sb"), 120.0)
    assert _pair_reason(("a/l0.png", "a/r0.png"), (ok, ok), settings, (640, 512)) is None
    reason = _pair_reason(("a/l0.png", "a/r0.png"), (ok, cut), settings, (640, 512))
    assert reason == "r0.png: the board is partly out of view (a corner within 2 px of the image border)"
    reason = _pair_reason(("a/l0.png", "a/r0.png"), (lost, ok), settings, (640, 512))
    assert reason == (
        "l0.png: the 9x6 board was not found (tried fast, robust, sb; no detector found it; 120 ms)"
    )


def test_cut_board_in_a_real_image_is_reported_by_file(hard_set: Path, tmp_path: Path) -> None:
    """A board shifted half out of the image: that pair is left out with one line naming the file,
    the others are used."""
    for i in range(6):
        left, right = _grey(hard_set / f"left_{i:02d}.png"), _grey(hard_set / f"right_{i:02d}.png")
        if i == 0:
            right = np.roll(right, 320, axis=1)
            right[:, :320] = 160
        cv2.imwrite(str(tmp_path / f"l{i}.png"), left)
        cv2.imwrite(str(tmp_path / f"r{i}.png"), right)
    res = calibrate_from_files(
        str(tmp_path / "l*.png"), str(tmp_path / "r*.png"),
        CalibrationSettings(board_cols=COLS, board_rows=ROWS, square_mm=SQUARE),
    )
    assert res.pairs_used == 5
    assert [v for v, _ in res.left_out] == ["l0.png|r0.png"]
    assert res.left_out[0][1].startswith("r0.png: ")
    assert "\n" not in res.left_out[0][1]
