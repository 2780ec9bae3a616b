from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from hil.cli import main
from hil.vision.camera_model import StereoCalibration, save_calibration
from hil.vision.render import RenderedPair, RingMarker3D


@pytest.fixture
def files(
    tmp_path: Path, cal: StereoCalibration, scene: tuple[list[RingMarker3D], RenderedPair]
) -> dict[str, Path]:
    markers, pair = scene
    out = {
        "cal": tmp_path / "cal.json",
        "left": tmp_path / "left.png",
        "right": tmp_path / "right.png",
        "markers": tmp_path / "markers.json",
    }
    save_calibration(cal, out["cal"])
    cv2.imwrite(str(out["left"]), pair.left)
    cv2.imwrite(str(out["right"]), cv2.cvtColor(pair.right, cv2.COLOR_GRAY2BGR))  # colour file: converted
    model = [[float(v) for v in m.center_mm + np.array([10.0, 0.0, 0.0])] for m in reversed(markers)]
    out["markers"].write_text(json.dumps(model))
    return out


def test_locate_prints_points_and_identification(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str], scene: tuple[list[RingMarker3D], RenderedPair]
) -> None:
    markers, _ = scene
    code = main(
        [
            "locate",
            "--calibration",
            str(files["cal"]),
            str(files["left"]),
            str(files["right"]),
            "--markers",
            str(files["markers"]),
        ]
    )
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert len(doc["detections_left"]) == len(markers) == len(doc["detections_right"])
    assert len(doc["points"]) == len(markers)
    pts = np.array([p["point_mm"] for p in doc["points"]])
    truth = np.array([m.center_mm for m in markers])
    assert max(float(np.min(np.linalg.norm(truth - p, axis=1))) for p in pts) < 0.3
    ident = doc["identification"]
    n = len(markers)
    for k, j in ident["model_to_point"].items():  # model k is marker n-1-k shifted by 10 mm in x
        np.testing.assert_allclose(pts[j], markers[n - 1 - int(k)].center_mm, atol=0.3)
    assert ident["fre_rms_mm"] < 0.3


@pytest.mark.parametrize(
    ("which", "content", "message"),
    [
        ("left", None, "image file not found"),
        ("right", b"", "image file is empty"),
        ("left", b"garbage", "not an image"),
        ("cal", b"{", "not valid JSON"),
        ("markers", b"[[1, 2]]", ""),
    ],
)
def test_locate_bad_inputs_exit_2_with_one_line(
    files: dict[str, Path],
    capsys: pytest.CaptureFixture[str],
    which: str,
    content: bytes | None,
    message: str,
) -> None:
    if content is None:
        files[which].unlink()
    else:
        files[which].write_bytes(content)
    code = main(
        [
            "locate",
            "--calibration",
            str(files["cal"]),
            str(files["left"]),
            str(files["right"]),
            "--markers",
            str(files["markers"]),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1
    assert str(files[which]) in err
    assert message in err


def test_locate_wrong_image_size(files: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    cv2.imwrite(str(files["left"]), np.zeros((480, 640), np.uint8))
    assert main(["locate", "--calibration", str(files["cal"]), str(files["left"]), str(files["right"])]) == 2
    assert "left image: image is 640x480 but the calibration is for 1920x1080" in capsys.readouterr().err
