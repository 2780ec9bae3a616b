"""End-to-end simulated procedures (simulated devices, real vision pipeline, ManualClock).

One run per scenario; each takes a few seconds of CPU (every frame is rendered and detected).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from hil.config import load_setup
from hil.config.faults import FaultKind, FaultSpec
from hil.config.setup import SetupConfig
from hil.config.simulation import DriftConfig, ShiftConfig
from hil.controller.metrics import RunSummary
from hil.controller.plan_file import load_plan
from hil.session import read_session_log, verify_session_log

CONFIG = Path("configs/sim.toml")
PLAN = load_plan("configs/plans/sim_plan.json")


def _setup(sim: dict[str, Any] | None = None, proc: dict[str, Any] | None = None,
           faults: tuple[FaultSpec, ...] = ()) -> SetupConfig:
    s = load_setup(CONFIG)
    return s.model_copy(update={"simulation": s.simulation.model_copy(update=sim or {}),
                                "procedure": s.procedure.model_copy(update=proc or {}),
                                "faults": faults})


def _run(setup: SetupConfig, tmp_path: Path, max_s: float = 40.0) -> RunSummary:
    from hil.cli.cmd_run import run_procedure

    return run_procedure(CONFIG, setup, PLAN, auto=True, session_dir=tmp_path, max_duration_s=max_s)


def _events(summary: RunSummary) -> list[str]:
    return [r["event"] for r in read_session_log(summary.session_log)]


NOMINAL = ["idle", "register", "plan", "approach", "gate", "compensate", "lock", "done"]


@pytest.mark.slow
def test_still_patient_locks_within_half_a_millimetre(tmp_path: Path) -> None:
    s0 = load_setup(CONFIG).simulation
    s = _run(_setup({"breathing": s0.breathing.model_copy(update={"enabled": False}),
                     "drift": DriftConfig()}), tmp_path)
    assert s.final_state == "done"
    assert s.states == NOMINAL
    assert s.fre_mm is not None
    assert s.fre_mm < 0.2
    assert s.lock_error_mm is not None
    assert s.lock_error_mm < 0.5
    assert s.lock_direction_error_deg is not None
    assert s.lock_direction_error_deg < 1.0
    assert s.commands_refused == 0
    summary = s.to_dict()
    for key in ("final_state", "states", "fre_mm", "tre_expected_mm", "lock_error_mm",
                "lock_direction_error_deg", "comp_error_p95_mm", "latency_ms", "session_log", "timeline",
                "gate_open_fraction"):
        assert key in summary
    assert set(summary["latency_ms"]) == {"p50", "p95"}
    header = next(read_session_log(s.session_log))
    assert len(header["config_sha256"]) == 64
    assert len(header["calibration_sha256"]) == 64
    assert header["perception_process"] is False   # the manual clock: located in the supervisor
    why = header["perception_in_supervisor_because"]
    assert why == "it needs the wall clock ([simulation] real_time = true)"
    rep = verify_session_log(s.session_log)
    assert (rep.ok, rep.closed) == (True, True)
    ev = _events(s)
    for name in ("registration_done", "plan_accepted", "command_sent", "compensation_step", "frame_measured",
                 "transition_applied", "truth_error"):
        assert name in ev
    # LOCK is held by the servo loop: one hold order at entry, then a command every period
    in_lock = _records_in(s, "lock")
    assert [(r["event"], r.get("command")) for r in in_lock if r["event"] in ("command_sent", "stop_sent")] \
        == [("command_sent", "hold")]
    stats = [r for r in in_lock if r["event"] == "servo_stats"]
    assert sum(r["commands"] for r in stats) == sum(r["periods"] for r in stats) > 100
    assert sum(r["refusals"] + r["following_faults"] for r in stats) == 0
    # APPROACH checks the stand-off optically only on pairs exposed settle_s after the arm was
    # seen at rest; the pairs exposed in between were left out
    a = load_setup(CONFIG).procedure.approach
    in_approach = _records_in(s, "approach")
    checks = [r for r in in_approach if r["event"] == "approach_measured"]
    exposures = [r["exposure_t_ns"] for r in in_approach if r["event"] == "frame_measured"]
    assert checks
    for r in checks:
        settled_ns = r["rest_ns"] + round(a.settle_s * 1e9)
        assert r["pairs"] == a.measure_frames
        assert r["first_exposure_ns"] >= settled_ns
        assert any(r["rest_ns"] <= e < settled_ns for e in exposures)


def _records_in(summary: RunSummary, state: str) -> list[dict[str, Any]]:
    """The session log's records written while ``state`` was current."""
    out, current = [], None
    for r in read_session_log(summary.session_log):
        if r["event"] == "state_entered":
            current = r["state"]
        if current == state:
            out.append(r)
    return out


