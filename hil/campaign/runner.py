"""One campaign run: build the simulated devices with one scheduled fault, run the procedure
with the campaign operator and a recording robot, then judge the run from its session log and
the recorded driver boundary (see docs/campaign.md for the criteria)."""

from __future__ import annotations

import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from hil.clock import ManualClock
from hil.config import build_devices, load_setup
from hil.config.faults import FAULT_DEVICE, FaultKind, FaultSpec
from hil.config.setup import SetupConfig
from hil.controller.fsm import State
from hil.controller.plan_file import load_plan
from hil.session.log import SessionLog, file_sha256, read_session_log, verify_session_log

from .operator import CampaignOperator
from .recorder import Recording, RecordingRobot
from .scenarios import PROFILES, KindProfile

#: States that count as the defined safe state after a fault (the robot is stopped on entry).
SAFE_STATES = ("fault", "safe_stop", "paused")
#: Reported TCP speed under which the robot counts as stopped (mm/s).
STOPPED_MM_S = 1.0
#: Settling time after the fault window before the operator recovers (s).
RECOVER_SETTLE_S = 0.5
#: Lock accuracy a tolerated fault must still reach (the seeds' 2 mm), vs simulator truth.
TOLERATED_LOCK_MM = 2.0


@dataclass(frozen=True)
class RunSpec:
    """What to run. ``kind`` None is the seed's fault-free baseline."""

    run_id: str
    config: str
    plan: str | None
    seed: int
    kind: str | None = None
    state: str | None = None
    start_s: float | None = None
    duration_s: float | None = None
    max_duration_s: float = 90.0
    log_dir: str = "."

    @property
    def scenario(self) -> str:
        return "baseline" if self.kind is None else f"{self.kind}@{self.state}"


@dataclass
class RunResult:
    run_id: str
    scenario: str
    kind: str | None
    state: str | None
    seed: int
    passed: bool
    reasons: list[str] = field(default_factory=list)
    outcome: str = ""  # "safe_state" | "tolerated" | "baseline" | "crashed" | "hang" | "not_reached"
    onset_s: float | None = None
    state_at_onset: str | None = None
    detected_s: float | None = None
    safe_state: str | None = None
    safe_latency_ms: float | None = None
    latency_bound_ms: float | None = None
    stop_latency_ms: float | None = None
    recovered_to_lock: bool | None = None
    final_state: str | None = None
    lock_error_mm: float | None = None
    commands: int = 0
    limit_violations: list[str] = field(default_factory=list)
    log_ok: bool | None = None
    log_reason: str = ""
    state_windows_s: dict[str, list[float]] = field(default_factory=dict)
    duration_s: float | None = None
    wall_s: float | None = None
    session_log: str | None = None
    error: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _plan_path(config: Path, plan: str | None) -> Path:
    if plan:
        return Path(plan)
    return config.resolve().parent / "plans" / f"{config.stem}_plan.json"


def _setup_for(spec: RunSpec) -> SetupConfig:
    setup = load_setup(spec.config)
    sim = setup.simulation.model_copy(update={"seed": spec.seed})
    faults: list[FaultSpec] = []
    if spec.kind is not None:
        assert spec.start_s is not None
        assert spec.duration_s is not None
        faults.append(FaultSpec(kind=FaultKind(spec.kind), start_s=spec.start_s, duration_s=spec.duration_s))
    return setup.model_copy(update={"simulation": sim, "faults": tuple(faults)})


def _latency_bound_ms(setup: SetupConfig, device: str, frame_rate_hz: float) -> float:
    """Detectable -> safe state, per device: the device's watchdog age, plus the camera's grab
    timeout for the camera, plus two control ticks (one to see it, one to act)."""
    sf = setup.safety
    tick_s = 1.0 / frame_rate_hz
    if device == "camera":
        age_s = sf.camera_frame_max_age_ms / 1e3 + max(4 * tick_s, 0.2)
    elif device == "robot":
        age_s = sf.robot_state_max_age_ms / 1e3
    else:
        age_s = sf.tracker_max_age_ms / 1e3
    return round(1e3 * (age_s + 2 * tick_s), 3)


