"""``hil rig-calibrate --samples`` on the real ETH recordings (../shared/data/handeye/eth, Furrer
et al. FSR 2017). Absent data is a failure naming the missing path, never a skip."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.cli import main
from tests.rigcal.samples_synth import shared_data_dir

ETH = shared_data_dir() / "handeye" / "eth"


def _zip(name: str) -> Path:
    p = ETH / name
    assert p.is_file(), f"missing data file {p} (the shared data set must sit beside the repository)"
    return p


def _run(p: Path, capsys: pytest.CaptureFixture[str]) -> dict[str, object]:
    assert main(["rig-calibrate", "--samples", str(p), "--json"]) == 0
    s: dict[str, object] = json.loads(capsys.readouterr().out)
    return s


def test_robot_arm_real(capsys: pytest.CaptureFixture[str]) -> None:
    """Robot poses at 50 Hz, camera target poses at 30 Hz, eye-in-hand: the camera's stamps are
    ~15 ms late; a few mm of residual (the camera's pose jitter); the closed forms but Daniilidis
    and Li agree with the refined X within ~7 mm (docs/rig-calibration.md has the figures)."""
    s = _run(_zip("robot_arm_w_color_camera_real.zip"), capsys)
    assert s["setup"] == "eye-in-hand"
    assert s["format"] == "eth"
    assert s["pairs"] == 1687
    assert s["time_offset_ms"] == pytest.approx(15.3, abs=1.5)
    assert 3.0 < s["residual_mm_rms"] < 4.0           # type: ignore[operator]
    assert 0.4 < s["residual_deg_rms"] < 0.8          # type: ignore[operator]
    v = s["validation"]
    assert isinstance(v, dict)
    assert v["pairs"] == 20
    assert v["residual_mm_rms"] < 4.0
    methods = s["methods"]
    assert isinstance(methods, dict)
    for m in ("TSAI", "PARK", "HORAUD", "ANDREFF", "SHAH"):
        assert methods[m]["dt_mm"] < 8.0
        assert methods[m]["dr_deg"] < 1.0
    assert s["solve_s"] > 0.0                          # type: ignore[operator]  # timed: docs, not here


def test_camera_with_vicon(capsys: pytest.CaptureFixture[str]) -> None:
    """A camera tracked by Vicon (hand = the Vicon body on the camera): the camera stamps are
    ~23 ms early."""
    s = _run(_zip("prime_sense_color_w_vicon_1.zip"), capsys)
    assert s["pairs"] == 1533
    assert s["time_offset_ms"] == pytest.approx(-22.6, abs=3.0)
    assert s["residual_mm_rms"] < 15.0                 # type: ignore[operator]


def test_simulated_arm_is_refused_as_degenerate(capsys: pytest.CaptureFixture[str]) -> None:
    """The simulated recording turns the hand about (almost) one axis only: refused, exit 2."""
    p = _zip("robot_arm_w_color_camera_sim.zip")
    assert main(["rig-calibrate", "--samples", str(p), "--json"]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err.startswith(f"hil rig-calibrate: error: {p}: degenerate motion: the robot rotates "
                              "(almost) only about the axis ")
    assert cap.err.count("\n") == 1
