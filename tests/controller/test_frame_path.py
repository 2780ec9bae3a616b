"""The frame path of a tick (hil/controller/controller.py): in COMPENSATE a pair's setpoint is
published as soon as its markers are in the estimate, before the camera cross-check, the frame's
record and the phase's judgement, exactly once per pair; and the camera-measured TCP pose (a Horn
registration of the flange markers) is computed once per flange set however many parts of the
tick ask for it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import hil.controller.estimate as estimate_mod
from hil.config import load_setup
from hil.controller.crosscheck import CameraCrossCheck
from hil.controller.markers import MarkerTracker
from hil.controller.phases.compensate import CompensatePhase
from hil.controller.plan_file import load_plan
from hil.session.log import SessionLog

CONFIG = Path("configs/sim.toml")
PLAN = load_plan("configs/plans/sim_plan.json")


def test_a_pairs_setpoint_is_published_once_and_before_its_cross_check_and_record(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.cli.cmd_run import run_procedure

    order: list[tuple[str, int]] = []
    horn_calls: list[int] = []
    updates: list[int] = []
    publish, check = CompensatePhase._publish, CameraCrossCheck.check
    write, update, horn = SessionLog.write, MarkerTracker.update, estimate_mod.register_horn

    def publish_spy(self: CompensatePhase, frame: Any, now_ns: int) -> Any:
        order.append(("publish", frame.left.seq))
        return publish(self, frame, now_ns)

    def check_spy(self: CameraCrossCheck, est: Any, frame: Any, state: Any) -> Any:
        order.append(("crosscheck", frame.left.seq))
        return check(self, est, frame, state)

    def write_spy(self: SessionLog, event: str, **fields: Any) -> Any:
        if event == "frame_measured":
            order.append(("record", fields["frame_seq"]))
        return write(self, event, **fields)

    def update_spy(self: MarkerTracker, *args: Any, **kwargs: Any) -> None:
        updates.append(1)
        update(self, *args, **kwargs)

    def horn_spy(*args: Any, **kwargs: Any) -> Any:
        horn_calls.append(1)
        return horn(*args, **kwargs)

    monkeypatch.setattr(CompensatePhase, "_publish", publish_spy)
    monkeypatch.setattr(CameraCrossCheck, "check", check_spy)
    monkeypatch.setattr(SessionLog, "write", write_spy)
    monkeypatch.setattr(MarkerTracker, "update", update_spy)
    monkeypatch.setattr(estimate_mod, "register_horn", horn_spy)
    s = run_procedure(CONFIG, load_setup(CONFIG), PLAN, auto=True, session_dir=tmp_path, max_duration_s=40.0)
    assert s.final_state == "done"
    published = [seq for what, seq in order if what == "publish"]
    assert len(published) >= 5
    assert len(published) == len(set(published))   # once per pair
    for seq in published:
        assert order.index(("publish", seq)) < order.index(("crosscheck", seq)) < order.index(("record", seq))
    # the flange set is registered at most once per marker update (cross-check, bias, guide error
    # and the snapshots share it)
    assert 0 < len(horn_calls) <= len(updates)
