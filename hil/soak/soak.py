"""``hil soak``: run the simulated procedure in real time and keep it in compensation, streaming
servo targets at the robot's rate (125 Hz CB3, 500 Hz e-Series), and measure the servo stream:
period jitter, missed deadlines, frame-to-command latency and memory growth.

Definitions (all on the monotonic wall clock):

- *servo interval*: time between two consecutive servo commands reaching the robot driver while
  in COMPENSATE; nominal ``T = 1 / rate``.
- *jitter*: ``|interval - T|`` of the intervals of at most ``2 T`` (longer ones are counted as
  missed deadlines instead). On the wall clock the next pair is grabbed and located in the
  controller's prefetch thread (hil/controller/prefetch.py), so the stream goes on across frames.
- *missed deadline*: an interval longer than ``2 T`` (at least one servo period passed without a
  command); ``longest_gap_ms`` is the worst.
- *stream deadlines missed*: the controller's count of servo commands of a frame's stream that
  were late by more than a period (the stream keeps absolute deadlines and skips those slots).
- *frame-to-command latency*: exposure time of a stereo frame -> the first servo command computed
  from it (the controller's own measurement).
- *frame boundaries*: servo intervals during which a control tick started (the operator is
  polled once per tick, before the tick takes the next pair); *frame-boundary misses*: those
  longer than ``2 T``; ``frame_boundary_ms``: their p50/p99/max. A controller that stops the
  stream to grab and process a pair misses about one per frame; one that streams on while the
  pair is prefetched only when the tick's own work is longer than two periods.
- *compensation frames*: stereo pairs the controller processed in COMPENSATE (each restarts the
  stream on a new estimate); *frames overwritten*: pairs the prefetcher replaced by a newer one
  before the control thread took them.
- *memory growth*: resident set size (``/proc/self/statm``) at the end minus after the warm-up
  (the first quarter of the compensation time, at most 30 s), and its least-squares slope.
"""

from __future__ import annotations

import os
import time
from array import array
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil.campaign.recorder import RecordingRobot
from hil.clock import MonotonicClock
from hil.config import build_devices, load_setup
from hil.config.setup import SetupConfig
from hil.controller.controller import Controller
from hil.controller.fsm import Event, State
from hil.controller.operator_input import OperatorView
from hil.controller.plan_file import load_plan
from hil.errors import InputFileError
from hil.session.log import SessionLog