@pytest.mark.slow
def test_breathing_patient_is_gated_and_compensated(tmp_path: Path) -> None:
    s0 = load_setup(CONFIG).simulation
    s = _run(_setup({"breathing": s0.breathing.model_copy(update={"amplitude_mm": 10.0, "period_s": 4.0})}),
             tmp_path)
    assert s.final_state == "done"
    assert s.states == NOMINAL
    assert s.gate_open_fraction is not None
    assert s.gate_open_fraction < 1.0  # breathing took the markers out of the gate tolerance
    t_gate = next(r["t_s"] for r in s.timeline if r["state"] == "gate")
    t_comp = next(r["t_s"] for r in s.timeline if r["state"] == "compensate")
    assert t_comp - t_gate > 1.0  # the gate waited for the requested breath-hold (1 s reaction)
    assert s.comp_error_p95_mm is not None
    assert s.comp_error_p95_mm < 1.0
    assert s.lock_error_mm is not None
    assert s.lock_error_mm < 0.5
    assert s.latency_ms["p50"] is not None
    assert "breath_hold_requested" in _events(s)
    # entering GATE: the arm is told to hold first, then the patient is asked to hold the breath
    recs = list(read_session_log(s.session_log))
    i_gate = next(i for i, r in enumerate(recs) if r["event"] == "state_entered" and r["state"] == "gate")
    entry = [r["event"] for r in recs[i_gate:] if r["event"] in ("stop_sent", "breath_hold_requested")]
    assert entry[:2] == ["stop_sent", "breath_hold_requested"]


@pytest.mark.slow
def test_drift_while_locked_raises_the_alarm_and_retracts(tmp_path: Path) -> None:
    proc = load_setup(CONFIG).procedure
    s = _run(_setup({"drift": DriftConfig(velocity_mm_s=(1.0, 0.0, 0.0), max_mm=20.0)},
                    {"lock": proc.lock.model_copy(update={"hold_s": 0.0}),
                     "gate": proc.gate.model_copy(update={"tolerance_mm": 8.0})}), tmp_path)
    assert s.states == ["idle", "register", "plan", "approach", "gate", "compensate", "lock", "retract",
                        "safe_stop"]
    assert "drift_alarm" in _events(s)
    assert s.timeline[-2]["event"] == "drift_detected"


@pytest.mark.slow
def test_sudden_shift_beyond_bounds_pauses_and_re_registers(tmp_path: Path) -> None:
    comp = load_setup(CONFIG).procedure.compensation.model_copy(update={"settle_s": 3.0})
    # the shift lands in COMPENSATE (entered at ~7.2 s of simulated time, held >= settle_s)
    s = _run(_setup({"shifts": (ShiftConfig(at_s=8.0, translation_mm=(30.0, 0.0, 0.0)),)},
                    {"compensation": comp}), tmp_path)
    assert s.states[:7] == ["idle", "register", "plan", "approach", "gate", "compensate", "paused"]
    paused = next(r for r in s.timeline if r["state"] == "paused")
    assert paused["event"] == "correction_out_of_bounds"
    assert "bound 25.0 mm" in paused["reason"]
    assert "correction_out_of_bounds" in _events(s)
    # the auto operator re-registers on the shifted patient and the procedure completes
    assert s.states[7:] == ["register", "plan", "approach", "gate", "compensate", "lock", "done"]
    assert s.lock_error_mm is not None
    assert s.lock_error_mm < 0.5


