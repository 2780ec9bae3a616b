"""One campaign run: build the simulated devices with one scheduled fault, run the procedure
with the campaign operator and a recording robot, then judge the run from its session log and
the recorded driver boundary (see docs/campaign.md for the criteria)."""

from __future__ import annotations

import traceback
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from hil.clock import ManualClock
from hil.config import build_devices, load_setup
from hil.config.faults import FAULT_DEVICE, FaultKind, FaultSpec
from hil.config.setup import SetupConfig
from hil.controller.fsm import State
from hil.controller.pipeline import camera_silence_s
from hil.controller.plan_file import load_plan
from hil.session.log import SessionLog, file_sha256, read_session_log, verify_session_log

from .operator import CampaignOperator
from .pairs import recovery_window
from .recorder import Recording, RecordingRobot
from .scenarios import PROFILES

#: States that count as the defined safe state after a fault (the robot is stopped on entry).
SAFE_STATES = ("fault", "safe_stop", "paused")
#: Reported TCP speed under which the robot counts as stopped (mm/s).
STOPPED_MM_S = 1.0
#: Settling time after the fault window before the operator recovers (s).
RECOVER_SETTLE_S = 0.5
#: Recovery attempts the operator has per scheduled fault (a resume, or a reset and a restart).
RECOVERIES_PER_FAULT = 2
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
    #: A compound fault (``hil campaign --pairs``): the second fault's kind, start and length, and
    #: whether it was placed in the recovery from the first (else it overlaps the first).
    second_kind: str | None = None
    second_start_s: float | None = None
    second_duration_s: float | None = None
    recovery: bool = False
    #: the state the second fault is meant to hit (recovery scenarios fail when it does not)
    second_state: str | None = None

    @property
    def scenario(self) -> str:
        if self.kind is None:
            return "baseline"
        if self.second_kind is None:
            return f"{self.kind}@{self.state}"
        return f"{self.kind}+{self.second_kind}@{self.state}" + ("+recovery" if self.recovery else "")

    def windows(self) -> list[tuple[str, float, float]]:
        """``(kind, start_s, duration_s)`` of every scheduled fault, in order."""
        out = []
        if self.kind is not None:
            assert self.start_s is not None
            assert self.duration_s is not None
            out.append((self.kind, self.start_s, self.duration_s))
        if self.second_kind is not None:
            assert self.second_start_s is not None
            assert self.second_duration_s is not None
            out.append((self.second_kind, self.second_start_s, self.second_duration_s))
        return out


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
    #: fault runs: the first state entered by a recovery transition after the safe state
    #: ``[enter_s, leave_s, state]`` (where a recovery scenario's second fault is placed)
    recovery_window_s: list[float | str] | None = None
    #: compound faults: the second fault, its onset, the state it hit, and the safe state it led to
    second_kind: str | None = None
    second_onset_s: float | None = None
    second_state_at_onset: str | None = None
    second_safe_state: str | None = None
    second_safe_latency_ms: float | None = None
    second_latency_bound_ms: float | None = None
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
    #: the servo loop's following-error supervision (hil/safety/following.py): the largest error
    #: of the run and the bound (mm); a fault the arm tolerated was tolerated within this bound
    following_peak_mm: float | None = None
    following_bound_mm: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _plan_path(config: Path, plan: str | None) -> Path:
    if plan:
        return Path(plan)
    return config.resolve().parent / "plans" / f"{config.stem}_plan.json"


def _setup_for(spec: RunSpec) -> SetupConfig:
    setup = load_setup(spec.config)
    sim = setup.simulation.model_copy(update={"seed": spec.seed})
    faults = [FaultSpec(kind=FaultKind(k), start_s=a, duration_s=d) for k, a, d in spec.windows()]
    return setup.model_copy(update={"simulation": sim, "faults": tuple(faults)})