Progress = Callable[[str], None]
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def rss_mb() -> float:
    """Resident set size of this process, MB (Linux /proc; 0 where unavailable)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * _PAGE / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


def _stats(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p99": None, "max": None}
    a = np.asarray(values)
    return {
        "p50": round(float(np.percentile(a, 50)), 4),
        "p99": round(float(np.percentile(a, 99)), 4),
        "max": round(float(a.max()), 4),
    }


@dataclass
class SoakResult:
    rate_hz: float
    minutes: float
    compensate_s: float = 0.0
    servo_commands: int = 0
    limit_violations: int = 0
    intervals: int = 0
    period_ms: dict[str, float | None] = field(default_factory=dict)
    jitter_ms: dict[str, float | None] = field(default_factory=dict)
    missed_deadlines: int = 0
    missed_fraction: float = 0.0
    longest_gap_ms: float | None = None
    #: the controller's own count: stream commands late by more than a period (slots skipped)
    stream_deadlines_missed: int = 0
    frame_to_command_ms: dict[str, float | None] = field(default_factory=dict)
    frame_boundaries: int = 0
    frame_boundary_missed: int = 0
    #: p50/p99/max of the frame-boundary intervals, ms
    frame_boundary_ms: dict[str, float | None] = field(default_factory=dict)
    compensation_frames: int = 0
    frames_overwritten: int = 0
    rss_mb: dict[str, float | None] = field(default_factory=dict)
    final_state: str = ""
    states: list[str] = field(default_factory=list)
    faults: list[str] = field(default_factory=list)
    resumes: int = 0
    session_log: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class SoakOperator:
    """Starts, confirms, resumes after a pause or fault, and ends the run ``soak_s`` of wall time
    after the procedure first entered COMPENSATE (or after ``give_up_s`` without reaching it)."""

    def __init__(self, soak_s: float, give_up_s: float, sample: Callable[[], None]) -> None:
        self.soak_s = soak_s
        self.give_up_s = give_up_s
        self.sample = sample
        self.t_start = time.monotonic()
        self.t_comp: float | None = None
        self.resumes = 0
        self._started = False
        self._last_halt_t: float | None = None
        self._tried_resume = False
        #: monotonic time of every poll, ns: one per control tick, before it takes the next pair
        self.tick_ns: array[int] = array("q")

    def poll(self, view: OperatorView) -> Event | None:
        self.tick_ns.append(time.monotonic_ns())
        now = time.monotonic()
        if view.state is State.COMPENSATE and self.t_comp is None:
            self.t_comp = now
        self.sample()
        if not self._started and view.state is State.IDLE:
            self._started = True
            return Event.START_REQUESTED
        if view.pending is not None:
            return Event.CONFIRM_REQUESTED
        halted = view.state in (State.PAUSED, State.FAULT, State.SAFE_STOP) or (
            view.state is State.IDLE and self._started
        )
        if not halted:
            self._last_halt_t = None
            self._tried_resume = False
            return None
        if self._last_halt_t is None:
            self._last_halt_t = now
        if now - self._last_halt_t < 0.5:  # let the robot stop, then carry on
            return None
        self._last_halt_t = now
        self.resumes += 1
        if view.state is State.IDLE:
            return Event.START_REQUESTED
        if not self._tried_resume:
            self._tried_resume = True
            return Event.RESUME_REQUESTED
        self._tried_resume = False  # resume refused (no plan yet): start over
        return Event.RESET_REQUESTED if view.state is State.FAULT else Event.START_REQUESTED

    def finished(self, view: OperatorView) -> bool:
        now = time.monotonic()
        if self.t_comp is not None:
            return now - self.t_comp >= self.soak_s
        return view.state is State.DONE or now - self.t_start > self.give_up_s


def soak_setup(setup: SetupConfig, rate_hz: float, minutes: float) -> SetupConfig:
    """The setup in real time, at ``rate_hz``, staying in compensation (never settles into lock)."""
    robot = setup.robot.model_copy(update={"control_rate_hz": rate_hz})
    proc = setup.procedure
    comp = proc.compensation.model_copy(
        update={"settle_s": 1e6, "timeout_s": 1e6}
    )
    gate = proc.gate.model_copy(update={"timeout_s": 1e6})
    procedure = proc.model_copy(
        update={"compensation": comp, "gate": gate, "max_duration_s": minutes * 60.0 + 600.0}
    )
    sim = setup.simulation.model_copy(update={"real_time": True})
    return setup.model_copy(update={"robot": robot, "procedure": procedure, "simulation": sim, "faults": ()})


def run_soak(
    minutes: float,
    rate_hz: float,
    *,
    config: Path,
    plan: str | None,
    session_dir: Path,
    progress: Progress | None = None,
) -> SoakResult:
    """Run the soak (blocking, ``minutes`` of compensation plus the time to reach it).

    Raises:
        InputFileError: a bad argument; ConfigError / InputFileError from the config and plan.
    """
    if not minutes > 0:
        raise InputFileError("--minutes", f"must be > 0, got {minutes}")
    if rate_hz not in (125.0, 500.0):
        raise InputFileError("--rate", f"must be 125 (CB3) or 500 (e-Series), got {rate_hz:g}")
    say = progress or (lambda _m: None)
    base = load_setup(config)
    setup = soak_setup(base, rate_hz, minutes)
    plan_path = Path(plan) if plan else config.resolve().parent / "plans" / f"{config.stem}_plan.json"
    procedure_plan = load_plan(plan_path)
    clock = MonotonicClock()
    from hil.controller.assembly import build_controller, wrap_robot  # the controller `hil run` builds

    limits = setup.safety.motion_limits()
    devices = wrap_robot(build_devices(setup, clock),
                         lambda robot: RecordingRobot(robot, limits, clock, compact=True))
    recorder = devices.robot
    assert isinstance(recorder, RecordingRobot)
    session = SessionLog(
        session_dir / f"soak_{time.strftime('%Y%m%dT%H%M%S')}_{os.getpid()}.jsonl",
        clock,
        {"setup": str(config), "soak_minutes": minutes, "rate_hz": rate_hz},
    )
    rss: list[tuple[float, float]] = []
    last = [0.0]

    def sample() -> None:
        now = time.monotonic()
        if now - last[0] >= 1.0:
            last[0] = now
            rss.append((now, rss_mb()))

    soak_s = minutes * 60.0
    operator = SoakOperator(soak_s, give_up_s=120.0, sample=sample)
    devices.open_all()
    say(f"soak: {minutes:g} min of compensation at {rate_hz:g} Hz (real time)")
    try:
        ctl = build_controller(setup, procedure_plan, devices, clock=clock, session=session,
                               operator=operator)
        summary = ctl.run()
    finally:
        devices.close_all()
    session.close(final_state=summary.final_state)
    return analyse(
        rate_hz,
        minutes,
        recorder,
        ctl,
        operator,
        rss,
        summary.final_state,
        summary.states,
        summary.faults,
        str(session.path),
    )


def analyse(
    rate_hz: float,
    minutes: float,
    recorder: RecordingRobot,
    ctl: Controller,
    operator: SoakOperator,
    rss: list[tuple[float, float]],
    final_state: str,
    states: list[str],
    faults: list[str],
    session_log: str,
) -> SoakResult:
    """Turn the recorded servo commands into the soak figures (see module doc)."""
    T_ms = 1e3 / rate_hz
    res = SoakResult(
        rate_hz,
        minutes,
        final_state=final_state,
        states=states,
        faults=faults,
        resumes=operator.resumes,
        session_log=session_log,
    )
    servo_ns = list(recorder.servo_t_ns)
    res.servo_commands = len(servo_ns)
    res.limit_violations = len(recorder.recording.violations_reached())
    if operator.t_comp is not None:
        res.compensate_s = round(time.monotonic() - operator.t_comp, 3)
    t_ns = np.asarray(servo_ns, dtype=np.int64)
    iv: np.ndarray[Any, np.dtype[np.float64]] = (
        np.diff(t_ns).astype(np.float64) * 1e-6 if len(servo_ns) > 1 else np.zeros(0)
    )
    # intervals longer than a few frames are pauses between compensation phases, not deadlines
    frame_ms = 1e3 * ctl.frame_period_s
    keep = iv < 4 * frame_ms
    ticks = np.asarray(operator.tick_ns, dtype=np.int64)
    if iv.size:
        spans_tick = (np.searchsorted(ticks, t_ns[1:], side="right")
                      - np.searchsorted(ticks, t_ns[:-1], side="right")) > 0
        boundary = spans_tick[keep]
        res.frame_boundaries = int(boundary.sum())
        res.frame_boundary_missed = int((boundary & (iv[keep] > 2 * T_ms)).sum())
        res.frame_boundary_ms = _stats([float(x) for x in iv[keep][boundary]])
    iv = iv[keep]
    res.intervals = int(iv.size)
    inside = iv[iv <= 2 * T_ms]
    res.period_ms = _stats([float(x) for x in inside])
    res.jitter_ms = _stats([float(abs(x - T_ms)) for x in inside])
    missed = iv[iv > 2 * T_ms]
    res.missed_deadlines = int(missed.size)
    res.missed_fraction = round(float(missed.size) / max(iv.size, 1), 5)
    res.longest_gap_ms = round(float(iv.max()), 3) if iv.size else None
    res.stream_deadlines_missed = ctl.servo_deadlines_missed
    res.frame_to_command_ms = _stats([float(x) for x in ctl.latency_ms])
    res.compensation_frames = len(ctl.latency_ms)
    res.frames_overwritten = ctl.frames_overwritten
    if rss:
        t0 = operator.t_comp or rss[0][0]
        warm = t0 + min(30.0, 0.25 * minutes * 60.0)
        after = [(t, m) for t, m in rss if t >= warm] or rss[-1:]
        slope = None
        if len(after) >= 3:
            ts = np.array([t for t, _ in after]) / 60.0
            ms = np.array([m for _, m in after])
            slope = round(float(np.polyfit(ts - ts[0], ms, 1)[0]), 4)
        res.rss_mb = {
            "start": round(rss[0][1], 2),
            "after_warmup": round(after[0][1], 2),
            "end": round(rss[-1][1], 2),
            "growth": round(rss[-1][1] - after[0][1], 2),
            "slope_mb_per_min": slope,
        }
    return res
