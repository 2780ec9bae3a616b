"""``hil rig-calibrate --samples FILE`` in process: the JSON, the result file, exit 2 with one
line and nothing written on a bad file or a bad combination of options."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hil.cli import main
from hil.rigcal.offline import HAND_EYE_METHODS, ROBOT_WORLD_METHODS
from tests.rigcal.samples_synth import easy_handeye_text, synth_pairs, write_csv_pairs, write_opencv_yaml


def test_json_and_result_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    X, Z, B, C = synth_pairs(np.random.default_rng(21), 30, False, noise_mm=0.2, noise_deg=0.05)
    f, out = tmp_path / "pairs.yml", tmp_path / "he.json"
    write_opencv_yaml(f, B, C)
    assert main(["rig-calibrate", "--samples", str(f), "--out", str(out), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["setup"] == "eye-to-hand"
    assert s["format"] == "opencv-yaml"
    assert s["pairs"] == 30
    assert s["pairs_used"] == 24      # 6 held out
    assert s["outliers"] == []
    assert np.linalg.norm(np.array(s["X"])[:3, 3] - X[:3, 3]) < 1.0
    assert np.linalg.norm(np.array(s["Z"])[:3, 3] - Z[:3, 3]) < 2.0
    assert s["residual_mm_rms"] < 1.0
    assert s["residual_deg_rms"] < 0.2
    assert s["validation"]["pairs"] == 6
    assert set(s["methods"]) == set(HAND_EYE_METHODS + ROBOT_WORLD_METHODS)
    assert set(s["methods"]["TSAI"]) == {"dt_mm", "dr_deg"}
    assert "time_offset_ms" not in s
    assert s["solve_s"] > 0.0   # its speed is a figure (docs/rig-calibration.md), not a timed test
    doc = json.loads(out.read_text())
    assert doc["schema"] == "hil.hand_eye"
    assert doc["version"] == 1
    assert doc["X"] == s["X"]


def test_eye_in_hand_easy_handeye_text_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _, _, B, C = synth_pairs(np.random.default_rng(22), 12, True)
    f = tmp_path / "eih.samples"
    f.write_text(easy_handeye_text(B, C, eye_in_hand=True))
    assert main(["rig-calibrate", "--samples", str(f), "--setup", "eye-in-hand"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("setup            eye-in-hand (T_base_from_target = T_base_from_flange @ X @ "
                           "T_camera_from_target, X = T_flange_from_camera, Z = T_base_from_target)\n")
    assert "residual         0.000 mm RMS, 0.000 deg RMS\n" in text


def test_bad_file_exit_2_one_line_nothing_written(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _, _, B, C = synth_pairs(np.random.default_rng(23), 10, False)
    C = C.copy()
    C[4, 0, 0] = np.nan
    f, out = tmp_path / "pairs.csv", tmp_path / "he.json"
    write_csv_pairs(f, B, C, layout="matrix", scale=1.0)
    assert main(["rig-calibrate", "--samples", str(f), "--out", str(out), "--json"]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err == f"hil rig-calibrate: error: {f}: line 7 (camera): not a finite number (NaN or inf)\n"
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [f]


def test_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "none.csv"
    assert main(["rig-calibrate", "--samples", str(f)]) == 2
    assert capsys.readouterr().err == f"hil rig-calibrate: error: {f}: no such file\n"


@pytest.mark.parametrize(("argv", "err"), [
    (["cfg.toml", "--samples", "x.csv"],
     "cfg.toml: give either CONFIG (live) or --samples FILE (offline), not both"),
    (["--samples", "x.csv", "--auto"], "--auto: only in the live mode (not with --samples)"),
    (["--samples", "x.csv", "--no-temporal"], "--no-temporal: only in the live mode (not with --samples)"),
    ([], "CONFIG: give a setup TOML (live) or --samples FILE (offline)"),
    (["cfg.toml", "--setup", "eye-in-hand"], "--setup/--format: only with --samples FILE"),
])
def test_option_mistakes(argv: list[str], err: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rig-calibrate", *argv]) == 2
    assert capsys.readouterr().err == f"hil rig-calibrate: error: {err}\n"


def test_fewest_pairs_accepted_and_one_fewer_refused(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    X, _, B, C = synth_pairs(np.random.default_rng(24), 6, False)
    f = tmp_path / "six.csv"
    write_csv_pairs(f, B, C)
    assert main(["rig-calibrate", "--samples", str(f), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["pairs"] == 6
    assert s["pairs_used"] == 5       # the 5th is held out
    assert np.linalg.norm(np.array(s["X"])[:3, 3] - X[:3, 3]) < 1e-6
    write_csv_pairs(f, B[:5], C[:5])
    assert main(["rig-calibrate", "--samples", str(f), "--json"]) == 2
    assert capsys.readouterr().err == f"hil rig-calibrate: error: {f}: too few pairs: 5 (need >= 6)\n"
