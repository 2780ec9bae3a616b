"""A small fixed transport campaign, end to end: faults sent through the emulators' fault channels
to the REAL drivers, in real time (docs/campaign.md, "Transport tier").

Four runs, serial, ~80 s in all: an RTDE protective stop while compensating (``ur_rtde`` on
``tools/ursim``, a subprocess on a private loopback address), serial silence while compensating
(``fob`` on ``tools/trackersim``, a subprocess on a pty), and two REGISTER faults whose only
recovery is reset and start again (an e-stop pressed and released; a 1 s network outage) - the
sweep found both stuck in FAULT once. Plus the pieces that need no emulator.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import pytest

from hil.campaign.recorder import CommandRecord, Recording, StateSample
from hil.campaign.runner import RunResult
from hil.campaign.scenarios import ScenarioSelectionError
from hil.campaign.transport import (
    BY_NAME,
    FAMILIES,
    TRANSPORT_FAULTS,
    TRANSPORT_SCENARIOS,
    TransportOperator,
    _stopped_after_link_back,
    run_transport_campaign,
    select_transport,
    transport_table,
    write_setup,
)
from hil.clock import ManualClock
from hil.config import load_setup
from hil.config.faults import FaultKind
from hil.controller.fsm import Event, State
from hil.controller.operator_input import OperatorView

SCENARIOS = ["rtde_protective_stop@compensate", "serial_silence@compensate", "rtde_estop@register",
             "rtde_drop_connection@register"]


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    out = tmp_path_factory.mktemp("transport")
    summary = run_transport_campaign(select_transport(SCENARIOS), [1], out_dir=out, timeout_s=100.0)
    return summary, out


@pytest.mark.emulator
@pytest.mark.slow
def test_transport_runs_pass_every_criterion(campaign: tuple[dict[str, Any], Path]) -> None:
    summary, out = campaign
    assert summary["failing"] == []
    assert (summary["runs"], summary["passed"], summary["failed"]) == (4, 4, 0)
    assert summary["limit_violations"] == 0
    runs = {r["scenario"]: r for r in summary["results"]}
    for name in SCENARIOS:
        r = runs[name]
        assert r["state_at_onset"] == name.partition("@")[2], r
        assert r["outcome"] == "safe_state", r
        assert r["safe_state"] == "fault", r
        assert 0.0 <= r["safe_latency_ms"] <= r["latency_bound_ms"], r
        assert r["stop_latency_ms"] is not None, r
        assert r["recovered_to_lock"] is True, r
        assert r["final_state"] == "done", r
        assert r["log_ok"] is True, r
        assert r["commands"] > 0, r
    assert json.loads((out / "transport.json").read_text())["runs"] == 4
    assert "rtde_protective_stop@compensate" in (out / "transport.html").read_text()
    assert not (out / "logs").exists()  # passing runs keep no logs, emulators are gone


@pytest.mark.emulator
@pytest.mark.slow
def test_the_table_names_every_scenario(campaign: tuple[dict[str, Any], Path]) -> None:
    summary, _ = campaign
    lines = transport_table(summary["results"]).splitlines()
    assert lines[0].split() == ["fault", "\\", "state", "register", "compensate"]
    cells = [ln.split()[:3] for ln in lines[1:5]]
    assert cells[0] == ["rtde_protective_stop", "-", "pass"]
    assert [c[:2] for c in cells[1:3]] == [["rtde_estop", "pass"], ["rtde_drop_connection", "pass"]]
    assert cells[3][:3] == ["serial_silence", "-", "pass"]
    assert lines[5].startswith("bounds: robot ")


def test_the_matrix_is_every_family_in_every_state() -> None:
    names = [s.name for s in TRANSPORT_SCENARIOS]
    assert len(names) == len(set(names)) == len(TRANSPORT_FAULTS) * 5
    assert FAMILIES == ("rtde_protective_stop", "rtde_estop", "rtde_drop_connection", "rtde_pause_stream",
                        "rtde_stop_program", "rtde_slow_responses", "rtde_stall", "serial_garbage",
                        "serial_truncate", "serial_lost_phase", "serial_wrong_baud", "serial_silence",
                        "aurora_bad_crc", "aurora_tool_missing", "aurora_out_of_volume", "aurora_reset",
                        "aurora_wrong_baud", "aurora_comm_baud", "camera_stream_loss")
    assert {s.state for s in TRANSPORT_SCENARIOS} == {"register", "approach", "gate", "compensate", "lock"}
    lock = BY_NAME["rtde_estop@lock"]
    assert (lock.emulator, lock.kind, lock.inject, lock.clear, lock.delay_s) == (
        "ursim", FaultKind.PROTECTIVE_STOP, "estop", "release", 0.5)
    assert lock.family == "rtde_estop"
    assert BY_NAME["serial_silence@compensate"].delay_s == 1.5


def test_selection() -> None:
    assert [s.name for s in select_transport(["serial_silence"])] == [
        f"serial_silence@{st}" for st in ("register", "approach", "gate", "compensate", "lock")]
    assert [s.name for s in select_transport(["rtde_*@approach"])] == [
        f"{f}@approach" for f in FAMILIES if f.startswith("rtde_")]
    assert [s.name for s in select_transport(["@lock"])] == [f"{f}@lock" for f in FAMILIES]
    assert [s.name for s in select_transport(["rtde@register"])] == [
        f"{f}@register" for f in FAMILIES if f.startswith("rtde_")]
    assert [s.name for s in select_transport(["rtde_estop@lock"])] == ["rtde_estop@lock"]
    both = [s.name for s in select_transport(["serial_garbage@gate", "serial_garbage"])]
    assert both[0] == "serial_garbage@gate"  # in the order asked, without repeats
    assert len(both) == len(set(both)) == 5
    assert select_transport([]) == list(TRANSPORT_SCENARIOS)
    with pytest.raises(ScenarioSelectionError, match=r"matches nothing.*families: rtde_protective_stop"):
        select_transport(["camera_loss"])


def test_the_table_is_family_by_state() -> None:
    def res(scenario: str, passed: bool, lat: float | None) -> dict[str, Any]:
        sc = BY_NAME[scenario]
        return {"scenario": scenario, "kind": sc.kind.value, "state": sc.state, "passed": passed,
                "safe_latency_ms": lat, "latency_bound_ms": 1133.3}

    text = transport_table([res("rtde_estop@lock", True, 41.0), res("rtde_estop@gate", False, 900.0),
                            res("rtde_estop@gate", True, 60.0), res("serial_silence@lock", True, 540.4)])
    lines = text.splitlines()
    assert lines[0].split() == ["fault", "\\", "state", "gate", "lock"]
    assert lines[1].split() == ["rtde_estop", "FAIL", "1/2", "900ms", "pass", "41ms"]
    assert lines[2].split() == ["serial_silence", "-", "pass", "540ms"]
    assert lines[3] == "bounds: robot 1133 ms, tracker 1133 ms"


def test_written_setups_point_the_real_drivers_at_the_emulators(tmp_path: Path) -> None:
    rtde = select_transport(["rtde_drop_connection@compensate"])[0]
    path = write_setup(rtde, tmp_path, seed=3, ursim_host="127.123.4.5")
    setup = load_setup(path)
    raw = tomllib.loads(path.read_text())
    assert raw["robot"]["driver"] == "ur_rtde"
    assert raw["robot"]["host"] == "127.123.4.5"
    assert raw["robot"]["state_max_age_s"] == 0.5  # under the robot watchdog (1000 ms)
    assert raw["camera"]["driver"] == "sim"
    assert setup.simulation.real_time is True
    assert setup.simulation.seed == 3
    assert raw["procedure"]["confirm"] == ["plan_to_approach", "compensate_to_lock", "lock_to_done"]
    serial = select_transport(["serial_garbage"])[0]
    (tmp_path / "b").mkdir()
    raw = tomllib.loads(write_setup(serial, tmp_path / "b", seed=1, tracker_port="/dev/pts/77").read_text())
    assert raw["tracker"] == {"driver": "fob", "port": "/dev/pts/77", "baud_rate": 115200,
                              "sensors": {"reference": 0}}
    assert raw["robot"]["driver"] == "sim"
    assert raw["safety"]["tracker_max_age_ms"] == 1000.0
    # the camera is not under test here: it may fall silent as long as its age bound allows
    assert (raw["safety"]["camera_frame_max_age_ms"], raw["safety"]["camera_silence_ms"]) == (1500.0, 1500.0)
    assert setup.safety.camera_silence_ms == 1500.0


def _view(state: State, t_s: float, pending: str | None = None) -> OperatorView:
    return OperatorView(state=state, pending=pending, last_reason="", t_s=t_s, started=True)


def test_operator_fires_inside_the_state_and_holds_lock_until_recovered() -> None:
    clock = ManualClock(10_000_000_000)
    sent: list[str] = []
    op = TransportOperator("compensate", 1.5, 0.5, clock, 9_000_000_000,
                           inject=lambda: sent.append("fault"), clear=lambda: sent.append("clear"))
    assert op.poll(_view(State.IDLE, 0.0)) is Event.START_REQUESTED
    assert op.poll(_view(State.COMPENSATE, 5.0)) is None
    assert op.poll(_view(State.COMPENSATE, 6.4, pending="compensate_to_lock")) is None  # held
    assert sent == []
    op.poll(_view(State.COMPENSATE, 6.5, pending="compensate_to_lock"))
    assert sent == ["fault"]
    assert op.onset_s == pytest.approx(1.0)  # clock time since the log's start
    assert op.poll(_view(State.FAULT, 6.9)) is None
    assert sent == ["fault"]
    assert op.poll(_view(State.FAULT, 7.0)) is None  # window over: cleared, still settling
    assert sent == ["fault", "clear"]
    assert op.poll(_view(State.FAULT, 7.5)) is Event.RESUME_REQUESTED
    assert op.poll(_view(State.COMPENSATE, 9.0, pending="compensate_to_lock")) is Event.CONFIRM_REQUESTED
    assert sent == ["fault", "clear"]


def test_operator_aimed_at_lock_confirms_until_lock_then_holds_lock_to_done() -> None:
    clock = ManualClock(10_000_000_000)
    sent: list[str] = []
    op = TransportOperator("lock", 0.5, 1.0, clock, 9_000_000_000, inject=lambda: sent.append("fault"),
                           clear=None)
    assert op.poll(_view(State.IDLE, 0.0)) is Event.START_REQUESTED
    # before LOCK every confirmation is given, so the procedure reaches the target state
    assert op.poll(_view(State.PLAN, 1.0, pending="plan_to_approach")) is Event.CONFIRM_REQUESTED
    assert op.poll(_view(State.COMPENSATE, 4.0, pending="compensate_to_lock")) is Event.CONFIRM_REQUESTED
    assert op.poll(_view(State.LOCK, 5.0)) is None
    assert op.poll(_view(State.LOCK, 5.2, pending="lock_to_done")) is None  # held: fault not sent yet
    assert op.poll(_view(State.LOCK, 5.5, pending="lock_to_done")) is None  # sent now, still held
    assert sent == ["fault"]
    assert op.poll(_view(State.LOCK, 6.9, pending="lock_to_done")) is None  # window + settle not over
    assert op.poll(_view(State.LOCK, 7.0, pending="lock_to_done")) is Event.CONFIRM_REQUESTED  # tolerated


def test_operator_recovers_a_fault_before_its_target_state_as_an_operator_would() -> None:
    """Issue 45 item 3: a fault on the way to the target state (here in APPROACH, aimed at
    COMPENSATE) is recovered once the robot had the settling time to stop, so the procedure gets
    to the target state and the fault is still sent there, with its own recovery attempts
    (before: held until the fault that never came)."""
    clock = ManualClock(10_000_000_000)
    sent: list[str] = []
    op = TransportOperator("compensate", 1.5, 0.5, clock, 9_000_000_000,
                           inject=lambda: sent.append("fault"), clear=lambda: sent.append("clear"))
    assert op.poll(_view(State.IDLE, 0.0)) is Event.START_REQUESTED
    assert op.poll(_view(State.PLAN, 1.0, pending="plan_to_approach")) is Event.CONFIRM_REQUESTED
    assert op.poll(_view(State.APPROACH, 2.0)) is None
    assert op.poll(_view(State.FAULT, 3.0)) is None                       # the robot stops first
    assert op.poll(_view(State.FAULT, 3.4)) is None
    assert op.poll(_view(State.FAULT, 3.5)) is Event.RESUME_REQUESTED     # then recovered
    assert op.poll(_view(State.APPROACH, 3.6)) is None
    assert op.poll(_view(State.COMPENSATE, 5.0)) is None
    assert op.poll(_view(State.COMPENSATE, 6.4, pending="compensate_to_lock")) is None  # held
    op.poll(_view(State.COMPENSATE, 6.5, pending="compensate_to_lock"))
    assert sent == ["fault"]
    assert op.recoveries_left == TransportOperator.MAX_RECOVERIES          # the fault's own attempts
    assert op.poll(_view(State.FAULT, 6.9)) is None
    assert op.poll(_view(State.FAULT, 7.5)) is Event.RESUME_REQUESTED
    assert [c for _, c in op.commands] == ["start_requested", "resume_requested", "resume_requested"]


def test_operator_restarts_a_fault_before_the_plan_and_gives_up_after_its_attempts() -> None:
    """A fault in REGISTER (no plan to resume): resume is refused, so reset and start again, as
    the campaign operator does; after MAX_RECOVERIES attempts before the fault the run ends."""
    clock = ManualClock(10_000_000_000)
    op = TransportOperator("gate", 0.2, 0.5, clock, 9_000_000_000, inject=lambda: None, clear=None)
    assert op.poll(_view(State.IDLE, 0.0)) is Event.START_REQUESTED
    assert op.poll(_view(State.FAULT, 1.0)) is None
    assert op.poll(_view(State.FAULT, 1.5)) is Event.RESUME_REQUESTED
    assert op.poll(_view(State.FAULT, 1.6)) is Event.RESET_REQUESTED      # resume refused: no plan
    assert op.poll(_view(State.IDLE, 1.7)) is Event.START_REQUESTED
    assert op.poll(_view(State.REGISTER, 1.8)) is None
    assert not op.finished(_view(State.REGISTER, 1.8))
    assert op.poll(_view(State.FAULT, 2.0)) is None
    assert not op.finished(_view(State.FAULT, 2.2))                       # settling
    assert op.poll(_view(State.FAULT, 2.5)) is None                       # no attempt left
    assert op.finished(_view(State.FAULT, 2.5))


def _link_back_case(tmp_path: Path, first_speed_mm_s: float, kind: str = "robot_disconnect",
                    stop_retry_s: float | None = None) -> RunResult:
    t0 = 5_000_000_000
    log = tmp_path / "run.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in [
        {"t_ns": t0, "event": "session_started"},
        {"t_ns": t0 + 1_100_000_000, "event": "state_entered", "state": "fault"},
    ]))
    op = TransportOperator("compensate", 1.0, 1.0, ManualClock(t0), t0, inject=lambda: None, clear=None)
    op.commands.append((2.5, "resume_requested"))
    rec = Recording(
        commands=([] if stop_retry_s is None else
                  [CommandRecord(t0 + round(stop_retry_s * 1e9), "stop", None, None, 500.0, ())])
        + [CommandRecord(t0 + 2_700_000_000, "move_linear", (0.0, 0.0, 0.0), 5.0, 20.0, ())],
        states=[StateSample(t0 + 2_600_000_000, first_speed_mm_s, "running", "normal")])
    out = RunResult("r", "rtde_drop_connection@compensate", kind, "compensate", 1, passed=False,
                    reasons=["robot not seen stopped (< 1.0 mm/s) in fault before recovery"],
                    onset_s=1.0, safe_state="fault")
    _stopped_after_link_back(out, rec, log, op)
    return out


def test_dropped_link_accepts_the_arm_at_rest_when_the_link_is_back(tmp_path: Path) -> None:
    out = _link_back_case(tmp_path, 0.2)
    assert out.reasons == []
    assert out.passed is True
    assert out.stop_latency_ms == pytest.approx(1500.0)


def test_a_stop_retried_while_the_link_is_down_is_not_a_motion_command(tmp_path: Path) -> None:
    # the controller re-sends its undelivered stop every tick (2.55 s, after the operator's first
    # command at 2.5 s): the first state read after the recovery (2.6 s) still counts
    out = _link_back_case(tmp_path, 0.2, stop_retry_s=2.55)
    assert out.passed is True, out.reasons
    assert out.stop_latency_ms == pytest.approx(1500.0)


@pytest.mark.parametrize(("speed", "kind"), [(30.0, "robot_disconnect"), (0.2, "protective_stop")])
def test_dropped_link_rule_keeps_the_failure(tmp_path: Path, speed: float, kind: str) -> None:
    """Moving when the link is back, or a kind whose states never stopped coming: still a failure."""
    out = _link_back_case(tmp_path, speed, kind)
    assert out.passed is False
    assert out.reasons == ["robot not seen stopped (< 1.0 mm/s) in fault before recovery"]
