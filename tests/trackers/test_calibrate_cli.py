"""``hil tracker-calibrate``: recorded poses -> calibration file; the interactive walk-through;
and the whole chain through the Flock emulator and driver."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from drivers.interfaces.tracker import TrackerSample
from drivers.tracker_serial.config import FlockOfBirdsConfig
from drivers.tracker_serial.fob import FlockOfBirdsTracker
from hil.cli import main
from hil.clock import ManualClock, MonotonicClock
from hil.geometry.transform import RigidTransform
from hil.tracking.pivot import pivot_calibration
from hil.tracking.session import (
    RecordedSession,
    RecordedTouch,
    collect_interactive,
    collect_samples,
    load_tracker_calibration,
    pose_to_json,
)

from .conftest import FobFactory
from .test_pivot import MARKERS_OPTICAL, _touches, pivot_poses

TIP = np.array([1.5, -2.0, 140.0])
T_OPT_FROM_TRK = RigidTransform.from_rotvec([0.1, 0.9, -0.2], [100.0, 20.0, 600.0])


def _session(rng: np.random.Generator) -> RecordedSession:
    pivot = pivot_poses(TIP, np.array([250.0, 30.0, 60.0]), 120, rng, noise_mm=0.1)
    touches = [RecordedTouch(t.label, list(t.poses), MARKERS_OPTICAL[k])
               for k, t in enumerate(_touches(T_OPT_FROM_TRK, TIP, rng))]
    return RecordedSession(stylus="stylus", pivot=pivot, touches=touches)


def test_cli_with_recorded_poses_writes_the_calibration(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps(_session(np.random.default_rng(4)).to_json()))
    out = tmp_path / "cal" / "tracker_calibration.json"
    assert main(["tracker-calibrate", "--poses", str(poses), "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["out"] == str(out)
    assert np.linalg.norm(np.array(summary["pivot"]["tip_offset_sensor_mm"]) - TIP) < 0.2
    assert summary["pivot"]["rms_mm"] < 0.3
    assert summary["registration"]["n_markers"] == 4
    assert summary["registration"]["fre_rms_mm"] < 0.3
    tip, T = load_tracker_calibration(out)
    np.testing.assert_allclose(tip, summary["pivot"]["tip_offset_sensor_mm"])
    assert T is not None
    assert T.is_close(T_OPT_FROM_TRK, atol_mm=0.5, atol_rad=2e-3)


def test_cli_markers_file_supplies_optical_positions(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    doc = _session(np.random.default_rng(8)).to_json()
    for t in doc["touches"]:
        del t["optical_mm"]
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps(doc))
    markers = tmp_path / "markers.csv"
    markers.write_text("label,x,y,z\n" + "".join(f"M{k + 1},{p[0]},{p[1]},{p[2]}\n"
                                                 for k, p in enumerate(MARKERS_OPTICAL)))
    out = tmp_path / "cal.json"
    args = ["tracker-calibrate", "--poses", str(poses), "--markers", str(markers), "--out", str(out)]
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out)["registration"]["fre_rms_mm"] < 0.3


@pytest.mark.parametrize(("content", "message"), [
    ("{not json", "not JSON"),
    ('{"pivot": [{"position_mm": [1, 2]}]}', "pivot[0]"),
    ('{"pivot": [{"position_mm": [1, 2, 3], "quaternion_wxyz": [2, 0, 0, 0]}]}', "norm"),
    ('{"pivot": []}', "at least 4 poses"),
])
def test_cli_bad_input_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str,
                                   message: str) -> None:
    poses = tmp_path / "poses.json"
    poses.write_text(content)
    assert main(["tracker-calibrate", "--poses", str(poses), "--out", str(tmp_path / "c.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert message in err[0]
    assert "Traceback" not in err[0]


class ScriptedTracker:
    """A stand-in tracker: each ``latest()`` gives the next pose of the current phase."""

    def __init__(self, phases: list[list[RigidTransform]]) -> None:
        self.phases = phases
        self.phase = -1
        self.i = 0
        self.seq = 0

    def next_phase(self, _message: str) -> None:
        self.phase += 1
        self.i = 0

    def latest(self) -> dict[str, TrackerSample]:
        poses = self.phases[self.phase]
        T = poses[self.i % len(poses)]
        self.i += 1
        self.seq += 1
        return {"stylus": TrackerSample("stylus", T, None, self.seq, self.seq)}


def test_interactive_walk_through() -> None:
    rng = np.random.default_rng(9)
    session = _session(rng)
    tracker = ScriptedTracker([session.pivot] + [t.poses for t in session.touches])
    said: list[str] = []
    got = collect_interactive(tracker, ManualClock(), stylus="stylus", labels=["M1", "M2", "M3", "M4"],
                              ask=tracker.next_phase, say=said.append, pivot_samples=100, touch_samples=10)
    assert len(got.pivot) == 100
    assert [t.label for t in got.touches] == ["M1", "M2", "M3", "M4"]
    assert said[0].startswith("pivot: tip offset")
    assert "spread" in said[1]


def test_collect_times_out_on_a_missing_sensor() -> None:
    from hil.errors import CalibrationError

    class Missing:
        def latest(self) -> dict[str, TrackerSample]:
            return {"stylus": TrackerSample("stylus", None, None, 0, 0, missing=True)}

    with pytest.raises(CalibrationError, match="only 0 of 5 samples"):
        collect_samples(Missing(), "stylus", 5, ManualClock(), timeout_s=1.0)


class PivotingStylus:
    """Pose source for the emulator: the stylus swivels about a divot (a pluggable PoseSource)."""

    def __init__(self, tip: np.ndarray, pivot: np.ndarray) -> None:
        self.tip, self.pivot = tip, pivot

    def pose(self, sensor: str, t_s: float) -> RigidTransform:
        a = 2 * math.pi * t_s / 1.3
        R = RigidTransform.from_rotvec([0.45 * math.cos(a), 0.45 * math.sin(a), 0.3 * math.sin(0.7 * a)]).R
        return RigidTransform(R, self.pivot - R @ self.tip)


def test_pivot_calibration_through_the_flock_emulator(fob_emulator: FobFactory) -> None:
    tip, pivot = np.array([0.0, 3.0, 150.0]), np.array([300.0, 40.0, 50.0])
    dev = fob_emulator(poses=PivotingStylus(tip, pivot))
    cfg = FlockOfBirdsConfig(driver="fob", port=dev.link.path, sensors={"stylus": 0}, reset_hold_s=0.0,
                             reset_settle_s=0.0, record_format="position_matrix")
    with FlockOfBirdsTracker(cfg) as tracker:
        poses, _ = collect_samples(tracker, "stylus", 150, MonotonicClock(), timeout_s=30.0)
    cal = pivot_calibration(poses)
    # 14-bit records (0.11 mm, 1/8192 per matrix element) limit the accuracy.
    assert np.linalg.norm(cal.tip_offset_sensor_mm - tip) < 0.5
    assert np.linalg.norm(cal.pivot_tracker_mm - pivot) < 0.5
    assert cal.rms_mm < 0.5


def test_pose_json_round_trip() -> None:
    T = RigidTransform.from_rotvec([0.2, 0.1, -0.3], [1.0, 2.0, 3.0])
    doc = pose_to_json(T)
    from hil.tracking.session import pose_from_json

    assert pose_from_json(doc, "x").is_close(T, atol_mm=1e-9, atol_rad=1e-9)


class PhasedStylus:
    """Pose source driven by the user's Enter presses: phase 0 swivels about the divot, phase k
    holds the tip on marker k (in the tracker frame) with a slowly changing orientation."""

    def __init__(self, tip: np.ndarray, pivot: np.ndarray, markers_tracker: np.ndarray) -> None:
        self.swivel = PivotingStylus(tip, pivot)
        self.tip, self.markers = tip, markers_tracker
        self.phase = -1

    def pose(self, sensor: str, t_s: float) -> RigidTransform:
        if self.phase <= 0:
            return self.swivel.pose(sensor, t_s)
        R = RigidTransform.from_rotvec([0.2 + 0.05 * math.sin(t_s), -0.1, 0.3]).R
        return RigidTransform(R, self.markers[self.phase - 1] - R @ self.tip)


class EnterKey:
    """stdin stand-in: each readline() is the user pressing Enter (the stylus moves on)."""

    def __init__(self, poses: PhasedStylus) -> None:
        self.poses = poses

    def readline(self) -> str:
        self.poses.phase += 1
        return "\n"


def test_interactive_cli_against_the_flock_emulator(fob_emulator: FobFactory, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    T_opt_trk = RigidTransform.from_rotvec([0.0, 0.0, 0.3], [-300.0, 0.0, 700.0])
    markers_tracker = T_opt_trk.inverse().apply(MARKERS_OPTICAL)
    tip = np.array([0.0, 0.0, 120.0])
    poses = PhasedStylus(tip, np.array([280.0, 20.0, 40.0]), markers_tracker)
    dev = fob_emulator(poses=poses)
    setup = tmp_path / "setup.toml"
    setup.write_text(f'''
[camera]
driver = "sim"
[robot]
driver = "sim"
[tracker]
driver = "fob"
port = "{dev.link.path}"
sensors = {{ stylus = 0 }}
record_format = "position_matrix"
reset_hold_s = 0.0
reset_settle_s = 0.0
''')
    markers = tmp_path / "markers.csv"
    markers.write_text("label,x,y,z\n" + "".join(f"M{k + 1},{p[0]},{p[1]},{p[2]}\n"
                                                 for k, p in enumerate(MARKERS_OPTICAL)))
    monkeypatch.setattr("sys.stdin", EnterKey(poses))
    record = tmp_path / "raw_poses.json"
    code = main(["tracker-calibrate", "--setup", str(setup), "--markers", str(markers),
                 "--pivot-samples", "150", "--touch-samples", "10", "--record", str(record)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    summary = json.loads(captured.out)
    assert summary["out"] == str(tmp_path / "tracker_calibration.json")
    assert np.linalg.norm(np.array(summary["pivot"]["tip_offset_sensor_mm"]) - tip) < 0.5
    assert summary["registration"]["fre_rms_mm"] < 0.5
    T = RigidTransform.from_matrix(np.array(summary["registration"]["T_optical_from_tracker"]))
    assert T.is_close(T_opt_trk, atol_mm=1.0, atol_rad=3e-3)
    assert "Touch marker M4" in captured.err
    # The raw poses recompute to the same calibration.
    again = tmp_path / "again.json"
    args = ["tracker-calibrate", "--poses", str(record), "--markers", str(markers), "--out", str(again)]
    assert main(args) == 0
