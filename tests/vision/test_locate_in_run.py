"""The marker locator in ``hil run`` (issue 17): ROI tracking by default, full-frame on request,
``locate_ms`` (p50, p95) in the summary and its JSON."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.cli.cmd_run import run_procedure
from hil.config import load_setup
from hil.config.setup import SetupConfig
from hil.controller.assembly import marker_locator
from hil.controller.plan_file import load_plan

CONFIG = Path("configs/sim.toml")
PLAN = load_plan("configs/plans/sim_plan.json")


def _setup(roi_tracking: bool) -> SetupConfig:
    s = load_setup(CONFIG)
    update = {"roi_tracking": roi_tracking, "reacquire_every_frames": 10}
    vision = s.procedure.vision.model_copy(update=update)
    return s.model_copy(update={"procedure": s.procedure.model_copy(update={"vision": vision})})


def test_locator_follows_the_config() -> None:
    tracking = marker_locator(_setup(True), None)
    assert tracking.tracker is not None
    assert tracking.tracker.params.reacquire_every == 10
    assert marker_locator(_setup(False), None).tracker is None


@pytest.mark.slow
@pytest.mark.parametrize("roi_tracking", [True, False])
def test_run_reports_locate_ms(roi_tracking: bool, tmp_path: Path) -> None:
    s = run_procedure(CONFIG, _setup(roi_tracking), PLAN, auto=True, session_dir=tmp_path, max_duration_s=6.0)
    assert s.frames > 0
    p50, p95 = s.locate_ms["p50"], s.locate_ms["p95"]
    assert p50 is not None
    assert p95 is not None
    assert 0.0 < p50 <= p95
    assert json.loads(json.dumps(s.to_dict(), default=str))["locate_ms"] == {"p50": p50, "p95": p95}
    assert s.fre_mm is not None  # the markers were located and registered either way