def execute(spec: RunSpec) -> tuple[RunResult, Recording, Path, CampaignOperator, float]:
    """Run the procedure for ``spec``; returns the unjudged result, the recording, the log path,
    the operator and the camera frame rate."""
    from hil.controller.assembly import build_controller, wrap_robot  # the controller `hil run` builds

    config = Path(spec.config)
    setup = _setup_for(spec)
    plan = load_plan(_plan_path(config, spec.plan))
    clock = ManualClock(1_000_000_000)
    limits = setup.safety.motion_limits()
    devices = wrap_robot(build_devices(setup, clock), lambda robot: RecordingRobot(robot, limits, clock))
    recorder = devices.robot
    assert isinstance(recorder, RecordingRobot)
    log_path = Path(spec.log_dir) / f"{spec.run_id}.jsonl"
    if log_path.exists():
        log_path.unlink()
    header = {
        "setup": str(config),
        "config_sha256": file_sha256(config),
        "campaign_run": spec.run_id,
        "scenario": spec.scenario,
        "seed": spec.seed,
        "fault_kind": spec.kind,
        "fault_start_s": spec.start_s,
        "fault_duration_s": spec.duration_s,
    }
    session = SessionLog(log_path, clock, header)
    end_s = (spec.start_s or 0.0) + (spec.duration_s or 0.0)
    operator = CampaignOperator(
        recover_after_s=end_s + RECOVER_SETTLE_S if spec.kind else 0.0, max_recoveries=2 if spec.kind else 0
    )
    result = RunResult(
        spec.run_id, spec.scenario, spec.kind, spec.state, spec.seed, passed=False, session_log=str(log_path)
    )
    devices.open_all()
    frame_rate = devices.camera.frame_rate_hz
    closed_fields: dict[str, Any] = {}
    try:
        ctl = build_controller(setup, plan, devices, clock=clock, session=session, operator=operator)
        summary = ctl.run(spec.max_duration_s)
        result.final_state = summary.final_state
        result.lock_error_mm = summary.lock_error_mm
        result.duration_s = round(summary.duration_s, 4)
        closed_fields = {"final_state": summary.final_state}
    except Exception as exc:  # noqa: BLE001 - a controller crash is a campaign finding, not ours
        result.error = "".join(traceback.format_exception(exc))[-4000:]
        closed_fields = {"final_state": "crashed", "error": f"{type(exc).__name__}: {exc}"}
    finally:
        devices.close_all()
        session.close(**closed_fields)
    if spec.kind is not None:
        result.latency_bound_ms = _latency_bound_ms(setup, FAULT_DEVICE[FaultKind(spec.kind)], frame_rate)
    return result, recorder.recording, log_path, operator, frame_rate


def _timeline(log_path: Path) -> tuple[int, list[tuple[float, str]], list[tuple[float, dict[str, Any]]]]:
    """(t0_ns, [(t_s, state entered)], [(t_s, record)] of every record)."""
    recs = list(read_session_log(log_path))
    t0 = int(recs[0]["t_ns"])
    entered = [
        ((r["t_ns"] - t0) * 1e-9, str(r.get("state"))) for r in recs if r.get("event") == "state_entered"
    ]
    return t0, entered, [((r["t_ns"] - t0) * 1e-9, r) for r in recs]


def state_windows(entered: list[tuple[float, str]], end_s: float) -> dict[str, list[float]]:
    """First window [enter, leave) of every state, seconds after start."""
    out: dict[str, list[float]] = {}
    for i, (t, s) in enumerate(entered):
        if s not in out:
            nxt = entered[i + 1][0] if i + 1 < len(entered) else end_s
            out[s] = [round(t, 4), round(nxt, 4)]
    return out


def _judge_run(
    result: RunResult, rec: Recording, log_path: Path
) -> tuple[int, list[tuple[float, str]], list[tuple[float, dict[str, Any]]]]:
    """The criteria every run is held to (crash, complete log, limits) and its timeline.

    Fills ``result``'s log verdict, state windows, command count and limit violations, adding
    to ``result.reasons``; returns :func:`_timeline`'s ``(t0_ns, entered, records)`` (times in s).
    """
    reasons = result.reasons
    if result.error is not None:
        result.outcome = "crashed"
        reasons.append("unhandled exception in the controller: " + result.error.strip().splitlines()[-1])
    verdict = verify_session_log(log_path)
    result.log_ok = verdict.ok and verdict.closed
    result.log_reason = verdict.reason
    if not result.log_ok:
        reasons.append(f"session log not complete and verifiable: {verdict.reason}")
    t0_ns, entered, records = _timeline(log_path)
    end_s = records[-1][0]
    result.state_windows_s = state_windows(entered, end_s)
    result.commands = len(rec.commands)
    bad = rec.violations_reached()
    result.limit_violations = [
        f"{c.kind} at {(c.t_ns - t0_ns) * 1e-9:.3f} s: {'; '.join(c.violations)}" for c in bad
    ]
    if bad:
        reasons.append(f"{len(bad)} command(s) outside the limits reached the driver")
    return t0_ns, entered, records


