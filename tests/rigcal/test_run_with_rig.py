"""``hil run`` with ``[calibration] rig``: the calibrated layout and time offsets are used, the file's
SHA-256 is in the session log header, and a bad file is one error line."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from hil.cli import main
from hil.config import SetupConfig, load_setup
from hil.rigcal.apply import flange_markers_mm, with_rig_time_offsets
from hil.rigcal.time_align import TimeAlignedCamera, TimeAlignedRobot, TimeAlignedTracker
from tests.rigcal.conftest import CONFIGS

LAYOUT = [[40.2, 90.1, 10.0], [-35.0, 105.3, 9.8], [-10.1, 140.0, 10.2], [30.0, 150.4, 25.1]]


def _setup_with_rig(tmp_path: Path, doc: dict[str, object]) -> Path:
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps(doc))
    text = (CONFIGS / "sim_realistic.toml").read_text()
    cal = (CONFIGS / "calibration" / "sim_stereo.json").resolve()
    text = text.replace('stereo = "calibration/sim_stereo.json"', f'stereo = "{cal}"\nrig = "{rig}"')
    cfg = tmp_path / "rigged.toml"
    cfg.write_text(text)
    return cfg


DOC = {"schema": "hil.rig_calibration", "version": 1, "hand_eye": {"flange_markers_mm": LAYOUT},
       "time_offsets": {"camera": {"offset_ms": 45.0, "sigma_ms": 0.2},
                        "robot": {"offset_ms": 8.0, "sigma_ms": 0.1}}}


def test_layout_and_offsets_come_from_the_file(tmp_path: Path, perfect: SetupConfig) -> None:
    setup = load_setup(_setup_with_rig(tmp_path, DOC))
    np.testing.assert_array_equal(flange_markers_mm(setup), np.array(LAYOUT))
    np.testing.assert_array_equal(flange_markers_mm(perfect), np.asarray(perfect.frames.flange_markers_mm))
    from hil.clock import ManualClock
    from hil.config import build_devices

    devs = with_rig_time_offsets(setup, build_devices(setup, ManualClock()))
    assert isinstance(devs.camera, TimeAlignedCamera)
    assert devs.camera.offset_ns == 45_000_000
    assert isinstance(devs.robot, TimeAlignedRobot)
    assert not isinstance(devs.tracker, TimeAlignedTracker)   # no tracker offset in the file
    devs.close_all()


def test_run_records_the_rig_file_hash(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = _setup_with_rig(tmp_path, DOC)
    code = main(["run", str(cfg), "--auto", "--json", "--no-report", "--plan",
                 str(CONFIGS / "plans" / "sim_realistic_plan.json"), "--session-dir", str(tmp_path / "s"),
                 "--max-duration", "3"])
    assert code in (0, 1)
    summary = json.loads(capsys.readouterr().out)
    header = json.loads(Path(summary["session_log"]).read_text().splitlines()[0])
    expect = hashlib.sha256((tmp_path / "rig.json").read_bytes()).hexdigest()
    assert json.dumps(header).count(expect) == 1


def test_a_rig_file_of_another_rig_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = {**DOC, "hand_eye": {"flange_markers_mm": LAYOUT[:3]}}
    cfg = _setup_with_rig(tmp_path, doc)
    assert main(["run", str(cfg), "--auto", "--plan", str(CONFIGS / "plans" / "sim_realistic_plan.json"),
                 "--session-dir", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("hand_eye.flange_markers_mm has 3 markers, [frames] flange_markers_mm 4: "
                        "a file of another rig?")
    assert len(err.splitlines()) == 1


def test_a_rig_file_made_through_another_stereo_calibration_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cal = (CONFIGS / "calibration" / "sim_stereo.json").resolve()
    now = hashlib.sha256(cal.read_bytes()).hexdigest()
    ok = _setup_with_rig(tmp_path, {**DOC, "stereo_calibration_sha256": now})
    np.testing.assert_array_equal(flange_markers_mm(load_setup(ok)), np.array(LAYOUT))   # the same: used
    cfg = _setup_with_rig(tmp_path, {**DOC, "stereo_calibration_sha256": "ab" * 32})
    assert main(["run", str(cfg), "--auto", "--plan", str(CONFIGS / "plans" / "sim_realistic_plan.json"),
                 "--session-dir", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.endswith(f"made through another stereo calibration (SHA-256 abababababab...) than "
                        f"[calibration] stereo = {cal} ({now[:12]}...): its layout and optical correction "
                        "were measured through that one; run hil rig-calibrate again after a camera "
                        "calibration")


def test_the_rig_file_names_its_stereo_calibration(tmp_path: Path) -> None:
    out = tmp_path / "rig.json"
    assert main(["rig-calibrate", str(CONFIGS / "sim_realistic.toml"), "--auto", "--no-temporal",
                 "--poses", "8", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    cal = (CONFIGS / "calibration" / "sim_stereo.json").resolve()
    assert Path(doc["stereo_calibration"]).resolve() == cal
    assert doc["stereo_calibration_sha256"] == hashlib.sha256(cal.read_bytes()).hexdigest()
