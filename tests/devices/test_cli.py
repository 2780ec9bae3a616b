"""``hil drivers`` and ``hil check-config``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.cli import main
from tests.devices.conftest import CONFIGS


def test_drivers_json_lists_every_driver_with_fields(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["drivers", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    by_key = {(d["kind"], d["name"]): d for d in out["drivers"]}
    assert {("camera", "sim"), ("robot", "sim"), ("tracker", "sim")} <= set(by_key)
    robot = by_key[("robot", "sim")]
    assert robot["origin"] == "builtin"
    assert robot["simulated"] is True
    fields = {f["name"]: f for f in robot["fields"]}
    assert fields["control_rate_hz"] == {"name": "control_rate_hz", "type": "float", "required": False,
                                         "default": 125.0, "description": "CB3: 125, e-Series: 500"}
    assert fields["driver"]["required"] is True
    assert "builtin" in out["plugins"]
    for u in out["unavailable"]:
        assert u["reason"]


def test_drivers_text(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["drivers"]) == 0
    text = capsys.readouterr().out
    assert "robot    sim              (builtin, simulated)" in text
    assert "    servo_time_constant_s: float = default 0.03  first-order servo tracking lag" in text


def test_check_config_valid_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(CONFIGS / "sim.toml"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["valid"] is True
    assert out["warnings"] == []
    assert out["setup"]["robot"]["driver"] == "sim"
    assert out["setup"]["calibration"]["stereo"] == str(CONFIGS / "calibration" / "sim_stereo.json")
    assert out["setup"]["procedure"]["lock"]["tolerance_mm"] > 0


def test_check_config_default_is_sim_toml(capsys: pytest.CaptureFixture[str],
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("HIL_SETUP", raising=False)
    assert main(["check-config", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["file"] == str(CONFIGS / "sim.toml")


def test_check_config_text_and_missing_file_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    p = tmp_path / "s.toml"
    p.write_text('[camera]\ndriver = "sim"\n[robot]\ndriver = "sim"\n[calibration]\nstereo = "nope.json"\n')
    assert main(["check-config", str(p)]) == 0
    cap = capsys.readouterr()
    assert cap.out.splitlines()[0] == f"{p}: valid"
    assert 'robot.driver = "sim"' in cap.out
    assert cap.err.strip() == (f"hil check-config: warning: {p}: calibration.stereo: file does not exist "
                               f"yet: {tmp_path / 'nope.json'}")


def test_check_config_bad_file_one_line_per_problem(
    tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    p = tmp_path / "bad.toml"
    p.write_text('[camera]\ndriver = "sim"\nfps = 3\n[robot]\ndriver = "sim"\nspeed = 1\n')
    assert main(["check-config", str(p)]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err.splitlines() == [
        f"hil check-config: error: {p}: camera.fps: unknown key",
        f"hil check-config: error: {p}: robot.speed: unknown key",
    ]