def _judge_safe_state(
    result: RunResult,
    profile: KindProfile,
    onset: float,
    safe: tuple[float, str],
    t0_ns: int,
    entered: list[tuple[float, str]],
    end_s: float,
    rec: Recording,
    operator: CampaignOperator,
) -> None:
    """A fault that reached the safe state ``safe = (t_safe, state)`` (s): its latency from when
    the fault was detectable, that the robot was seen stopped before the operator's recovery, and
    that the procedure continued to lock. Fills ``result`` and adds to ``result.reasons``."""
    reasons = result.reasons
    t_safe, s_safe = safe
    result.outcome = result.outcome or "safe_state"
    result.safe_state = s_safe
    ref = onset
    if profile.detect == "on_command":
        after = [(c.t_ns - t0_ns) * 1e-9 for c in rec.commands if (c.t_ns - t0_ns) * 1e-9 >= onset - 1e-9]
        ref = after[0] if after else onset
    result.safe_latency_ms = round((t_safe - ref) * 1e3, 3)
    if (
        profile.detect != "content"
        and result.latency_bound_ms is not None
        and result.safe_latency_ms > result.latency_bound_ms
    ):
        reasons.append(
            f"safe state {s_safe} {result.safe_latency_ms:.0f} ms after the fault was "
            f"detectable (bound {result.latency_bound_ms:.0f} ms)"
        )
    # stopped or holding: a state sample under STOPPED_MM_S after entering the safe state,
    # before the operator's first recovery command
    t_recover = next((t for t, c in operator.commands if t >= t_safe), end_s + 1.0)
    stops = [
        (s.t_ns - t0_ns) * 1e-9
        for s in rec.states
        if t_safe - 1e-9 <= (s.t_ns - t0_ns) * 1e-9 <= t_recover and s.speed_mm_s < STOPPED_MM_S
    ]
    if stops:
        result.stop_latency_ms = round((stops[0] - t_safe) * 1e3, 3)
    else:
        reasons.append(f"robot not seen stopped (< {STOPPED_MM_S} mm/s) in {s_safe} before recovery")
    result.recovered_to_lock = any(s == "lock" and t > t_safe for t, s in entered)
    if not result.recovered_to_lock:
        reasons.append(f"did not continue to lock after recovery (final state {result.final_state})")


def _judge_tolerated(result: RunResult) -> None:
    """A fault that never reached a safe state: it passes only when the run still ended in done
    with a lock error within ``TOLERATED_LOCK_MM`` mm. Adds to ``result.reasons``."""
    result.outcome = result.outcome or "tolerated"
    if result.final_state != State.DONE.value:
        result.reasons.append(
            f"fault neither reached a safe state nor was tolerated (final state {result.final_state})"
        )
    elif result.lock_error_mm is None or result.lock_error_mm > TOLERATED_LOCK_MM:
        result.reasons.append(f"tolerated, but lock error {result.lock_error_mm} mm > {TOLERATED_LOCK_MM} mm")


def judge(
    spec: RunSpec, result: RunResult, rec: Recording, log_path: Path, operator: CampaignOperator
) -> RunResult:
    """Apply the pass criteria (docs/campaign.md) and fill ``result``."""
    reasons = result.reasons
    t0_ns, entered, records = _judge_run(result, rec, log_path)
    end_s = records[-1][0]
    if spec.kind is None:
        if result.outcome != "crashed":
            result.outcome = "baseline"
            if result.final_state != State.DONE.value:
                reasons.append(f"baseline did not reach done (final state {result.final_state})")
        result.passed = not reasons
        return result

    assert spec.start_s is not None
    assert spec.duration_s is not None
    onset = spec.start_s
    result.onset_s = onset
    before = [s for t, s in entered if t <= onset]
    result.state_at_onset = before[-1] if before else "idle"
    if end_s < onset:
        result.outcome = "not_reached"
        reasons.append(f"the run ended at {end_s:.2f} s, before the fault at {onset:.2f} s")
        result.passed = False
        return result
    profile = PROFILES[FaultKind(spec.kind)]
    detected = [t for t, r in records if r.get("event") == "fault_detected" and t >= onset - 1e-9]
    result.detected_s = round(detected[0], 4) if detected else None
    safe = [(t, s) for t, s in entered if s in SAFE_STATES and t >= onset - 1e-9]
    if safe:
        t_safe, s_safe = safe[0]
        _judge_safe_state(result, profile, onset, (t_safe, s_safe), t0_ns, entered, end_s, rec, operator)
    else:
        _judge_tolerated(result)
    result.passed = not reasons
    return result


def run_one(spec: RunSpec) -> RunResult:
    """Execute and judge one run. Never raises for a controller problem (it fails the run)."""
    import time

    t_wall = time.perf_counter()
    result, rec, log_path, operator, _ = execute(spec)
    out = judge(spec, result, rec, log_path, operator)
    out.wall_s = round(time.perf_counter() - t_wall, 3)
    return out
