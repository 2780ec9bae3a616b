"""``hil rig-calibrate`` on the simulator with a real rig's errors: figures against the truth,
the file, and every bad input giving one error, the arm stopped and nothing written."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.cli import main
from hil.clock import ManualClock
from hil.config import SetupConfig, build_devices
from hil.rigcal.collect import Confirm, RigCalibrationAbortedError
from hil.rigcal.handeye import RigCalibrationError
from hil.rigcal.rigfile import load_rig_calibration
from hil.rigcal.runner import RigCalibrationOutcome, run_rig_calibration
from plugins.registry import DriverRegistry
from tests.rigcal.conftest import CONFIGS

REALISTIC = str(CONFIGS / "sim_realistic.toml")


def _with(setup: SetupConfig, **rc: object) -> SetupConfig:
    return setup.model_copy(update={"rig_calibration": setup.rig_calibration.model_copy(update=rc)})


def test_cli_recovers_the_true_rig(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "rig.json"
    assert main(["rig-calibrate", REALISTIC, "--auto", "--json", "--out", str(out)]) == 0
    s = json.loads(capsys.readouterr().out)
    for key in ("poses", "poses_used", "outliers", "residual_mm_rms", "residual_deg_rms", "validation_mm_rms",
                "time_offset_ms", "truth_layout_error_mm_rms", "truth_time_offset_error_ms"):
        assert key in s
    assert s["poses"] == 16
    assert s["poses_used"] == 12
    assert s["truth_layout_error_mm_rms"] < 0.06
    assert 0.05 < s["optical_correction_mm"] < 1.0   # the config's cameras are 0.2 px off
    assert set(s["time_offset_ms"]) == {"camera", "robot", "tracker"}
    assert all(abs(e) < 2.0 for e in s["truth_time_offset_error_ms"].values())
    rig = load_rig_calibration(out)
    assert rig.flange_markers_mm is not None
    assert rig.flange_markers_mm.shape == (4, 3)
    assert rig.offset_ns("camera") == round(s["time_offset_ms"]["camera"] * 1e6)
    assert rig.optical_correction is not None


def test_the_optical_correction_keeps_the_cameras_error_out_of_the_layout(
        realistic: SetupConfig, registry: DriverRegistry, tmp_path: Path) -> None:
    """The same rig, the same poses: fitting the camera's error as a warp of space takes it out of
    the layout; without, the layout absorbs it. The rig is the drawn rig 24, the worst of the
    50-rig bench (its cameras 0.29 px off), a draw that is the same on every machine."""
    from hil.rigcal.draw import RigTolerances, draw_rig
    from hil.rigcal.fleet import rig_setup

    rig24 = rig_setup(realistic, draw_rig(24, RigTolerances()))
    errors = {}
    for on in (True, False):
        _, go = _run(_with(rig24, optical_correction=on), registry, tmp_path / f"rig_{on}.json",
                     temporal=False)
        s = go().summary
        errors[on] = s["truth_layout_error_mm_rms"]
        assert (s["optical_correction_mm"] is None) is (not on)
        assert (load_rig_calibration(tmp_path / f"rig_{on}.json").optical_correction is None) is (not on)
    assert errors[True] < 0.03 < 0.25 < errors[False]


def _run(setup: SetupConfig, registry: DriverRegistry, out: Path, confirm: Confirm | None = None,
         **kw: bool) -> tuple[Any, Callable[[], RigCalibrationOutcome]]:
    clock = ManualClock(start_ns=1_000_000_000)
    devices = build_devices(setup, clock, registry)
    return devices, lambda: run_rig_calibration(
        setup, CONFIGS / "sim_realistic.toml", devices, clock,
        confirm if confirm is not None else (lambda _p: True), out_path=out, **kw)


def test_operator_abort_midway_stops_the_arm_and_writes_nothing(
        realistic: SetupConfig, registry: DriverRegistry, tmp_path: Path) -> None:
    answers = iter([True, True, True, False])
    out = tmp_path / "rig.json"
    devices, go = _run(realistic, registry, out, confirm=lambda _p: next(answers))
    stops: list[float | None] = []
    original = devices.robot._stop
    devices.robot._stop = lambda d: (stops.append(d), original(d))
    with pytest.raises(RigCalibrationAbortedError, match="operator aborted at pose 4 of 16"):
        go()
    assert stops
    assert not out.exists()


def test_poses_too_similar(realistic: SetupConfig, registry: DriverRegistry, tmp_path: Path) -> None:
    out = tmp_path / "rig.json"
    _, go = _run(_with(realistic, cone_half_angle_deg=1.0, spin_deg=0.0), registry, out, temporal=False)
    with pytest.raises(RigCalibrationError, match="poses too similar: the largest rotation between two "
                                                  r"poses is \d\.\d deg"):
        go()
    assert not out.exists()


def test_a_pose_outside_the_workspace_is_refused_before_the_arm_moves(
        realistic: SetupConfig, registry: DriverRegistry, tmp_path: Path) -> None:
    safety = realistic.safety.model_copy(update={"workspace_max_mm": (400.0, 500.0, 300.0)})
    out = tmp_path / "rig.json"
    devices, go = _run(realistic.model_copy(update={"safety": safety}), registry, out, temporal=False)
    moves: list[object] = []
    original = devices.robot._move_linear
    devices.robot._move_linear = lambda *a: (moves.append(a), original(*a))
    with pytest.raises(RigCalibrationError, match=r"pose 0 at \[.*\] mm cannot be reached: .*outside box"):
        go()
    assert moves == []
    assert not out.exists()


def test_markers_not_seen(realistic: SetupConfig, registry: DriverRegistry, tmp_path: Path) -> None:
    frames = realistic.frames.model_copy(update={"flange_markers_mm": ((0.0, 0.0, 0.0), (90.0, 0.0, 0.0),
                                                                       (0.0, 15.0, 0.0))})
    setup = _with(realistic, still_timeout_s=1.0).model_copy(update={"frames": frames})
    out = tmp_path / "rig.json"
    devices, go = _run(setup, registry, out, temporal=False)
    stops: list[float] = []
    original = devices.robot._stop
    devices.robot._stop = lambda d: (stops.append(d), original(d))
    with pytest.raises(RigCalibrationError, match="markers not seen at pose 0"):
        go()
    assert stops
    assert not out.exists()


def test_validation_bound_refuses_the_file(realistic: SetupConfig, registry: DriverRegistry,
                                           tmp_path: Path) -> None:
    out = tmp_path / "rig.json"
    _, go = _run(_with(realistic, max_validation_mm=0.001), registry, out, temporal=False)
    with pytest.raises(RigCalibrationError, match=r"validation error .* over the bound 0.001 mm"):
        go()
    assert not out.exists()


def test_too_few_poses_on_the_command_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rig-calibrate", REALISTIC, "--auto", "--poses", "3"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == ("hil rig-calibrate: error: --poses: too few poses: 3 (need >= 8, "
                           "[rig_calibration] min_poses)")


def test_temporal_only_keeps_the_hand_eye_part(realistic: SetupConfig, registry: DriverRegistry,
                                               tmp_path: Path) -> None:
    out = tmp_path / "rig.json"
    _, go = _run(_with(realistic, poses=8, min_poses=8), registry, out, temporal=False)
    go()
    first = load_rig_calibration(out)
    assert first.time_offsets == {}
    _, go2 = _run(realistic, registry, out, hand_eye=False)
    go2()
    second = load_rig_calibration(out)
    assert first.flange_markers_mm is not None
    assert second.flange_markers_mm is not None
    np.testing.assert_array_equal(first.flange_markers_mm, second.flange_markers_mm)
    assert first.optical_correction is not None
    assert second.optical_correction is not None
    np.testing.assert_array_equal(first.optical_correction.H_metric_from_measured,
                                  second.optical_correction.H_metric_from_measured)
    assert set(second.time_offsets) == {"camera", "robot", "tracker"}