def _latency_bound_ms(setup: SetupConfig, device: str, frame_rate_hz: float) -> float:
    """Detectable -> safe state, per device: the device's watchdog age, plus the camera's grab
    timeout for the camera (:func:`hil.controller.pipeline.camera_silence_s`), plus two control
    ticks (one to see it, one to act)."""
    sf = setup.safety
    tick_s = 1.0 / frame_rate_hz
    if device == "camera":
        configured_s = None if sf.camera_silence_ms is None else sf.camera_silence_ms / 1e3
        silence_s = camera_silence_s(tick_s, configured_s)
        age_s = sf.camera_frame_max_age_ms / 1e3 + silence_s
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
    if spec.second_kind is not None:
        header.update(second_fault_kind=spec.second_kind, second_fault_start_s=spec.second_start_s,
                      second_fault_duration_s=spec.second_duration_s, second_fault_in_recovery=spec.recovery)
    session = SessionLog(log_path, clock, header)
    end_s = (spec.start_s or 0.0) + (spec.duration_s or 0.0)
    faults = spec.windows()
    holds = tuple((a, round(a + d + RECOVER_SETTLE_S, 6)) for _, a, d in faults[1:])
    operator = CampaignOperator(
        recover_after_s=end_s + RECOVER_SETTLE_S if spec.kind else 0.0,
        max_recoveries=RECOVERIES_PER_FAULT * len(faults), holds=holds,
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
    if spec.second_kind is not None:
        result.second_latency_bound_ms = _latency_bound_ms(
            setup, FAULT_DEVICE[FaultKind(spec.second_kind)], frame_rate)
    return result, recorder.recording, log_path, operator, frame_rate


def _timeline(log_path: Path) -> tuple[int, list[tuple[float, str]], list[tuple[float, dict[str, Any]]]]:
    """(t0_ns, [(t_s, state entered)], [(t_s, record)] of every record)."""
    recs = list(read_session_log(log_path))
    t0 = int(recs[0]["t_ns"])
    entered = [
        ((r["t_ns"] - t0) * 1e-9, str(r.get("state"))) for r in recs if r.get("event") == "state_entered"
    ]
    return t0, entered, [((r["t_ns"] - t0) * 1e-9, r) for r in recs]


def state_path(log_path: Path, *, limit: int = 12) -> str:
    """Where a run went, for a reason a reader can act on: ``register 0.46 s, plan 3.31 s, ...``
    (seconds after the log's start), a safe state with the reason it was entered; the first
    ``limit`` entries, then how many more."""
    try:
        recs = list(read_session_log(log_path))
    except (OSError, ValueError) as exc:
        return f"session log unreadable: {exc}"
    if not recs:
        return "no records"
    t0 = int(recs[0]["t_ns"])
    steps = []
    for r in recs:
        if r.get("event") != "state_entered":
            continue
        step = f"{r.get('state')} {(int(r['t_ns']) - t0) * 1e-9:.2f} s"
        if r.get("state") in SAFE_STATES:
            step += f" ({r.get('reason')})"
        steps.append(step)
    more = f", ... {len(steps) - limit} more" if len(steps) > limit else ""
    return ", ".join(steps[:limit]) + more if steps else "no state entered"


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
    result.following_peak_mm, result.following_bound_mm = following_figures(r for _, r in records)
    return t0_ns, entered, records


def following_note(r: dict[str, Any]) -> str:
    """For a tolerated fault: the run's following-error peak beside its bound (hil/safety/
    following.py), so a tolerated stall or slow response shows how far inside the bound it stayed;
    empty otherwise (the progress line's suffix)."""
    peak, bound = r.get("following_peak_mm"), r.get("following_bound_mm")
    if r.get("outcome") != "tolerated" or peak is None or bound is None:
        return ""
    return f" (following error peak {peak:.2f} mm, bound {bound:g} mm)"


def following_figures(records: Iterable[dict[str, Any]]) -> tuple[float | None, float | None]:
    """``(peak, bound)`` of the run's following error, mm, from its ``servo_stats`` (the peak is a
    running maximum) and ``servo_following_bounds`` records; None where the log has none."""
    peak: float | None = None
    bound: float | None = None
    for r in records:
        if r.get("event") == "servo_stats" and r.get("following_peak_mm") is not None:
            peak = max(peak or 0.0, float(r["following_peak_mm"]))
        elif r.get("event") == "servo_following_bounds" and bound is None:
            bound = float(r["bound_mm"])
    return peak, bound


def detectable_s(kind: str, onset_s: float, rec: Recording, t0_ns: int) -> float | None:
    """When a fault of ``kind`` that started at ``onset_s`` (s) became detectable: its onset
    (``watchdog`` kinds), the first command to the robot at or after it (``on_command``; the onset
    when none came), None for kinds detectable only in the data (``content``: not bounded)."""
    detect = PROFILES[FaultKind(kind)].detect
    if detect == "content":
        return None
    if detect == "on_command":
        after = [(c.t_ns - t0_ns) * 1e-9 for c in rec.commands if (c.t_ns - t0_ns) * 1e-9 >= onset_s - 1e-9]
        return after[0] if after else onset_s
    return onset_s


@dataclass
class SafeVerdict:
    """What :func:`check_safe_state` found for one safe state."""

    latency_ms: float
    bounded: bool
    stop_latency_ms: float | None
    recovered_to_lock: bool
    reasons: list[str]


def check_safe_state(
    safe: tuple[float, str],
    ref_s: float,
    bound_ms: float | None,
    t0_ns: int,
    entered: list[tuple[float, str]],
    end_s: float,
    rec: Recording,
    operator: CampaignOperator,
    final_state: str | None,
) -> SafeVerdict:
    """A safe state ``safe = (t_safe, state)`` (s) entered after a fault: its latency from
    ``ref_s`` (when the fault was detectable) against ``bound_ms`` (None: not bounded), that the
    robot was seen stopped before the operator's next recovery command, and that the procedure
    continued to lock afterwards."""
    reasons: list[str] = []
    t_safe, s_safe = safe
    latency_ms = round((t_safe - ref_s) * 1e3, 3)
    if bound_ms is not None and latency_ms > bound_ms:
        reasons.append(f"safe state {s_safe} {latency_ms:.0f} ms after the fault was detectable "
                       f"(bound {bound_ms:.0f} ms)")
    # stopped or holding: a state sample under STOPPED_MM_S after entering the safe state,
    # before the operator's first recovery command
    t_recover = next((t for t, c in operator.commands if t >= t_safe), end_s + 1.0)
    stops = [
        (s.t_ns - t0_ns) * 1e-9
        for s in rec.states
        if t_safe - 1e-9 <= (s.t_ns - t0_ns) * 1e-9 <= t_recover and s.speed_mm_s < STOPPED_MM_S
    ]
    stop_ms = round((stops[0] - t_safe) * 1e3, 3) if stops else None
    if stop_ms is None:
        reasons.append(f"robot not seen stopped (< {STOPPED_MM_S} mm/s) in {s_safe} before recovery")
    recovered = any(s == "lock" and t > t_safe for t, s in entered)
    if not recovered:
        reasons.append(f"did not continue to lock after recovery (final state {final_state})")
    return SafeVerdict(latency_ms, bound_ms is not None, stop_ms, recovered, reasons)


def _judge_safe_state(result: RunResult, safe: tuple[float, str], ref_s: float, bound_ms: float | None,
                      timeline: tuple[int, list[tuple[float, str]], float], rec: Recording,
                      operator: CampaignOperator) -> None:
    """A fault that reached the safe state ``safe`` (:func:`check_safe_state`). Fills ``result``
    and adds to ``result.reasons``."""
    t0_ns, entered, end_s = timeline
    v = check_safe_state(safe, ref_s, bound_ms, t0_ns, entered, end_s, rec, operator, result.final_state)
    result.outcome = result.outcome or "safe_state"
    result.safe_state = safe[1]
    result.safe_latency_ms = v.latency_ms
    result.stop_latency_ms = v.stop_latency_ms
    result.recovered_to_lock = v.recovered_to_lock
    result.reasons += v.reasons


def _judge_tolerated(result: RunResult, what: str = "fault") -> None:
    """A fault that never reached a safe state: it passes only when the run still ended in done
    with a lock error within ``TOLERATED_LOCK_MM`` mm. Adds to ``result.reasons``."""
    result.outcome = result.outcome or "tolerated"
    if result.final_state != State.DONE.value:
        result.reasons.append(
            f"{what} neither reached a safe state nor was tolerated (final state {result.final_state})"
        )
    elif result.lock_error_mm is None or result.lock_error_mm > TOLERATED_LOCK_MM:
        result.reasons.append(f"tolerated, but lock error {result.lock_error_mm} mm > {TOLERATED_LOCK_MM} mm")


def _state_at(entered: list[tuple[float, str]], t_s: float) -> str:
    before = [s for t, s in entered if t <= t_s]
    return before[-1] if before else "idle"


def _first_bound(spec: RunSpec, result: RunResult, rec: Recording, t0_ns: int, safe_s: float
                 ) -> tuple[float | None, float | None]:
    """``(ref_s, bound_ms)`` of the first safe state (entered at ``safe_s``): ``ref_s`` the time
    the first fault became detectable; the bound such that ``ref_s + bound`` is the earliest
    deadline of the faults detectable by ``safe_s`` (each one's detectable time plus its device's
    bound). So a robot fault starting while the camera drops frames must be acted on within the
    robot's bound, not the camera's. For an overlapping pair the second fault competes; a fault
    in the recovery does not (it is judged on its own). ``(None, None)`` when no fault is bounded
    (content kinds only)."""
    bounds = [result.latency_bound_ms]
    if spec.second_kind is not None and not spec.recovery:
        bounds.append(result.second_latency_bound_ms)
    detectable = []
    for (kind, start, _), bound in zip(spec.windows(), bounds, strict=False):
        det = detectable_s(kind, start, rec, t0_ns)
        if det is not None and bound is not None:
            detectable.append((det, bound))
    if not detectable:
        return None, None
    ref = min(det for det, _ in detectable)
    due = [det + bound / 1e3 for det, bound in detectable if det <= safe_s + 1e-9] or \
        [det + bound / 1e3 for det, bound in detectable if det == ref]
    return ref, round(1e3 * (min(due) - ref), 3)


def judge_second(spec: RunSpec, result: RunResult, rec: Recording,
                 timeline: tuple[int, list[tuple[float, str]], float], operator: CampaignOperator) -> None:
    """The second fault of a compound-fault run (``hil campaign --pairs``; docs/campaign.md,
    "Compound faults"): its onset and the state it hit; for one placed in the recovery from the
    first, the criteria again from its onset: the first safe state at or after it (within its
    device's bound from when it was detectable, the robot seen stopped before the next recovery,
    the procedure continuing to lock), or, with none, tolerated (done, lock within 2 mm). A
    recovery scenario whose second fault did not start in the recovery state it was placed in
    fails: that cell was not tested. Fills ``result``'s ``second_*`` fields and adds to
    ``result.reasons``; ``timeline`` is ``(t0_ns, [(t_s, state entered)], end_s)``."""
    assert spec.second_kind is not None
    assert spec.second_start_s is not None
    t0_ns, entered, end_s = timeline
    onset = spec.second_start_s
    result.second_kind = spec.second_kind
    result.second_onset_s = onset
    if end_s < onset:
        result.reasons.append(f"the run ended at {end_s:.2f} s, before the second fault at {onset:.2f} s")
        return
    result.second_state_at_onset = _state_at(entered, onset)
    if not spec.recovery:
        return
    if result.second_state_at_onset != spec.second_state:
        result.reasons.append(
            f"second fault started in {result.second_state_at_onset}, not in the recovery state "
            f"{spec.second_state} it was placed in: not tested")
        return
    safe = [(t, s) for t, s in entered if s in SAFE_STATES and t >= onset - 1e-9]
    if not safe:
        _judge_tolerated(result, "second fault")
        return
    ref = detectable_s(spec.second_kind, onset, rec, t0_ns)
    bound = result.second_latency_bound_ms
    if ref is None or ref > safe[0][0]:  # safe before the second fault was detectable: not bounded
        ref, bound = onset, None
    v = check_safe_state(safe[0], ref, bound, t0_ns, entered, end_s, rec, operator, result.final_state)
    result.second_safe_state = safe[0][1]
    result.second_safe_latency_ms = v.latency_ms
    if not v.bounded:
        result.second_latency_bound_ms = None
    result.reasons += [f"second fault: {r}" for r in v.reasons]


def judge(
    spec: RunSpec, result: RunResult, rec: Recording, log_path: Path, operator: CampaignOperator
) -> RunResult:
    """Apply the pass criteria (docs/campaign.md) and fill ``result``. A compound fault (a
    second fault in ``spec``) is judged from its first fault as one fault is (the latency from
    the first fault that became detectable, against the earliest bound either sets); a second
    fault placed in the recovery is then judged again on its own (:func:`judge_second`)."""
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
    result.state_at_onset = _state_at(entered, onset)
    if end_s < onset:
        result.outcome = "not_reached"
        reasons.append(f"the run ended at {end_s:.2f} s, before the fault at {onset:.2f} s")
        result.passed = False
        return result
    detected = [t for t, r in records if r.get("event") == "fault_detected" and t >= onset - 1e-9]
    result.detected_s = round(detected[0], 4) if detected else None
    transitions = [(t, str(r.get("state")), str(r.get("transition"))) for t, r in records
                   if r.get("event") == "state_entered"]
    window = recovery_window(transitions, onset, end_s)
    result.recovery_window_s = None if window is None else [window[0], window[1], window[2]]
    safe = [(t, s) for t, s in entered if s in SAFE_STATES and t >= onset - 1e-9]
    if safe:
        ref, bound = _first_bound(spec, result, rec, t0_ns, safe[0][0])
        if ref is None or ref > safe[0][0]:  # safe before any fault was detectable: not bounded
            ref, bound = onset, None
        if spec.second_kind is not None and not spec.recovery:
            result.latency_bound_ms = bound if bound is not None else result.latency_bound_ms
        _judge_safe_state(result, safe[0], ref, bound, (t0_ns, entered, end_s), rec, operator)
    else:
        _judge_tolerated(result)
    if spec.second_kind is not None:
        judge_second(spec, result, rec, (t0_ns, entered, end_s), operator)
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
