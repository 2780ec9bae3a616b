"""The camera cross-check (hil/controller/crosscheck.py): a camera bumped while the arm compensates
makes the patient appear to move, and the compensation would chase it; the camera-measured TCP no
longer agrees with the robot's report, and the controller faults with the figures instead of
guiding on that data. A clean run stays far inside the bound."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import hil.controller.assembly as assembly
from drivers.interfaces.camera import StereoFrame
from hil.config import load_setup
from hil.controller.located import LocatedMarkers
from hil.controller.perception import StereoMarkerLocator
from hil.controller.plan_file import load_plan

CONFIG = Path("configs/sim.toml")
PLAN = load_plan("configs/plans/sim_plan.json")
BUMP_MM = np.array([0.0, 3.0, 0.0])


def _run(tmp_path: Path) -> Any:
    from hil.cli.cmd_run import run_procedure

    return run_procedure(CONFIG, load_setup(CONFIG), PLAN, auto=True, session_dir=tmp_path,
                         max_duration_s=40.0)


@pytest.mark.slow
def test_a_camera_bumped_during_compensation_faults_on_the_cross_check(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    clean = _run(tmp_path / "clean")
    assert clean.final_state == "done"
    records = [json.loads(x) for x in Path(clean.session_log).read_text().splitlines()]
    seen = [r["camera_discrepancy_mm"] for r in records
            if r["event"] == "frame_measured" and r.get("camera_discrepancy_mm") is not None]
    assert seen
    assert max(seen) < 0.5   # the bound is 2 mm
    t_comp_s = next(row["t_s"] for row in clean.timeline if row["state"] == "compensate")
    t0_ns = next(r["t_ns"] for r in records if r["event"] == "session_started")
    bump_from_ns = t0_ns + round((t_comp_s + 0.2) * 1e9)

    class BumpedCamera(StereoMarkerLocator):
        """Everything the camera sees moves by BUMP_MM from ``bump_from_ns`` on: the camera moved."""

        def locate_pair(self, frame: StereoFrame) -> LocatedMarkers:
            found = super().locate_pair(frame)
            if frame.left.t_ns < bump_from_ns:
                return found
            return LocatedMarkers.of(frame, np.asarray(found.points_mm) + BUMP_MM)

    monkeypatch.setattr(assembly, "StereoMarkerLocator", BumpedCamera)
    s = _run(tmp_path / "bumped")
    assert s.final_state == "fault", s.timeline
    assert len(s.faults) == 1
    reason = s.faults[0]
    assert reason.startswith("camera cross-check: the TCP the camera measures is ")
    assert "bound 2 mm / 2 deg for 300 ms" in reason
    err_mm = float(reason.split(" is ")[1].split(" mm")[0])
    assert 2.0 < err_mm < 3.5
    faulted = next(r for r in [json.loads(x) for x in Path(s.session_log).read_text().splitlines()]
                   if r["event"] == "fault_detected")
    assert faulted["state"] in ("compensate", "gate")
    assert (faulted["t_ns"] - bump_from_ns) * 1e-9 < 1.0   # 300 ms held, at the camera rate