@pytest.mark.slow
def test_shift_beyond_bounds_while_gated_pauses_instead_of_asking_for_breath_holds(tmp_path: Path) -> None:
    # the shift lands in GATE (entered at ~5.1 s of simulated time, opened at ~7.2 s unshifted):
    # no breath-hold brings the markers back, so the operator decides (the auto operator
    # re-registers on the shifted patient) -- before, GATE asked for breath-holds until aborted
    s = _run(_setup({"shifts": (ShiftConfig(at_s=6.0, translation_mm=(30.0, 0.0, 0.0)),)}), tmp_path)
    assert s.states == ["idle", "register", "plan", "approach", "gate", "paused",
                        "register", "plan", "approach", "gate", "compensate", "lock", "done"]
    paused = next(r for r in s.timeline if r["state"] == "paused")
    assert paused["event"] == "correction_out_of_bounds"
    assert "bound 25.0 mm" in paused["reason"]
    t_shift_s = 6.0
    assert t_shift_s < paused["t_s"] < t_shift_s + 0.5
    rec = next(r for r in read_session_log(s.session_log) if r["event"] == "correction_out_of_bounds")
    assert rec["reason"].startswith("patient moved 3")
    assert s.lock_error_mm is not None
    assert s.lock_error_mm < 0.5


def test_protective_stop_enters_fault_and_stops(tmp_path: Path) -> None:
    s = _run(_setup(faults=(FaultSpec(kind=FaultKind.PROTECTIVE_STOP, start_s=3.0, duration_s=5.0),)),
             tmp_path)
    assert s.final_state == "fault"
    assert s.faults
    assert "protective_stop" in s.faults[0]
    ev = _events(s)
    assert "fault_detected" in ev
    assert "stop_sent" in ev[ev.index("fault_detected"):]


@pytest.mark.parametrize(("kind", "params", "expect"), [
    (FaultKind.STALE_TIMESTAMP, {"age_ms": 400.0}, "watchdog: camera data"),
    (FaultKind.ROBOT_DISCONNECT, {}, "robot"),
])
def test_device_faults_enter_fault_with_the_reason(kind: FaultKind, params: dict[str, Any], expect: str,
                                                   tmp_path: Path) -> None:
    s = _run(_setup(faults=(FaultSpec(kind=kind, start_s=1.0, duration_s=2.0, **params),)), tmp_path, 10.0)
    assert s.final_state == "fault"
    assert expect in s.faults[0]


class _PauseOnceOperator:
    """Pauses the first time COMPENSATE is seen, resumes 1 s later; otherwise like --auto."""

    def __init__(self) -> None:
        from hil.controller.operator_input import AutoOperator

        self.auto = AutoOperator()
        self.paused_at: float | None = None
        self.resumed = False

    def poll(self, view: Any) -> Any:
        from hil.controller.fsm import Event, State

        if view.state is State.COMPENSATE and self.paused_at is None:
            self.paused_at = view.t_s
            return Event.PAUSE_REQUESTED
        if view.state is State.PAUSED:
            if not self.resumed and view.t_s > (self.paused_at or 0.0) + 1.0:
                self.resumed = True
                return Event.RESUME_REQUESTED
            return None
        return self.auto.poll(view)

    def finished(self, view: Any) -> bool:
        from hil.controller.fsm import State

        return view.state is not State.PAUSED and self.auto.finished(view)


