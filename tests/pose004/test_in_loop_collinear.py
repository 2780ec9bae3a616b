"""The seed-004 needle-axis check from collinear bead markers in the loop: the simulator draws three
bright beads on the guide tube (configs/sim_needle_collinear.toml), the controller measures the tube
axis from them in both views (seed 004 §II-A, stereo checked against the monocular estimate) against
the plan before LOCK and while locked (docs/pose004.md section 7)."""

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
from hil.controller.assembly import _needle_checker
from hil.controller.config import NeedleCheckConfig, ProcedureConfig
from hil.controller.metrics import RunSummary
from hil.controller.perception import CollinearNeedleChecker, StereoNeedleChecker
from hil.controller.plan_file import load_plan
from hil.errors import VisionError
from hil.geometry.collinear import direction_error_deg
from hil.vision.beads import detect_beads, measure_bead_axis, order_along
from hil.vision.camera_model import StereoCalibration
from hil.vision.render import RenderOptions
from hil.vision.render_instrument import Instrument3D, render_instrument_stereo

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "sim_needle_collinear.toml"
PLAN = ROOT / "configs" / "plans" / "sim_needle_collinear_plan.json"
CAL = StereoCalibration.synthetic()
POSITIONS = (20.0, 50.0, 80.0)


def _events(summary: RunSummary) -> list[dict[str, Any]]:
    return [json.loads(line) for line in Path(summary.session_log).read_text().splitlines()]


def _run(tmp_path: Path, setup: SetupConfig, max_duration_s: float | None = None) -> RunSummary:
    return run_procedure(CONFIG, setup, load_plan(PLAN), auto=True, session_dir=tmp_path,
                         max_duration_s=max_duration_s)


def _misaligned(setup: SetupConfig, angle_deg: float, timeout_s: float) -> SetupConfig:
    """The guide as actually mounted is tilted by ``angle_deg`` about the flange x axis; the
    controller still believes ``[frames] T_flange_from_guide``."""
    believed = setup.frames.T_flange_from_guide
    assert believed.translation_mm is not None
    true_guide = TransformConfig(translation_mm=believed.translation_mm,
                                 rotvec_rad=(math.radians(angle_deg), 0.0, 0.0))
    camera = setup.camera.model_copy(update={"T_flange_from_needle_guide": true_guide})
    proc = setup.procedure.model_dump()
    proc["compensation"]["timeout_s"] = timeout_s
    return setup.model_copy(update={"camera": camera, "procedure": ProcedureConfig.model_validate(proc)})


# ------------------------------------------------------------------ the detector on its own
@pytest.fixture(scope="module")
def beaded() -> tuple[Instrument3D, Any]:
    tip = np.array([20.0, 10.0, 600.0])
    d = np.array([0.5, -0.3, -0.6])
    inst = Instrument3D.needle_with_beads(tip, d, 100.0, radius_mm=2.0, marker_positions_mm=POSITIONS,
                                          bead_radius_mm=2.5)
    return inst, render_instrument_stereo(CAL, inst, RenderOptions(), np.random.default_rng(3))


def test_beads_are_found_ordered_and_give_the_axis(beaded: tuple[Instrument3D, Any]) -> None:
    inst, r = beaded
    for img, tr in ((r.left, r.truth_left), (r.right, r.truth_right)):
        box = np.vstack([tr.tip_px, tr.hub_px])
        roi = (int(box[:, 0].min()) - 30, int(box[:, 1].min()) - 30,
               int(box[:, 0].max()) + 30, int(box[:, 1].max()) + 30)
        got = order_along(detect_beads(img, roi, 3), tr.tip_px, tr.hub_px)
        np.testing.assert_allclose(got, tr.marker_px, atol=0.3)
    d = inst.axis.direction
    hub_side, tip_side = inst.tip_mm + 110.0 * d, inst.tip_mm + 10.0 * d
    target = inst.tip_mm - 80.0 * d  # the planned path continues beyond the tip
    m = measure_bead_axis(CAL, r.left, r.right, hub_side, tip_side, inst.tip_mm, target, POSITIONS)
    assert direction_error_deg(m.stereo.direction, d) < 0.3
    assert m.path_error.direction_error_deg < 0.3  # oriented: the axis is turned towards the target
    assert m.path_error.entry_offset_mm < 0.3
    assert m.agreement.angle_deg < 5.0
    # the same beads against the reversed path: an oriented error of ~180 deg
    rev = measure_bead_axis(CAL, r.left, r.right, hub_side, tip_side, target, inst.tip_mm, POSITIONS)
    assert rev.path_error.direction_error_deg > 179.0
    with pytest.raises(VisionError, match="monocular and stereo"):
        measure_bead_axis(CAL, r.left, r.right, hub_side, tip_side, inst.tip_mm, target, POSITIONS,
                          max_mono_stereo_deg=1e-6)


def test_detector_errors_are_typed() -> None:
    img = np.full((100, 120), 200, np.uint8)
    img[40:44, 50:54] = 255
    with pytest.raises(VisionError, match="found 1 bright blobs, need 3"):
        detect_beads(img, (0, 0, 120, 100), 3)
    with pytest.raises(VisionError, match="empty search region"):
        detect_beads(img, (130, 0, 140, 100), 1)
    with pytest.raises(VisionError, match="2-D uint8"):
        detect_beads(img.astype(np.float32), (0, 0, 120, 100), 1)
    np.testing.assert_allclose(detect_beads(img, (0, 0, 120, 100), 1), [[51.5, 41.5]])
    with pytest.raises(VisionError, match="no length"):
        order_along(np.zeros((2, 2)), np.ones(2), np.ones(2))


