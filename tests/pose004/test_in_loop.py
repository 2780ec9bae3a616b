"""The seed-004 needle-axis check in the loop: the simulator renders the guide tube carried by the
robot (configs/sim_needle.toml), the controller measures its axis in both views (seed 004 §III)
against the plan before LOCK and while locked (docs/pose004.md section 6)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from hil.cli.cmd_run import run_procedure
from hil.config import load_setup
from hil.config.setup import SetupConfig
from hil.config.types import TransformConfig
from hil.controller.config import NeedleCheckConfig, ProcedureConfig
from hil.controller.metrics import RunSummary
from hil.controller.plan_file import load_plan

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "sim_needle.toml"
PLAN = ROOT / "configs" / "plans" / "sim_needle_plan.json"


def _events(summary: RunSummary) -> list[dict[str, Any]]:
    lines = Path(summary.session_log).read_text().splitlines()
    return [json.loads(line) for line in lines]


def _run(tmp_path: Path, setup: SetupConfig, max_duration_s: float | None = None) -> RunSummary:
    return run_procedure(CONFIG, setup, load_plan(PLAN), auto=True, session_dir=tmp_path,
                         max_duration_s=max_duration_s)


def _misaligned(setup: SetupConfig, angle_deg: float, **procedure: Any) -> SetupConfig:
    """The guide as actually mounted is tilted by ``angle_deg`` about the flange x axis; the
    controller still believes ``[frames] T_flange_from_guide`` (the untilted one)."""
    believed = setup.frames.T_flange_from_guide
    assert believed.translation_mm is not None
    true_guide = TransformConfig(translation_mm=believed.translation_mm,
                                 rotvec_rad=(math.radians(angle_deg), 0.0, 0.0))
    camera = setup.camera.model_copy(update={"T_flange_from_needle_guide": true_guide})
    proc = setup.procedure.model_dump()
    for dotted, value in procedure.items():
        section, key = dotted.split("__")
        if section == "needle_check":
            proc["lock"]["needle_check"][key] = value
        else:
            proc[section][key] = value
    return setup.model_copy(update={"camera": camera, "procedure": ProcedureConfig.model_validate(proc)})


def test_aligned_guide_passes_the_check_and_locks(tmp_path: Path) -> None:
    setup = load_setup(CONFIG)
    assert setup.camera.render_needle
    assert setup.procedure.lock.needle_check is not None
    s = _run(tmp_path, setup)
    assert s.final_state == "done"
    assert "lock" in s.states
    assert s.needle_direction_error_deg is not None
    assert s.needle_direction_error_deg < 0.5
    assert s.lock_direction_error_deg is not None
    assert s.lock_direction_error_deg < 0.5
    ev = _events(s)
    locked = [e for e in ev if e["event"] == "needle_axis_measured" and e["state"] == "lock"]
    assert locked, "the needle axis is measured while locked"
    assert all(e["within"] for e in locked)
    assert max(e["direction_error_deg"] for e in locked) < 1.0
    assert max(e["entry_offset_mm"] for e in locked) < 1.0
    assert not [e for e in ev if e["event"] == "needle_axis_alarm"]
    # LOCK was entered only after a passing measurement in COMPENSATE
    i_lock = next(i for i, e in enumerate(ev) if e["event"] == "state_entered" and e["state"] == "lock")
    before = [e for e in ev[:i_lock] if e["event"] == "needle_axis_measured"]
    assert before
    assert before[-1]["within"]
    assert before[-1]["state"] == "compensate"
    assert json.loads(json.dumps(s.to_dict(), default=str))["needle_direction_error_deg"] == pytest.approx(
        s.needle_direction_error_deg)


def test_misaligned_guide_is_refused_before_lock(tmp_path: Path) -> None:
    """A guide mounted 4 deg off what the controller believes: the robot aligns the believed guide
    (the flange markers cannot see the tilt), the optical check refuses LOCK with the reason."""
    setup = _misaligned(load_setup(CONFIG), 4.0, compensation__timeout_s=3.0)
    s = _run(tmp_path, setup, max_duration_s=16.0)
    assert "compensate" in s.states
    assert "lock" not in s.states
    assert s.final_state != "done"
    assert s.needle_direction_error_deg == pytest.approx(4.0, abs=0.6)
    ev = _events(s)
    refused = [e for e in ev if e["event"] == "needle_check_refused"]
    assert refused
    assert any("off the plan" in e["reason"] and e["direction_error_deg"] > 2.0 for e in refused)
    assert any(e["event"] == "transition_applied" and e["input"] == "timed_out" for e in ev)


def test_misaligned_guide_raises_the_alarm_while_locked(tmp_path: Path) -> None:
    """Without the check before LOCK, the alarm while locked catches the tilted guide and the
    drift policy (retract) backs the guide off."""
    setup = _misaligned(load_setup(CONFIG), 4.0, needle_check__required_before_lock=False)
    assert setup.procedure.lock.on_drift == "retract"
    s = _run(tmp_path, setup, max_duration_s=20.0)
    assert "lock" in s.states
    assert "retract" in s.states
    ev = _events(s)
    alarms = [e for e in ev if e["event"] == "needle_axis_alarm"]
    assert len(alarms) == 1
    assert alarms[0]["direction_error_deg"] == pytest.approx(4.0, abs=0.6)
    assert alarms[0]["policy"] == "retract"
    assert s.needle_direction_error_deg == pytest.approx(4.0, abs=0.6)
    retract = next(r for r in s.timeline if r["state"] == "retract")
    assert "needle axis" in retract["reason"]


def test_bundled_plan_matches_the_needle_phantom() -> None:
    from drivers.sim.world import phantom_from_config

    setup = load_setup(CONFIG)
    plan = json.loads(PLAN.read_text())
    ph = phantom_from_config(setup.simulation.patient)
    np.testing.assert_allclose(plan["fiducials_mm"], ph.markers_mm, atol=1e-4)
    np.testing.assert_allclose(plan["entry_mm"], ph.entry_mm, atol=1e-4)
    np.testing.assert_allclose(plan["target_mm"], ph.target_mm, atol=1e-4)


def test_needle_check_is_off_by_default_and_validated() -> None:
    from drivers.sim.camera import SimCameraConfig

    assert ProcedureConfig().lock.needle_check is None
    cam = SimCameraConfig.model_validate({"driver": "sim"})
    assert not cam.render_needle
    assert cam.T_flange_from_needle_guide is None
    with pytest.raises(ValidationError, match="visible_to_mm"):
        NeedleCheckConfig(visible_from_mm=50.0, visible_to_mm=40.0)
    with pytest.raises(ValidationError):
        ProcedureConfig.model_validate({"lock": {"needle_check": {"max_direction_deg": 0}}})
