"""The frame path of a tick (hil/controller/controller.py): in COMPENSATE a pair's setpoint is
published as soon as its markers are in the estimate, before the camera cross-check, the frame's
record and the phase's judgement, exactly once per pair; the tracker is read after it unless a
reference sensor takes part in the markers, and its watchdog is still judged in that tick; and the
camera-measured TCP pose (a Horn registration of the flange markers) is computed once per flange
set however many parts of the tick ask for it; the flange markers are brought in after the setpoint
unless its bias correction needs them first."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import pytest

import hil.controller.estimate as estimate_mod
from drivers.sim.tracker import SimTracker
from hil.config import load_setup
from hil.controller.config import TrackingConfig
from hil.controller.crosscheck import CameraCrossCheck
from hil.controller.markers import MarkerTracker
from hil.controller.phases.compensate import CompensatePhase
from hil.controller.plan_file import load_plan
from hil.session.log import SessionLog

CONFIG = Path("configs/sim.toml")
PLAN = load_plan("configs/plans/sim_plan.json")


def _spy_order(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, int]]:
    """Records, in order, each setpoint published (pair seq), each tracker read (-1) and each
    cross-check (pair seq)."""
    order: list[tuple[str, int]] = []
    publish, check, latest = CompensatePhase._publish, CameraCrossCheck.check, SimTracker.latest

    def publish_spy(self: CompensatePhase, frame: Any, now_ns: int, st: Any) -> Any:
        order.append(("publish", frame.left.seq))
        return publish(self, frame, now_ns, st)

    def check_spy(self: CameraCrossCheck, est: Any, frame: Any, state: Any) -> Any:
        order.append(("crosscheck", frame.left.seq))
        return check(self, est, frame, state)

    def latest_spy(self: SimTracker) -> Any:
        order.append(("tracker", -1))
        return latest(self)

    monkeypatch.setattr(CompensatePhase, "_publish", publish_spy)
    monkeypatch.setattr(CameraCrossCheck, "check", check_spy)
    monkeypatch.setattr(SimTracker, "latest", latest_spy)
    return order


def test_a_pairs_setpoint_is_published_once_and_before_its_cross_check_and_record(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.cli.cmd_run import run_procedure

    order = _spy_order(monkeypatch)
    horn_calls: list[int] = []
    updates: list[int] = []
    write, update, horn = SessionLog.write, MarkerTracker.update_flange, estimate_mod.register_horn

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

    monkeypatch.setattr(SessionLog, "write", write_spy)
    monkeypatch.setattr(MarkerTracker, "update_flange", update_spy)
    monkeypatch.setattr(estimate_mod, "register_horn", horn_spy)
    s = run_procedure(CONFIG, load_setup(CONFIG), PLAN, auto=True, session_dir=tmp_path, max_duration_s=40.0)
    assert s.final_state == "done"
    published = [seq for what, seq in order if what == "publish"]
    assert len(published) >= 5
    assert len(published) == len(set(published))   # once per pair
    for seq in published:
        assert order.index(("publish", seq)) < order.index(("crosscheck", seq)) < order.index(("record", seq))
    # the flange set is registered at most once per flange update (cross-check, bias, guide error
    # and the snapshots share it)
    assert 0 < len(horn_calls) <= len(updates)


def test_the_flange_markers_follow_the_setpoint_unless_its_bias_correction_needs_them(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.cli.cmd_run import run_procedure

    order = _spy_order(monkeypatch)
    flange, bias = MarkerTracker.update_flange, estimate_mod.Estimate.bias_measurement

    def flange_spy(self: MarkerTracker, est: Any, points_mm: Any) -> None:
        order.append(("flange", est.last_frame.left.seq))
        flange(self, est, points_mm)

    def bias_spy(self: Any, frame: Any) -> Any:
        order.append(("bias", frame.left.seq))
        return bias(self, frame)

    monkeypatch.setattr(MarkerTracker, "update_flange", flange_spy)
    monkeypatch.setattr(estimate_mod.Estimate, "bias_measurement", bias_spy)
    s = run_procedure(CONFIG, load_setup(CONFIG), PLAN, auto=True, session_dir=tmp_path, max_duration_s=40.0)
    assert s.final_state == "done"
    published = [seq for what, seq in order if what == "publish"]
    with_bias = [seq for seq in published if ("bias", seq) in order
                 and order.index(("bias", seq)) < order.index(("publish", seq))]
    assert with_bias, "no pair's setpoint carried a bias correction: the test would prove nothing"
    assert len(with_bias) < len(published), "every setpoint carried a bias correction"
    for seq in published:
        assert order.count(("flange", seq)) == 1   # once per pair
        if seq in with_bias:
            assert order.index(("flange", seq)) < order.index(("bias", seq)) < order.index(("publish", seq))
        else:
            at = order.index(("flange", seq))
            assert order.index(("publish", seq)) < at < order.index(("crosscheck", seq))


def _reads_between(order: list[tuple[str, int]], a: tuple[str, int], b: tuple[str, int]) -> int:
    return sum(1 for what, _ in order[order.index(a) + 1:order.index(b)] if what == "tracker")


def test_the_tracker_is_read_after_the_setpoint_when_no_sample_feeds_the_markers(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.cli.cmd_run import run_procedure

    order = _spy_order(monkeypatch)
    setup = load_setup(CONFIG)
    assert setup.procedure.tracking.reference_sensor is None
    s = run_procedure(CONFIG, setup, PLAN, auto=True, session_dir=tmp_path, max_duration_s=40.0)
    assert s.final_state == "done"
    published = [seq for what, seq in order if what == "publish"]
    assert len(published) >= 5
    for seq in published:   # once, between the pair's setpoint and its cross-check
        assert _reads_between(order, ("publish", seq), ("crosscheck", seq)) == 1


def test_a_reference_sensor_is_read_before_the_markers_it_backs_up(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.cli.cmd_run import run_procedure

    order = _spy_order(monkeypatch)
    base = load_setup(CONFIG)
    tracking = TrackingConfig(reference_sensor="reference")
    setup = base.model_copy(update={"procedure": base.procedure.model_copy(update={"tracking": tracking})})
    s = run_procedure(CONFIG, setup, PLAN, auto=True, session_dir=tmp_path, max_duration_s=40.0)
    assert s.final_state == "done"
    published = [seq for what, seq in order if what == "publish"]
    assert len(published) >= 5
    for prev, seq in itertools.pairwise(published):
        assert _reads_between(order, ("publish", seq), ("crosscheck", seq)) == 0
        assert _reads_between(order, ("crosscheck", prev), ("publish", seq)) >= 1


def test_a_tracker_gone_stale_faults_on_its_watchdog_after_the_deferred_read(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """From the first setpoint on the tracker repeats its last samples (their stamps stop): the
    watchdog judged after the deferred read faults within its bound and a pair."""
    from hil.cli.cmd_run import run_procedure

    order = _spy_order(monkeypatch)
    latest = SimTracker.latest   # the spy
    frozen: dict[str, Any] = {}

    def freezing(self: SimTracker) -> Any:
        got = latest(self)
        if not any(what == "publish" for what, _ in order):
            return got
        if not frozen:
            frozen.update(got)
        return dict(frozen)

    monkeypatch.setattr(SimTracker, "latest", freezing)
    setup = load_setup(CONFIG)
    s = run_procedure(CONFIG, setup, PLAN, auto=True, session_dir=tmp_path, max_duration_s=40.0)
    assert s.final_state == "fault", s.timeline
    assert len(s.faults) == 1
    assert s.faults[0].startswith("watchdog: tracker data"), s.faults
    age_s = float(s.faults[0].split()[3])
    bound_s = setup.safety.tracker_max_age_ms * 1e-3
    assert bound_s < age_s <= bound_s + 2 / 15.0   # within two camera periods of the bound
