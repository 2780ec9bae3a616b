"""``hil rig-calibrate --samples`` on the project's own session logs (hil.rigcal.session_samples):
a log written by the controller's own writer, with still poses, moving frames and unseen markers;
a real procedure's log (too few still poses, said so); and malformed logs, each one line."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from hil.cli import main
from hil.clock import ManualClock
from hil.controller.events import FRAME_MEASURED
from hil.geometry.transform import RigidTransform
from hil.rigcal.sample_readers import detect_format, read_samples
from hil.rigcal.samples import SamplesError
from hil.rigcal.session_samples import MIN_STILL_FRAMES, read_session_log
from hil.session.log import SessionLog

PLATE_GUIDE_MM = np.array([[40.0, 90.0, -50.0], [-35.0, 105.0, -50.0], [-10.0, 140.0, -50.0],
                           [30.0, 150.0, -35.0]])
Z_TRUE = RigidTransform.from_rotvec((math.pi, 0.02, -0.01), (60.0, 300.0, 1120.0))   # T_optical_from_robot
START = RigidTransform.from_rotvec((math.pi, 0.0, 0.0), (0.0, 250.0, 220.0))        # the guide's pose


def _poses(n: int, rng: np.random.Generator) -> list[RigidTransform]:
    return [START @ RigidTransform.from_rotvec(np.radians(rng.uniform(-20, 20, size=3)),
                                               rng.uniform(-40, 40, size=3)) for _ in range(n)]


def _write_log(path: Path, poses: list[RigidTransform], rng: np.random.Generator, noise_mm: float = 0.02,
               still_frames: int = 5) -> None:
    """A session log as the controller writes it: per pose ``still_frames`` still frames, then two
    frames moving to the next pose; one marker unseen in every fourth still frame."""
    clock = ManualClock(1_000_000_000)
    log = SessionLog(path, clock, {"setup": "synthetic", "auto": True})
    try:
        for k, T in enumerate(poses):
            seen = (Z_TRUE @ T).apply(PLATE_GUIDE_MM)
            for i in range(still_frames):
                clock.advance(1 / 15)
                m: list[list[float] | None] = [list(p) for p in seen + noise_mm * rng.normal(size=seen.shape)]
                if i % 4 == 3:
                    m[k % 4] = None
                log.write(FRAME_MEASURED, frame_seq=k * 10 + i, exposure_t_ns=clock.now_ns() - 40_000_000,
                          flange_markers=sum(r is not None for r in m), flange_mm=m,
                          T_robot_from_guide=T, tcp_speed_mm_s=0.0)
            for i in range(2):   # moving: never paired
                clock.advance(1 / 15)
                log.write(FRAME_MEASURED, frame_seq=k * 10 + 8 + i, exposure_t_ns=clock.now_ns(),
                          flange_markers=4, flange_mm=(seen + 5.0).tolist(),
                          T_robot_from_guide=T @ RigidTransform.from_translation((3.0 * (i + 1), 0, 0)),
                          tcp_speed_mm_s=40.0)
    finally:
        log.close(final_state="done")


def test_a_session_log_gives_one_pair_per_still_pose(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    poses = _poses(14, rng)
    f = tmp_path / "session.jsonl"
    _write_log(f, poses, rng)
    assert detect_format(f) == "session-log"
    pairs = read_samples(f, "session-log", eye_in_hand=False)
    assert len(pairs) == 14
    np.testing.assert_allclose(pairs.T_base_from_flange[5], poses[5].as_matrix(), atol=1e-9)
    # the plate's pose is a rigid motion of the reference shape: Z B X with one fixed X
    X = np.linalg.inv(Z_TRUE.as_matrix() @ pairs.T_base_from_flange[0]) @ pairs.T_camera_from_target[0]
    for k in range(14):
        pred = Z_TRUE.as_matrix() @ pairs.T_base_from_flange[k] @ X
        assert np.linalg.norm(pred[:3, 3] - pairs.T_camera_from_target[k][:3, 3]) < 0.1


def test_the_command_solves_a_session_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(4)
    f = tmp_path / "session.jsonl"
    _write_log(f, _poses(16, rng), rng)
    assert main(["rig-calibrate", "--samples", str(f), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["format"] == "session-log"
    assert s["setup"] == "eye-to-hand"
    assert s["pairs"] == 16
    Z = RigidTransform.from_matrix(np.array(s["Z"]))
    assert Z.is_close(Z_TRUE, atol_mm=0.2, atol_rad=math.radians(0.02))
    assert s["residual_mm_rms"] < 0.1


def test_a_procedure_log_has_too_few_still_poses(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(5)
    f = tmp_path / "run.jsonl"
    _write_log(f, _poses(3, rng), rng)    # a procedure: home, stand-off, lock
    assert main(["rig-calibrate", "--samples", str(f)]) == 2
    assert capsys.readouterr().err.strip() == f"hil rig-calibrate: error: {f}: too few pairs: 3 (need >= 6)"


def test_short_stretches_are_not_poses(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    f = tmp_path / "run.jsonl"
    _write_log(f, _poses(8, rng), rng, still_frames=MIN_STILL_FRAMES - 1)
    with pytest.raises(SamplesError, match=r"no still poses with >= 3 flange markers seen"):
        read_session_log(f)


def test_eye_in_hand_is_refused(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    f = tmp_path / "s.jsonl"
    _write_log(f, _poses(8, rng), rng)
    with pytest.raises(SamplesError, match="a session log is eye-to-hand"):
        read_samples(f, "session-log", eye_in_hand=True)


HEADER = '{"event": "session_started"}'
GOOD_FRAME = {"event": "frame_measured", "exposure_t_ns": 1, "tcp_speed_mm_s": 0,
              "flange_mm": [[1, 2, 3], [4, 5, 6], [7, 8, 10]],
              "T_robot_from_guide": {"rotvec_rad": [0, 0, 0], "t_mm": [1, 2, 3]}}


def _frame(**change: object) -> str:
    return json.dumps({**GOOD_FRAME, **change})


@pytest.mark.parametrize(("lines", "message"), [
    (['{"event": "frame_measured"}'],
     r"line 1: not a session log \(the first record must be 'session_started'\)"),
    ([HEADER, "{oops"], r"line 2: not JSON"),
    ([HEADER, "[1, 2]"], r"line 2: not a JSON object"),
    ([HEADER, _frame(T_robot_from_guide={"rotvec_rad": [0, 0, None], "t_mm": [1, 2, 3]})],
     r"line 2 \(T_robot_from_guide\): not a finite number"),
    ([HEADER, _frame(T_robot_from_guide={"rotvec_rad": [0, 0], "t_mm": [1, 2, 3]})],
     r"line 2: T_robot_from_guide is not two 3-vectors"),
    ([HEADER, _frame(T_robot_from_guide={"t_mm": [1, 2, 3]})],
     r"line 2: T_robot_from_guide must be \{rotvec_rad, t_mm\}"),
    ([HEADER, _frame(exposure_t_ns=1.5)], r"line 2: exposure_t_ns must be an integer"),
    ([HEADER, _frame(flange_mm=[[1, 2], [4, 5, 6]])], r"line 2: flange_mm is not a list of \[x, y, z\] rows"),
])
def test_a_malformed_log_names_the_line(tmp_path: Path, lines: list[str], message: str) -> None:
    f = tmp_path / "bad.jsonl"
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(SamplesError, match=message):
        read_session_log(f)