@pytest.mark.slow
def test_pause_and_resume_restart_from_the_actual_pose_with_a_ramp(tmp_path: Path) -> None:
    from hil.cli.cmd_run import run_procedure

    setup = _setup()
    s = run_procedure(CONFIG, setup, PLAN, auto=True, session_dir=tmp_path, max_duration_s=40.0,
                      operator=_PauseOnceOperator())
    assert s.states == ["idle", "register", "plan", "approach", "gate", "compensate", "paused", "approach",
                        "gate", "compensate", "lock", "done"]
    recs = list(read_session_log(s.session_log))
    i_resume = next(i for i, r in enumerate(recs) if r["event"] == "transition_applied"
                    and r["transition"] == "resume")
    i_pause = next(i for i, r in enumerate(recs) if r["event"] == "transition_applied"
                   and r["transition"] == "pause")
    assert any(r["event"] == "stop_sent" for r in recs[i_pause:i_resume])
    first_move = next(r for r in recs[i_resume:] if r["event"] == "command_sent")
    a = setup.procedure.approach
    frac = setup.procedure.resume.initial_speed_fraction
    assert first_move["command"] == "move_linear"
    assert first_move["speed_mm_s"] == a.speed_mm_s * frac
    assert first_move["accel_mm_s2"] == a.accel_mm_s2 * frac


def test_a_refused_command_is_never_sent_and_faults(tmp_path: Path) -> None:
    """The approach acceleration exceeds the [safety] limit: the safety layer refuses the move
    before the driver sees it, and the controller enters FAULT with the reason."""
    base = _setup()
    setup = base.model_copy(update={"safety": base.safety.model_copy(update={"max_accel_mm_s2": 100.0})})
    s = _run(setup, tmp_path, 15.0)
    assert s.final_state == "fault"
    assert s.states[-2:] == ["approach", "fault"]
    assert s.commands_refused == 1
    assert s.commands_sent == 0
    assert s.faults[0].startswith("entering approach: safety: acceleration: 200.0 mm/s^2 not in (0, 100.0]")


def test_an_internal_error_in_a_tick_becomes_a_fault(tmp_path: Path) -> None:
    from hil.clock import ManualClock
    from hil.config import build_devices
    from hil.controller.assembly import rig_geometry as _rig
    from hil.controller.controller import Controller
    from hil.controller.operator_input import AutoOperator
    from hil.session import SessionLog

    setup = _setup()
    clock = ManualClock(10**9)
    dev = build_devices(setup, clock)
    dev.open_all()

    def broken(frame: Any) -> Any:
        raise ValueError("boom")

    try:
        with SessionLog(tmp_path / "s.jsonl", clock) as log:
            ctl = Controller(camera=dev.camera, robot=dev.robot, tracker=None, clock=clock, locate=broken,
                             plan=PLAN, rig=_rig(setup, dev.robot), procedure=setup.procedure,
                             limits=setup.safety.motion_limits(),
                             watchdog_ages_s={"camera": 0.25, "robot": 0.05}, session=log,
                             operator=AutoOperator())
            s = ctl.run(5.0)
    finally:
        dev.close_all()
    assert s.final_state == "fault"
    assert s.faults == ["internal error: ValueError: boom"]


class _StopWhileAskedOperator:
    """Starts; never confirms plan_to_approach by itself; once the robot has faulted (protective
    stop while the confirmation was pending) asks to RESUME, and confirms only after ``hold_s``."""

    def __init__(self, hold_s: float) -> None:
        self.hold_s = hold_s
        self.started = False
        self.resumed_at: float | None = None
        self.confirmed = False
        self.pendings: list[tuple[str, str | None]] = []

    def poll(self, view: Any) -> Any:
        from hil.controller.fsm import Event, State

        self.pendings.append((view.state.value, view.pending))
        if not self.started:
            self.started = True
            return Event.START_REQUESTED
        if view.state is State.FAULT and self.resumed_at is None and view.t_s > 4.0:
            self.resumed_at = view.t_s
            return Event.RESUME_REQUESTED
        if (self.resumed_at is not None and view.pending is not None and not self.confirmed
                and view.t_s > self.resumed_at + self.hold_s):
            self.confirmed = True
            return Event.CONFIRM_REQUESTED
        return None

    def finished(self, view: Any) -> bool:
        from hil.controller.fsm import State

        return view.state is State.APPROACH and self.confirmed