# ------------------------------------------------------------------ in the loop
def test_aligned_guide_passes_the_bead_check_and_locks(tmp_path: Path) -> None:
    setup = load_setup(CONFIG)
    nc = setup.procedure.lock.needle_check
    assert nc is not None
    assert nc.method == "collinear"
    assert setup.camera.needle_bead_count == 3
    assert isinstance(_needle_checker(setup, None), CollinearNeedleChecker)
    s = _run(tmp_path, setup)
    assert s.final_state == "done"
    assert "lock" in s.states
    assert s.needle_direction_error_deg is not None
    assert s.needle_direction_error_deg < 1.0
    ev = _events(s)
    measured = [e for e in ev if e["event"] == "needle_axis_measured"]
    locked = [e for e in measured if e["state"] == "lock"]
    assert locked, "the needle axis is measured while locked"
    assert all(e["within"] for e in locked)
    assert max(e["direction_error_deg"] for e in locked) < 1.0
    assert max(e["entry_offset_mm"] for e in locked) < 1.5
    assert not [e for e in ev if e["event"] in ("needle_axis_alarm", "needle_axis_unavailable")]
    i_lock = next(i for i, e in enumerate(ev) if e["event"] == "state_entered" and e["state"] == "lock")
    before = [e for e in ev[:i_lock] if e["event"] == "needle_axis_measured"]
    assert before
    assert before[-1]["within"]
    assert before[-1]["state"] == "compensate"


@pytest.mark.parametrize("roi_tracking", [True, False], ids=["roi-tracking", "full-frame"])
def test_locked_needle_check_reads_the_true_guide_error_in_both_locator_modes(
    tmp_path: Path, roi_tracking: bool
) -> None:
    """Regression (issue 17): with ROI tracking this run tripped the needle alarm while locked
    (target 2.04 mm off) although the simulator's truth had the guide 0.05-0.14 mm off the plan.
    The locator was not the cause (its centres equal full-frame ones within 0.012 px on the same
    images); the bead check read 0.06-2.26 mm frame to frame in both modes, from 0.07 px noise
    on its bead centres (hil.vision.beads). Now, in either mode, the guide is truly within the
    lock tolerance of the plan while locked (0.14 mm with a moveL approach, 0.33-0.36 mm since the
    servo-streamed approach settles before its check: LOCK now begins at another instant of the
    compensation's noise) and the check's reading stays well inside its 2 mm limit."""
    setup = load_setup(CONFIG)
    proc = setup.procedure.model_dump()
    proc["vision"]["roi_tracking"] = roi_tracking
    s = _run(tmp_path, setup.model_copy(update={"procedure": ProcedureConfig.model_validate(proc)}))
    assert s.final_state == "done"
    ev = _events(s)
    locked = [e for e in ev if e["event"] == "needle_axis_measured" and e["state"] == "lock"]
    truth = [e for e in ev if e["event"] == "truth_error" and e["state"] == "lock"]
    assert len(locked) >= 25
    assert truth
    assert max(e["position_mm"] for e in truth) < setup.procedure.lock.tolerance_mm
    assert max(e["target_offset_mm"] for e in locked) < 1.5
    assert max(e["direction_error_deg"] for e in locked) < 0.8


def test_misaligned_guide_is_refused_before_lock(tmp_path: Path) -> None:
    """A guide mounted 4 deg off what the controller believes: the bead check refuses LOCK."""
    s = _run(tmp_path, _misaligned(load_setup(CONFIG), 4.0, timeout_s=3.0), max_duration_s=16.0)
    assert "compensate" in s.states
    assert "lock" not in s.states
    assert s.final_state != "done"
    assert s.needle_direction_error_deg == pytest.approx(4.0, abs=0.8)
    refused = [e for e in _events(s) if e["event"] == "needle_check_refused"]
    assert refused
    assert any("off the plan" in e["reason"] and e["direction_error_deg"] > 2.0 for e in refused)


def test_method_defaults_to_cylinder_and_is_validated() -> None:
    from drivers.sim.camera import SimCameraConfig

    nc = NeedleCheckConfig()
    assert nc.method == "cylinder"
    assert nc.bead_positions_mm() == (20.0, 50.0, 80.0)
    assert SimCameraConfig.model_validate({"driver": "sim"}).needle_bead_count == 0
    cyl = load_setup(ROOT / "configs" / "sim_needle.toml")
    assert isinstance(_needle_checker(cyl, None), StereoNeedleChecker)
    with pytest.raises(ValidationError):
        NeedleCheckConfig.model_validate({"method": "plucker"})
    with pytest.raises(ValidationError):
        NeedleCheckConfig.model_validate({"bead_count": 2})


def test_bundled_plan_is_the_needle_plan() -> None:
    assert json.loads(PLAN.read_text()) == json.loads(
        (ROOT / "configs" / "plans" / "sim_needle_plan.json").read_text())
