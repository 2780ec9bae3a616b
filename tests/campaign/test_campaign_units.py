"""Campaign building blocks: scenario selection, fault placement, the recovering operator and the
driver-boundary recorder (no simulation: fast)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from drivers.interfaces.errors import LimitViolationError
from drivers.interfaces.robot import MotionLimits, Robot, RobotMode, RobotState, SafetyStatus
from hil.campaign.operator import CampaignOperator
from hil.campaign.recorder import RecordingRobot
from hil.campaign.report import summarise, table
from hil.campaign.scenarios import TARGET_STATES, ScenarioSelectionError, all_scenarios, place_fault, select
from hil.cli import main
from hil.clock import ManualClock
from hil.config.faults import FaultKind
from hil.controller.fsm import Event, State
from hil.controller.operator_input import OperatorView
from hil.geometry.transform import RigidTransform


def test_matrix_is_every_kind_times_every_target_state() -> None:
    names = [s.name for s in all_scenarios()]
    assert len(names) == len(FaultKind) * len(TARGET_STATES) == 90
    patient = {"cough@compensate", "marker_lost@gate", "patient_shift@lock", "marker_moved@register"}
    assert patient <= set(names)
    assert {"frame_drop@compensate", "motion_lag@lock"} <= set(names)


@pytest.mark.parametrize(
    ("patterns", "expected"),
    [
        (["frame_drop@compensate"], ["frame_drop@compensate"]),
        (["robot_disconnect"], [f"robot_disconnect@{s}" for s in TARGET_STATES]),
        (["@lock"], [f"{k.value}@lock" for k in FaultKind]),
        (["*_stop@gate", "glare@g*"], ["protective_stop@gate", "glare@gate"]),
    ],
)
def test_select(patterns: list[str], expected: list[str]) -> None:
    assert [s.name for s in select(patterns)] == expected


def test_select_unknown_names_the_pattern_and_choices() -> None:
    with pytest.raises(ScenarioSelectionError, match=r"'nosuch@lock' matches nothing .*kinds: frame_drop"):
        select(["nosuch@lock"])


def test_cli_reports_a_bad_scenario_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["campaign", "nosuch"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("hil campaign: error: scenario 'nosuch' matches nothing")


@pytest.mark.parametrize(
    ("window", "expected"), [((2.0, 4.0), 2.3), ((6.23, 6.686), 6.3668), ((5.0, 5.0), 5.0), (None, None)]
)
def test_place_fault(window: tuple[float, float] | None, expected: float | None) -> None:
    assert place_fault(window, 0.6) == expected


def _view(state: State, t_s: float, pending: str | None = None) -> OperatorView:
    return OperatorView(state, pending, "", t_s, True)


def test_operator_waits_for_the_fault_to_end_then_resumes_then_restarts() -> None:
    op = CampaignOperator(recover_after_s=5.0, max_recoveries=2)
    assert op.poll(_view(State.IDLE, 0.0)) is Event.START_REQUESTED
    assert op.poll(_view(State.APPROACH, 1.0, pending="plan_to_approach")) is Event.CONFIRM_REQUESTED
    assert op.poll(_view(State.FAULT, 4.0)) is None
    assert not op.finished(_view(State.FAULT, 4.0))
    assert op.poll(_view(State.FAULT, 5.0)) is Event.RESUME_REQUESTED
    # resume rejected (no plan yet): reset, then start again from idle
    assert op.poll(_view(State.FAULT, 5.1)) is Event.RESET_REQUESTED
    assert op.poll(_view(State.IDLE, 5.2)) is Event.START_REQUESTED
    assert op.recoveries_left == 0
    assert op.finished(_view(State.FAULT, 9.0))
    assert op.finished(_view(State.DONE, 9.0))


def test_operator_resumes_a_pause_once_then_re_registers() -> None:
    """A body that still does not match after resuming (a marker slid, the patient moved) pauses
    again: the second answer is a re-registration (START from PAUSED), as an operator would."""
    op = CampaignOperator(recover_after_s=1.0, max_recoveries=3)
    op.poll(_view(State.IDLE, 0.0))
    assert op.poll(_view(State.PAUSED, 2.0)) is Event.RESUME_REQUESTED
    assert op.poll(_view(State.APPROACH, 2.1)) is None
    assert op.poll(_view(State.PAUSED, 3.0)) is Event.START_REQUESTED
    assert op.poll(_view(State.REGISTER, 3.1)) is None
    assert op.poll(_view(State.FAULT, 4.0)) is Event.RESUME_REQUESTED   # a fault is still resumed
    assert op.recoveries_left == 0
    # a pause after resuming from a safe stop (drift while locked, then the patient found moved)
    op2 = CampaignOperator(recover_after_s=1.0, max_recoveries=2)
    op2.poll(_view(State.IDLE, 0.0))
    assert op2.poll(_view(State.SAFE_STOP, 2.0)) is Event.RESUME_REQUESTED
    assert op2.poll(_view(State.GATE, 2.1)) is None
    assert op2.poll(_view(State.PAUSED, 3.0)) is Event.START_REQUESTED


def test_operator_without_recoveries_ends_at_the_first_halt() -> None:
    op = CampaignOperator(recover_after_s=0.0, max_recoveries=0)
    op.poll(_view(State.IDLE, 0.0))
    assert op.poll(_view(State.FAULT, 1.0)) is None
    assert op.finished(_view(State.FAULT, 1.0))


class _PermissiveRobot(Robot):
    """Accepts anything (its own limits are huge): what a buggy driver would do."""

    def __init__(self) -> None:
        super().__init__("robot", MotionLimits((-1e9,) * 3, (1e9,) * 3, 1e9, 1e9, 1e9),
                         T_flange_from_tcp=RigidTransform.identity())
        self.clock = ManualClock()
        self.sent: list[str] = []

    @property
    def control_rate_hz(self) -> float:
        return 125.0

    def _open(self) -> None: ...

    def _close(self) -> None: ...

    def _move_linear(self, T: RigidTransform, speed: float, accel: float, blocking: bool) -> None:
        self.sent.append("move_linear")

    def _servo(self, T: RigidTransform, period_s: float) -> None:
        self.sent.append("servo")

    def _stop(self, decel: float) -> None:
        self.sent.append("stop")

    def _state_now(self) -> RobotState:
        return RobotState(
            t_ns=self.clock.now_ns(),
            q_rad=np.zeros(6),
            T_robot_from_tcp=RigidTransform.identity(),
            tcp_speed_mm_s=0.0,
            mode=RobotMode.IDLE,
            safety=SafetyStatus.NORMAL,
        )


def test_recorder_counts_violations_that_reached_the_driver() -> None:
    inner = _PermissiveRobot()
    strict = MotionLimits((-100.0,) * 3, (100.0,) * 3, 50.0, 200.0, 1.0)
    rec = RecordingRobot(inner, strict, inner.clock)
    rec.open()
    rec.state_now()
    rec.move_linear(RigidTransform(np.eye(3), np.array([10.0, 0, 0])), 20.0, 100.0, blocking=False)
    rec.move_linear(RigidTransform(np.eye(3), np.array([500.0, 0, 0])), 20.0, 100.0, blocking=False)
    rec.move_linear(RigidTransform(np.eye(3), np.array([0.0, 0, 0])), 80.0, 100.0, blocking=False)
    rec.servo(RigidTransform(np.eye(3), np.array([0.0, 0, 0.1])), 0.008)  # 12.5 mm/s from rest: accel!
    rec.stop()
    assert inner.sent == ["move_linear"] * 3 + ["servo", "stop"]
    bad = rec.recording.violations_reached()
    assert [c.kind for c in bad] == ["move_linear", "move_linear", "servo"]
    assert "workspace" in bad[0].violations[0]
    assert "speed" in bad[1].violations[0]
    assert "acceleration" in bad[2].violations[0]


def test_recorder_does_not_count_what_the_driver_refused() -> None:
    inner = _PermissiveRobot()
    inner.limits = MotionLimits((-100.0,) * 3, (100.0,) * 3, 50.0, 200.0, 1.0)
    rec = RecordingRobot(inner, inner.limits, inner.clock)
    rec.open()
    with pytest.raises(LimitViolationError):
        rec.move_linear(RigidTransform(np.eye(3), np.array([500.0, 0, 0])), 20.0, 100.0, blocking=False)
    assert inner.sent == []
    assert rec.recording.commands[0].violations
    assert not rec.recording.commands[0].reached_driver
    assert rec.recording.violations_reached() == []


def test_summary_and_table() -> None:
    results: list[dict[str, Any]] = [
        {
            "run_id": "baseline_s1",
            "scenario": "baseline",
            "kind": None,
            "state": None,
            "seed": 1,
            "passed": True,
            "outcome": "baseline",
        },
        {
            "run_id": "a",
            "scenario": "frame_drop@lock",
            "kind": "frame_drop",
            "state": "lock",
            "seed": 1,
            "passed": True,
            "outcome": "safe_state",
            "safe_latency_ms": 300.0,
            "stop_latency_ms": 10.0,
        },
        {
            "run_id": "b",
            "scenario": "frame_drop@lock",
            "kind": "frame_drop",
            "state": "lock",
            "seed": 2,
            "passed": False,
            "outcome": "safe_state",
            "safe_latency_ms": 900.0,
            "reasons": ["late"],
        },
        {
            "run_id": "c",
            "scenario": "glare@gate",
            "kind": "glare",
            "state": "gate",
            "seed": 1,
            "passed": True,
            "outcome": "tolerated",
        },
    ]
    s = summarise(results, config="configs/sim.toml")
    assert (s["runs"], s["passed"], s["failed"], s["worst_safe_latency_ms"]) == (4, 3, 1, 900.0)
    assert s["failing"][0]["replay"] == "hil campaign frame_drop@lock --seed 2 --config configs/sim.toml"
    t = table(results).splitlines()
    assert t[0].split() == ["fault", "\\", "state", "gate", "lock"]
    assert t[1].split() == ["frame_drop", "-", "FAIL", "1/2", "900ms"]
    assert t[2].split() == ["glare", "pass", "-"]


def test_a_tolerated_run_shows_its_following_error_peak_beside_the_bound() -> None:
    from hil.campaign.runner import following_figures, following_note

    records = [{"event": "servo_following_bounds", "bound_mm": 2.0, "lag_ms": 30.0},
               {"event": "servo_stats", "following_peak_mm": 0.0},
               {"event": "servo_stats", "following_peak_mm": 0.47},
               {"event": "servo_stats", "following_peak_mm": 0.47},
               {"event": "frame_measured"}]
    assert following_figures(records) == (0.47, 2.0)
    assert following_figures([{"event": "frame_measured"}]) == (None, None)
    tolerated = {"outcome": "tolerated", "following_peak_mm": 0.47, "following_bound_mm": 2.0}
    assert following_note(tolerated) == " (following error peak 0.47 mm, bound 2 mm)"
    assert following_note({**tolerated, "outcome": "safe_state"}) == ""
    assert following_note({**tolerated, "following_peak_mm": None}) == ""


def test_state_path_names_where_a_run_went_and_why_it_stopped(tmp_path: Any) -> None:
    """A transport run whose fault was never sent says where the procedure went instead."""
    from hil.campaign.runner import state_path
    from hil.session.log import SessionLog

    clock = ManualClock(5 * 10**9)
    log = SessionLog(tmp_path / "s.jsonl", clock)
    steps = [(0.5, "register", "operator"), (2.75, "plan", "FRE 0.02 mm"), (0.125, "approach", "reachable"),
             (1.0, "fault", "tracker: no data for 0.3 s")]
    for dt_s, state, reason in steps:
        clock.advance(dt_s)
        log.write("state_entered", state=state, reason=reason, transition="x")
    log.close()
    assert state_path(tmp_path / "s.jsonl") == (
        "register 0.50 s, plan 3.25 s, approach 3.38 s, fault 4.38 s (tracker: no data for 0.3 s)")
    assert state_path(tmp_path / "s.jsonl", limit=2) == "register 0.50 s, plan 3.25 s, ... 2 more"
    assert state_path(tmp_path / "missing.jsonl").startswith("session log unreadable: ")