def test_recovery_does_not_skip_the_pending_approach_confirmation(tmp_path: Path) -> None:
    """Regression: a protective stop while plan_to_approach waits for its confirmation, then RESUME:
    the robot must not move until the operator has confirmed."""
    from hil.cli.cmd_run import run_procedure

    setup = _setup(faults=(FaultSpec(kind=FaultKind.PROTECTIVE_STOP, start_s=3.0, duration_s=0.5),))
    op = _StopWhileAskedOperator(hold_s=0.5)
    s = run_procedure(CONFIG, setup, PLAN, auto=False, session_dir=tmp_path, max_duration_s=15.0, operator=op)
    assert s.states == ["idle", "register", "plan", "fault", "approach"]
    recs = list(read_session_log(s.session_log))
    i_resume = next(i for i, r in enumerate(recs) if r["event"] == "operator_command"
                    and r["input"] == "resume_requested")
    i_confirm = next(i for i, r in enumerate(recs) if r["event"] == "operator_command"
                     and r["input"] == "confirm_requested")
    assert i_resume < i_confirm
    between = recs[i_resume:i_confirm]
    assert not [r for r in between if r["event"] == "command_sent" and r["command"] != "stop"]
    assert any(r["event"] == "transition_pending" and r["target"] == "approach" for r in between)
    first_move = next(r for r in recs[i_confirm:] if r["event"] == "command_sent")
    assert first_move["command"] == "move_linear"
    fault_row = next(r for r in s.timeline if r["state"] == "fault")
    assert "protective_stop" in fault_row["reason"]


class _ReRegisterThenResumeOperator:
    """Pauses in COMPENSATE, re-registers, aborts the new registration, then asks to resume."""

    def __init__(self) -> None:
        from hil.controller.operator_input import AutoOperator

        self.auto = AutoOperator()
        self.step = 0

    def poll(self, view: Any) -> Any:
        from hil.controller.fsm import Event, State

        script = [(State.COMPENSATE, Event.PAUSE_REQUESTED), (State.PAUSED, Event.START_REQUESTED),
                  (State.REGISTER, Event.ABORT_REQUESTED), (State.SAFE_STOP, Event.RESUME_REQUESTED)]
        if self.step < len(script) and view.state is script[self.step][0]:
            self.step += 1
            return script[self.step - 1][1]
        return None if self.step else self.auto.poll(view)

    def finished(self, view: Any) -> bool:
        return self.step == 4 and view.t_s > 0


@pytest.mark.slow
def test_resume_after_a_restarted_registration_is_refused_not_guided_on_the_old_plan(tmp_path: Path) -> None:
    """Found by the 60-minute soak: a registration restarted (its patient registration forgotten)
    kept the old guide plan, and a resume went to APPROACH and on to GATE without a registration
    (an internal error). The resume must be refused until registration and planning are redone."""
    from hil.cli.cmd_run import run_procedure

    s = run_procedure(CONFIG, _setup(), PLAN, auto=True, session_dir=tmp_path, max_duration_s=40.0,
                      operator=_ReRegisterThenResumeOperator())
    assert s.states == ["idle", "register", "plan", "approach", "gate", "compensate", "paused", "register",
                        "safe_stop"]
    assert s.faults == []
    results = [r for r in read_session_log(s.session_log) if r["event"] == "operator_command_result"]
    resume = [r for r in results if r["input"] == "resume_requested"]
    assert [(r["outcome"], r["reason"]) for r in resume] == [
        ("rejected",
         "the guide plan belongs to a registration that was restarted: register and plan first (s)")]
