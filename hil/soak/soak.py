"""``hil soak``: run the simulated procedure in real time, keep it in compensation, and measure
the servo loop that commands the arm at the robot's rate (125 Hz CB3, 500 Hz e-Series) in its own
process (hil/servo): period jitter, late periods, frame-to-command latency, memory growth, and what
the OS granted the loop (``rt_granted``).

Definitions (the servo loop's own wake-up times on the monotonic clock; hil/servo/figures.py):

- *servo interval*: time between two consecutive periods of the loop, counted from the first
  entry into COMPENSATE to the end (the warm-up before is left out); nominal ``T = 1 / rate``.
- *jitter*: ``|interval - T|`` over all those intervals (10 µs histogram bins, ±5 µs).
- *missed deadline*: an interval longer than ``2 T`` (a period passed without the loop running);
  ``longest_gap_ms`` is the worst.
- *frame-to-command latency*: exposure time of a stereo pair -> the first servo command the loop
  computed from that pair's setpoint. ``frame_to_setpoint_ms``: its supervisor part, the exposure
  -> the pair's setpoint handed to the loop (the rest is the wait for the loop's next period and
  that period's work). ``setpoint_us``: the setpoint work inside it, per pair (the predictor's
  update and the setpoint; hil/controller/cost.py), under ``predictor``: what a predictor adds
  to the path, measured in the run rather than by differencing two runs' latencies.
  ``change_fit_us``: the change estimator's and the target model's time per registered pair
  (``estimator``). ``pair_model_us``: per compensation pair, that pair's change estimate and
  setpoint work added: what the three together put on the path (the two parts' p99s added
  overstate it, their slow pairs being different pairs); its p99 against the defaults' is the
  growth issue 41 bounds.
- *memory growth*: resident set size of the supervisor (``rss_mb``), of the servo process
  (``servo_rss_mb``) and of the perception process (``perception_rss_mb``, when it runs), sampled
  once a second. ``growth``: the median of the last window minus the median of the first window
  after the warm-up (the first quarter of the compensation time, at most 30 s); a window is 60 s,
  or a quarter of the compensation time when shorter. Medians, because the heap trim
  (hil/heap.py, every 10 s) makes the resident size a saw-tooth around what is really held: a
  single sample catches a tooth. ``end`` - ``after_warmup`` are the raw samples; the
  least-squares slope over everything after the warm-up. ``heap_by_minute`` says where the
  supervisor's memory is (glibc, CPython, mappings by kind), ``file_rss_growth`` which mapped files'
  resident pages grew after the warm-up (code paged in for the first time: hil/soak/heapmap.py).
- ``locate_ms``: p50 / p95 of the time to locate one pair's markers (where it ran).
- ``camera_latency_ms``: p50 / p99 of the camera's own latency, the left exposure -> the camera
  handed the pair over (measured in the perception process; empty when perception ran in the
  supervisor). ``latency_bound_ms``: the frame-to-command bound it implies (issue 45), ``p50`` =
  camera p50 + locate p50 + one servo period (``1 / rate``: the wait for the loop's next period,
  8 ms at 125 Hz, 2 ms at 500 Hz) + :data:`LATENCY_HANDOVER_MS` (the supervisor's hand-over), and
  ``p99`` = that + :data:`LATENCY_P99_MARGIN_MS`.
- ``stream_deadlines_missed``, ``frame_boundaries``, ``frame_boundary_missed``,
  ``frame_boundary_ms``: figures of the former in-thread stream, kept in the JSON for comparison
  with older runs; with the servo process the loop never waits for a frame, and they are 0 / empty.
- ``limit_violations``: servo steps the loop's merged limit check refused (none reaches the driver;
  the controller faults on each).
- ``transient_faults`` (with ``--faults-every S``): a transient fault injected into the simulated
  devices every S seconds (cycling through :data:`TRANSIENT_FAULTS`); for each, its onset (s after
  the devices opened) and the fault records it explains: it is *detected* when a fault is recorded
  from a second before its onset (the devices open up to a second apart) to a second after its
  window ends, else ``tolerated``; a detected fault explains every fault record from then until
  the procedure is compensating again (else until the next fault's onset). ``detected`` is the
  first reason naming the faulted device, else the first reason at all; ``reasons`` every distinct
  one (a frame drop is reported by the camera watchdog and by the grab's timeout);
  ``back_in_compensation_s`` how long after the onset the procedure was compensating again (None
  if it never came back, or if it was tolerated). The last fault leaves at least one period
  before the soak's planned end.
- ``unexplained_faults``: fault reasons no injected fault explains; any one fails the soak.
- The soak operator confirms every prompt, resumes after every fault, and registers again (pause,
  then start) when the gate stays shut for :data:`REREGISTER_AFTER_GATE_S` — the patient moved
  since registration; ``reregistrations`` counts those. After a protective stop it first unlocks
  the arm at the pendant (:mod:`hil.soak.pendant`), as an operator does, pressing unlock again
  every half second while the arm refuses (its stop not yet over), and resumes once the pendant
  no longer shows the stop (half a second after the press that took, or later): ``unlocks`` and
  ``unlocks_refused`` count those presses (a resume while the arm is still locked, or still
  reads locked, would fault the procedure a second time).
- ``following_peak_mm``: the largest following error the servo loop measured
  (hil/safety/following.py), and ``following_faults``.
- ``late_causes``: where late intervals came from, as the servo process timed each period after
  its first 100: ``woke_late`` periods it woke more than a period after their deadline (the OS or
  the host did not run the loop), ``overran`` periods whose work ran more than a period past the
  next deadline (wall time: a preemption during the work counts here), of those ``overran_off_cpu``
  the ones during whose work the loop thread was off its CPU for more than a period (wall time
  its CPU clock did not see: the host or the OS took the CPU, or a driver call blocked), all in
  compensation; and
  ``longest_wake_delay_ms``, ``longest_step_ms`` (wall), ``longest_step_cpu_ms`` (the thread's
  CPU time), ``longest_off_cpu_ms`` (off its CPU during one step), ``longest_overrun_ms`` since
  the servo process started (its warm-up periods left out).
- ``host_steal_percent`` and ``steal_free``: what the hypervisor took of the loop's CPU, and the
  late intervals over the windows it took none (hil/soak/host.py).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from hil.clock import MonotonicClock
from hil.config import build_devices, load_setup
from hil.config.faults import FaultKind, FaultSpec
from hil.config.setup import SetupConfig
from hil.config.simulation import RigErrorsConfig
from hil.controller.controller import Controller
from hil.controller.fsm import Event, State
from hil.controller.gate import REREGISTER_ADVICE
from hil.controller.operator_input import OperatorView
from hil.controller.perception import StereoMarkerLocator
from hil.controller.plan_file import load_plan
from hil.errors import InputFileError
from hil.perception.process import PerceptionProcess
from hil.servo.client import ServoRobot
from hil.servo.figures import LoopFigures, loop_figures
from hil.session.log import SessionLog
from hil.soak.attribution import fault_outcomes, unexplained_faults
from hil.soak.heapmap import HeapBreakdown, file_growth
from hil.soak.pendant import Pendant, RobotPendant
from hil.soak.sampler import Sampler
from hil.soak.viewer import check_viewer_target, close_soak_viewer, follow_truth, open_devices_and_viewer

Progress = Callable[[str], None]

#: The documented bound on late intervals (docs/benchmarks.md), a share of all intervals: with
#: SCHED_FIFO and a pinned CPU granted, and without. A figure to print beside the measurement, not
#: a pass/fail of the soak: on a virtual machine the host's steal (``host_steal_percent``) adds
#: late periods no setting in the guest can prevent.
LATE_FRACTION_BOUND_RT = 0.005
LATE_FRACTION_BOUND = 0.05

#: Frame-to-command latency allowed beyond the camera's own latency, the marker location and one
#: servo period, ms: the supervisor's hand-over (issue 45's bound: p50 within camera latency +
#: locate time + one servo period + 2 ms, p99 within that + 10 ms; issue 16's left out the period,
#: which a 125 Hz loop's 8 ms cannot fit in). A figure printed beside the measurement, not a
#: pass/fail of the soak.
LATENCY_HANDOVER_MS = 2.0
LATENCY_P99_MARGIN_MS = 10.0

#: The transient faults ``--faults-every`` cycles through: kind, window length (s) — the simulator
#: tier's profiles (hil/campaign/scenarios.py) for a camera, a robot link and a robot safety fault.
TRANSIENT_FAULTS: tuple[tuple[FaultKind, float], ...] = (
    (FaultKind.FRAME_DROP, 0.6),
    (FaultKind.ROBOT_DISCONNECT, 0.6),
    (FaultKind.PROTECTIVE_STOP, 0.6),
    (FaultKind.OCCLUSION, 1.0),
    (FaultKind.MOTION_LAG, 1.5),
)


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
    #: p50/p99/max of the exposure -> the setpoint handed to the loop, ms (module doc)
    frame_to_setpoint_ms: dict[str, float | None] = field(default_factory=dict)
    #: ``[procedure.compensation] predictor`` of the run
    predictor: str = ""
    #: COMPENSATE's setpoint work per pair: count, p50_us / p99_us / max_us (module doc)
    setpoint_us: dict[str, float | int | None] = field(default_factory=dict)
    #: ``[procedure.compensation] estimator`` of the run, and its time per registered pair
    #: (count, p50_us / p99_us / max_us; hil/controller/cost.py)
    estimator: str = ""
    change_fit_us: dict[str, float | int | None] = field(default_factory=dict)
    #: per compensation pair, its change estimate and its setpoint work added (module doc)
    pair_model_us: dict[str, float | int | None] = field(default_factory=dict)
    #: the supervisor's heap trims (hil/heap.py): trims, released, max_ms, total_ms
    heap_trim: dict[str, float | int] = field(default_factory=dict)
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
    #: protective stops the operator unlocked at the pendant before resuming; unlock presses refused
    unlocks: int = 0
    unlocks_refused: int = 0
    session_log: str = ""
    #: what the OS granted the servo process (hil.servo.rt.RtGranted as a dict)
    rt_granted: dict[str, Any] = field(default_factory=dict)
    #: the CPUs the supervisor (and the perception process it started) kept to, off the loop's
    #: (``[servo] reserve_cpu``); None: every CPU
    supervisor_cpus: list[int] | None = None
    servo_rss_mb: dict[str, float | None] = field(default_factory=dict)
    #: periods the loop ran on a stale setpoint (bringing the arm to rest), and other loop counts
    stale_periods: int = 0
    read_errors: int = 0
    command_errors: int = 0
    #: stop requested by the supervisor -> the loop issued it, ms (every stop of the run)
    stop_to_command_ms: dict[str, float | None] = field(default_factory=dict)
    #: the injected transient faults and what became of each (module doc)
    transient_faults: list[dict[str, Any]] = field(default_factory=list)
    #: fault reasons no injected fault explains (module doc): any one fails the soak
    unexplained_faults: list[str] = field(default_factory=list)
    #: times the soak operator registered again because the gate stayed shut (module doc)
    reregistrations: int = 0
    following_peak_mm: float = 0.0
    following_faults: int = 0
    #: where the late intervals came from (module doc)
    late_causes: dict[str, float | int] = field(default_factory=dict)
    #: periods the loop went on with its last setpoint because the supervisor was writing the
    #: block throughout the read (a writer preempted mid-write; hil/servo/shm.py)
    setpoint_busy_periods: int = 0
    #: memory of the perception process as ``rss_mb`` (empty: perception ran in the supervisor)
    perception_rss_mb: dict[str, float | None] = field(default_factory=dict)
    #: p50 / p95 of the time to locate the markers of one pair, ms (in the perception process when
    #: it runs, else the supervisor's locator)
    locate_ms: dict[str, float | None] = field(default_factory=dict)
    #: p50 / p99 of the camera's exposure -> hand-over latency, ms (module doc; perception process)
    camera_latency_ms: dict[str, float | None] = field(default_factory=dict)
    #: the frame-to-command bound from the camera and locate figures, p50 / p99, ms (module doc)
    latency_bound_ms: dict[str, float | None] = field(default_factory=dict)
    #: the supervisor's RSS (MB) at each whole minute after compensation first started: tells a
    #: one-off step (the C heap keeping the high-water mark of the first full-frame re-acquisition
    #: after a fault) from a steady growth
    rss_mb_by_minute: list[float] = field(default_factory=list)
    #: the perception process's RSS (MB) at each whole minute, as ``rss_mb_by_minute``
    perception_rss_mb_by_minute: list[float] = field(default_factory=list)
    #: where the supervisor's memory is, once a minute (hil/soak/heapmap.py ``HeapBreakdown``
    #: fields, MB, plus ``t_min``: minutes from compensation's first start, negative before it)
    heap_by_minute: list[dict[str, float | int | None]] = field(default_factory=list)
    #: the supervisor's mapped files whose resident pages grew by 64 kB or more after the warm-up
    #: (hil/soak/heapmap.py ``file_growth``: ``file``, ``kb``, ``first_grew_min``): library code
    #: paged in for the first time shows here, not in the heap's figures
    file_rss_growth: list[dict[str, str | int | float]] = field(default_factory=list)
    #: the camera was grabbed, rendered and located in the perception process (else in the
    #: supervisor)
    perception_process: bool = False
    #: the simulated camera's frame clock against the host's, ppm (``[simulation.rig_errors]
    #: camera_clock_rate_error_ppm``; :data:`SOAK_CAMERA_CLOCK_PPM` unless given or the setup's)
    camera_clock_ppm: float = 0.0
    #: the servo process's CPU use in compensation, % of one CPU: near the kernel's RT cap
    #: (``rt_granted.rt_cpu_cap``) the loop is throttled, paused for the rest of each second
    servo_cpu_percent: float | None = None
    #: the host's steal in compensation, % of wall time (hil/soak/host.py): ``loop_cpu`` of the
    #: CPU the servo loop was pinned to (absent when it was not pinned), ``all_cpus`` the mean of
    #: all; empty where /proc/stat cannot be read. Late periods on a host that took the loop's
    #: CPU measure the host, not the loop.
    host_steal_percent: dict[str, float | None] = field(default_factory=dict)
    #: the late intervals over the windows in which the host took none of the loop's CPU
    #: (hil.soak.host.StealFreeFigures as a dict; empty where /proc/stat cannot be read): what
    #: the documented bound judges
    steal_free: dict[str, Any] = field(default_factory=dict)
    #: the live viewer's figures with ``--viewer`` (hil.soak.viewer.close_soak_viewer: counts,
    #: ``hook_ms`` p50 / p99 / max: the time the plugin adds to a supervisor tick); empty without
    viewer: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def late_fraction_bound(self) -> float:
        """The documented bound on the late share (``steal_free["late_fraction"]``) for what the OS
        granted this run."""
        return LATE_FRACTION_BOUND_RT if self.rt_granted.get("realtime") else LATE_FRACTION_BOUND

    def passed(self) -> bool:
        """Compensated, no refused step, no fault that the injected ones do not explain, and back
        in compensation after every injected fault that was detected."""
        detected = [f for f in self.transient_faults if f["detected"] != "tolerated"]
        came_back = all(f["back_in_compensation_s"] is not None for f in detected)
        return bool(self.compensate_s > 0 and not self.limit_violations and came_back
                    and not self.unexplained_faults)


#: How long the soak operator waits in GATE for the breath-hold gate to open before it pauses
#: and re-registers, s. The simulated breathing cycle is about 4 s and an open gate needs 1 s of
#: stillness, so a gate shut this long means the patient moved since registration (the simulated
#: patient drifts 3 mm on the table in the first 150 s of configs/sim.toml): what an operator
#: does then is register again.
REREGISTER_AFTER_GATE_S = 30.0


class SoakOperator:
    """Starts, confirms, resumes after a pause or fault, re-registers when the gate stays shut for
    ``reregister_after_s`` (pause, then start: PAUSED -> REGISTER) or when a pause's reason advises
    it (:data:`~hil.controller.gate.REREGISTER_ADVICE`: the patient moved), and ends the run ``soak_s`` of
    wall time after the procedure first entered COMPENSATE (or after ``give_up_s`` without
    reaching it)."""

    def __init__(self, soak_s: float, give_up_s: float, sample: Callable[[], None],
                 on_compensate: Callable[[], None] | None = None,
                 progress: Callable[[str], None] | None = None, progress_every_s: float = 30.0,
                 reregister_after_s: float = REREGISTER_AFTER_GATE_S, pendant: Pendant | None = None) -> None:
        self.reregister_after_s = reregister_after_s
        #: the robot's pendant: a protective stop is unlocked there before the resume (None: never)
        self.pendant = pendant
        #: protective stops unlocked at the pendant, and unlock presses the arm refused
        self.unlocks = 0
        self.unlocks_refused = 0
        #: re-registrations: the gate stayed shut, or a pause advised it
        self.reregistrations = 0
        self._gate_since: float | None = None
        self._reregister = False
        self.on_compensate = on_compensate
        self.progress = progress
        self.progress_every_s = progress_every_s
        self._last_progress = time.monotonic()
        self.soak_s = soak_s
        self.give_up_s = give_up_s
        self.sample = sample
        self.t_start = time.monotonic()
        self.t_comp: float | None = None
        self.resumes = 0
        self._started = False
        self._last_halt_t: float | None = None
        self._tried_resume = False

    def poll(self, view: OperatorView) -> Event | None:
        now = time.monotonic()
        if view.state is State.COMPENSATE and self.t_comp is None:
            self.t_comp = now
            if self.on_compensate is not None:
                self.on_compensate()
        if self.progress is not None and now - self._last_progress >= self.progress_every_s:
            self._last_progress = now
            done = 0.0 if self.t_comp is None else now - self.t_comp
            self.progress(f"soak: {done:.0f} of {self.soak_s:.0f} s in compensation; "
                          f"state {view.state.value}, {self.resumes} resume(s)")
        self.sample()
        if not self._started and view.state is State.IDLE:
            self._started = True
            return Event.START_REQUESTED
        if view.pending is not None:
            return Event.CONFIRM_REQUESTED
        if self._gate_shut_too_long(view.state, now):
            return Event.PAUSE_REQUESTED
        if view.state is State.COMPENSATE:
            self._reregister = False   # the gate opened after all (the pause came too late)
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
        if view.state is State.PAUSED and (self._reregister or REREGISTER_ADVICE in view.last_reason):
            # the gate stayed shut, or the controller says the body no longer matches the
            # registration (the patient moved): register again rather than resume into the pause
            if not self._reregister:
                self.reregistrations += 1
            self._reregister = False
            return Event.START_REQUESTED   # PAUSED -> REGISTER
        if not self._unlocked():
            return None                    # still locked: press unlock again in a while
        self.resumes += 1
        if view.state is State.IDLE:
            return Event.START_REQUESTED
        if not self._tried_resume:
            self._tried_resume = True
            return Event.RESUME_REQUESTED
        self._tried_resume = False  # resume refused (no plan yet): start over
        return Event.RESET_REQUESTED if view.state is State.FAULT else Event.START_REQUESTED

    def _unlocked(self) -> bool:
        """Before a resume: when the pendant shows a protective stop, press unlock (once per call,
        so at most once per settling time); True when the pendant shows no stop. After an unlock
        that took, the resume waits for the next call: the arm's status read right after the
        press may still be the stop's, and a resume on it faults again ("robot is in
        protective_stop" on entering APPROACH: seen twice in the hour's soak)."""
        if self.pendant is None or not self.pendant.protective_stop():
            return True
        why = self.pendant.unlock()
        if why:
            self.unlocks_refused += 1
            if self.progress is not None:
                self.progress(f"soak: unlock refused at the pendant ({why}); trying again")
            return False
        self.unlocks += 1
        return False

    def _gate_shut_too_long(self, state: State, now: float) -> bool:
        """True once per ``reregister_after_s`` spent in GATE without a break (then the operator
        pauses and, once paused, starts a new registration)."""
        if state is not State.GATE:
            self._gate_since = None
            return False
        if self._gate_since is None:
            self._gate_since = now
            return False
        if now - self._gate_since < self.reregister_after_s:
            return False
        self._gate_since = None
        self._reregister = True
        self.reregistrations += 1
        if self.progress is not None:
            self.progress(f"soak: the gate stayed shut for {self.reregister_after_s:g} s; "
                          "pausing to register again")
        return True

    def finished(self, view: OperatorView) -> bool:
        now = time.monotonic()
        if self.t_comp is not None:
            return now - self.t_comp >= self.soak_s
        return view.state is State.DONE or now - self.t_start > self.give_up_s


def transient_schedule(minutes: float, every_s: float, warmup_s: float = 60.0) -> tuple[FaultSpec, ...]:
    """A fault from :data:`TRANSIENT_FAULTS` every ``every_s`` seconds, the first ``warmup_s``
    (at least one period) after the devices open, cycling through the kinds, until the end of
    ``minutes`` of compensation (plus the time to reach it, about 15 s)."""
    if not every_s > 0:
        return ()
    out: list[FaultSpec] = []
    t = max(warmup_s, every_s)
    while t + every_s <= minutes * 60.0 + 15.0:   # each fault gets a whole period to recover
        kind, duration_s = TRANSIENT_FAULTS[len(out) % len(TRANSIENT_FAULTS)]
        out.append(FaultSpec(kind=kind, start_s=round(t, 3), duration_s=duration_s))
        t += every_s
    return tuple(out)


#: The simulated camera's clock rate error a soak runs with unless told or the setup has one, ppm.
#: A real camera's frame clock is its own crystal's (tens of ppm off the host's); a simulated one
#: exactly on the host's clock keeps every pair at the same phase of the servo periods for the
#: whole soak (33.3 ms against 2 ms: three phases), so the wait for the loop's next period, and
#: with it the frame -> command figure, would depend on the phase the loop happened to start at.
#: At 50 ppm the phase sweeps a servo period about every 40 s, as on a rig.
SOAK_CAMERA_CLOCK_PPM = 50.0


def soak_camera_clock_ppm(setup: SetupConfig, asked: float | None) -> float:
    """The camera clock rate error a soak runs with (ppm): ``asked`` when given (0: the camera
    on the host's clock), else the setup's when it has one, else :data:`SOAK_CAMERA_CLOCK_PPM`."""
    if asked is not None:
        return asked
    own = setup.simulation.rig_errors.camera_clock_rate_error_ppm
    return own if own != 0.0 else SOAK_CAMERA_CLOCK_PPM


def soak_setup(setup: SetupConfig, rate_hz: float, minutes: float, realtime: bool = True,
               faults: tuple[FaultSpec, ...] = (), perception_process: bool = False,
               camera_clock_ppm: float | None = None) -> SetupConfig:
    """The setup in real time, at ``rate_hz``, staying in compensation (never settles into lock),
    with the servo loop in its own process (real-time scheduling asked for when ``realtime``),
    grabbing, rendering and locating in the supervisor (``perception_process``: in the perception
    process, ``[perception] process = "on"``, on any number of CPUs; a setup that cannot run it,
    e.g. with a needle check, is a ConfigError naming why), the camera's clock off the host's by
    :func:`soak_camera_clock_ppm` and only the given faults (none by default: the setup's own are
    left out)."""
    robot = setup.robot.model_copy(update={"control_rate_hz": rate_hz})
    proc = setup.procedure
    comp = proc.compensation.model_copy(update={"settle_s": 1e6, "timeout_s": 1e6})
    gate = proc.gate.model_copy(update={"timeout_s": 1e6})
    procedure = proc.model_copy(
        update={"compensation": comp, "gate": gate, "max_duration_s": minutes * 60.0 + 600.0}
    )
    try:   # validated (model_copy would not): the value may come from the command line
        errors = RigErrorsConfig.model_validate(
            {**setup.simulation.rig_errors.model_dump(),
             "camera_clock_rate_error_ppm": soak_camera_clock_ppm(setup, camera_clock_ppm)})
    except ValidationError as exc:
        raise InputFileError("--camera-clock-ppm", exc.errors()[0]["msg"]) from None
    sim = setup.simulation.model_copy(update={"real_time": True, "rig_errors": errors})
    servo = setup.servo.model_copy(update={"process": "on", "realtime": realtime})
    perception = setup.perception.model_copy(update={"process": "on" if perception_process else "off"})
    return setup.model_copy(update={"robot": robot, "procedure": procedure, "simulation": sim,
                                    "faults": faults, "servo": servo, "perception": perception})


def _check_arguments(minutes: float, rate_hz: float, faults_every_s: float) -> None:
    """Raises InputFileError naming the option for a bad one."""
    if not minutes > 0:
        raise InputFileError("--minutes", f"must be > 0, got {minutes}")
    if not (faults_every_s == 0 or faults_every_s >= 10.0):
        raise InputFileError("--faults-every", f"must be 0 (none) or at least 10 s, got {faults_every_s:g}")
    if rate_hz not in (125.0, 500.0):
        raise InputFileError("--rate", f"must be 125 (CB3) or 500 (e-Series), got {rate_hz:g}")


def run_soak(
    minutes: float,
    rate_hz: float,
    *,
    config: Path,
    plan: str | None,
    session_dir: Path,
    realtime: bool = True,
    progress: Progress | None = None,
    faults_every_s: float = 0.0,
    perception_process: bool = False,
    camera_clock_ppm: float | None = None,
    viewer: str | None = None,
) -> SoakResult:
    """Run the soak (blocking, ``minutes`` of compensation plus the time to reach it). The servo
    process is started and stopped here (the arm is stopped on every path). ``faults_every_s`` >
    0: a transient fault that often (module doc). ``perception_process``: grab, render and locate
    in the perception process (unless the setup cannot: ``perception_in_process`` says why), else
    in the supervisor. ``camera_clock_ppm``: :func:`soak_camera_clock_ppm`. ``viewer`` (a ``.rrd``
    path or a Rerun viewer address): the live viewer plugin streams the soak, its cost in
    ``SoakResult.viewer`` (:mod:`hil.soak.viewer`); closed on every path.

    Raises:
        InputFileError: a bad argument (or ``viewer`` in a missing directory); ConfigError /
        InputFileError from the config and plan; DriverError when the servo process cannot start;
        ViewerUnavailableError: ``viewer`` without rerun-sdk.
    """
    _check_arguments(minutes, rate_hz, faults_every_s)
    check_viewer_target(viewer)
    say = progress or (lambda _m: None)
    base = load_setup(config)
    schedule = transient_schedule(minutes, faults_every_s)
    setup = soak_setup(base, rate_hz, minutes, realtime, schedule, perception_process, camera_clock_ppm)
    plan_path = Path(plan) if plan else config.resolve().parent / "plans" / f"{config.stem}_plan.json"
    procedure_plan = load_plan(plan_path)
    clock = MonotonicClock()
    t_open_ns = clock.now_ns()
    from hil.controller.assembly import (  # what `hil run` builds
        build_controller,
        with_perception_process,
        with_servo_process,
    )

    devices = with_servo_process(setup, build_devices(setup, clock), clock)
    devices = with_perception_process(setup, devices, clock)
    feed = process if isinstance(process := devices.camera.perception_feed, PerceptionProcess) else None
    robot = devices.robot
    assert isinstance(robot, ServoRobot)
    session = _soak_session(session_dir, clock, config, minutes, rate_hz, realtime)
    sampler = Sampler(robot, None if feed is None else lambda: feed.pid)
    operator = _soak_operator(minutes, sampler, say, robot)
    live, hooks = open_devices_and_viewer(devices, viewer)
    try:
        say(f"soak: {minutes:g} min of compensation at {rate_hz:g} Hz (real time); servo process: "
            f"{robot.rt.summary() if robot.rt else 'n/a'}")
        ctl = build_controller(setup, procedure_plan, devices, clock=clock, session=session,
                               operator=operator, hooks=hooks)
        follow_truth(live, ctl)
        summary = ctl.run()
        end = sampler.finish()   # before the servo process ends
    except BaseException as exc:   # Ctrl-C, SIGTERM: the log still ends with session_closed
        devices.close_all()
        close_soak_viewer(live)
        session.close(final_state="interrupted" if isinstance(exc, KeyboardInterrupt) else "error",
                      ended_by=type(exc).__name__)
        raise
    devices.close_all()
    viewer_figures = close_soak_viewer(live)
    session.close(final_state=summary.final_state)
    figs = loop_figures(sampler.start or end.stats, end.stats, 1.0 / rate_hz)
    res = analyse(rate_hz, minutes, figs, ctl, operator, sampler.rss, summary.final_state, summary.states,
                  summary.faults, str(session.path))
    res.servo_cpu_percent, res.host_steal_percent, res.steal_free = end.cpu_percent, end.steal, end.steal_free
    res.following_peak_mm, res.following_faults = figs.following_peak_mm, figs.following_faults
    _add_fault_outcomes(res, schedule, str(session.path), t_open_ns, feed)
    _add_process_figures(res, robot, feed, ctl, sampler, operator, minutes)
    comp = setup.procedure.compensation
    res.camera_clock_ppm = setup.simulation.rig_errors.camera_clock_rate_error_ppm
    res.predictor, res.estimator, res.viewer = comp.predictor, comp.estimator, viewer_figures
    return res


def _add_fault_outcomes(res: SoakResult, schedule: tuple[FaultSpec, ...], session_log: str, t_open_ns: int,
                        feed: PerceptionProcess | None) -> None:
    """What became of each injected fault, and the faults none explains (hil/soak/attribution.py)."""
    # the perception process opens its own camera, after the robot: its faults count from then
    info = None if feed is None else feed.ready_info
    opened = {} if info is None else {"camera": info.opened_ns}
    res.transient_faults = fault_outcomes(schedule, session_log, t_open_ns, opened)
    res.unexplained_faults = unexplained_faults(schedule, session_log, t_open_ns, opened)


def _soak_session(session_dir: Path, clock: MonotonicClock, config: Path, minutes: float, rate_hz: float,
                  realtime: bool) -> SessionLog:
    """The soak's session log (``soak_<time>_<pid>.jsonl`` in ``session_dir``)."""
    return SessionLog(
        session_dir / f"soak_{time.strftime('%Y%m%dT%H%M%S')}_{os.getpid()}.jsonl",
        clock,
        {"setup": str(config), "soak_minutes": minutes, "rate_hz": rate_hz, "realtime": realtime},
    )


def _soak_operator(minutes: float, sampler: Sampler, say: Callable[[str], None],
                   robot: ServoRobot) -> SoakOperator:
    """The soak's operator: ``minutes`` of compensation, sampling with ``sampler``, reporting with
    ``say``, at the pendant of ``robot`` (its state read without taking the controller's errors)."""
    return SoakOperator(minutes * 60.0, give_up_s=120.0, sample=sampler.sample,
                        on_compensate=sampler.on_compensate, progress=say,
                        pendant=RobotPendant(robot.state_view(), robot.recover))


def _add_process_figures(res: SoakResult, robot: ServoRobot, feed: PerceptionProcess | None,
                         ctl: Controller, sampler: Sampler, operator: SoakOperator, minutes: float) -> None:
    """What the servo and perception processes were granted and measured, and the operator's
    re-registrations, into ``res``."""
    res.rt_granted = robot.rt.to_dict() if robot.rt is not None else {}
    ready = robot.link.ready
    moved = None if ready is None else ready.supervisor_cpus
    res.supervisor_cpus = None if moved is None else sorted(moved)
    res.reregistrations = operator.reregistrations
    res.unlocks, res.unlocks_refused = operator.unlocks, operator.unlocks_refused
    res.stop_to_command_ms = _stats([x * 1e-6 for x in robot.stop_latency_ns])
    res.perception_rss_mb = _rss_figures(sampler.perception_rss, operator.t_comp, minutes)
    res.perception_process = feed is not None
    res.perception_rss_mb_by_minute = rss_by_minute(sampler.perception_rss, operator.t_comp)
    res.heap_by_minute = heap_by_minute(sampler.heap, operator.t_comp)
    t_comp = operator.t_comp
    if t_comp is not None:
        res.file_rss_growth = file_growth(sampler.heap, _warm_until(t_comp, minutes), t_comp)
    if feed is not None:
        res.locate_ms = feed.locate_figures()
        res.camera_latency_ms = feed.delivery_figures()
        res.latency_bound_ms = latency_bound(res.camera_latency_ms, res.locate_ms, 1e3 / res.rate_hz)
    elif isinstance(ctl.locate, StereoMarkerLocator):
        res.locate_ms = ctl.locate.locate_ms()


def latency_bound(camera_ms: dict[str, float | None], locate_ms: dict[str, float | None],
                  servo_period_ms: float) -> dict[str, float | None]:
    """The frame-to-command bound (module doc), ms: camera p50 + locate p50 + ``servo_period_ms``
    + :data:`LATENCY_HANDOVER_MS` as ``p50``, that + :data:`LATENCY_P99_MARGIN_MS` as ``p99``;
    empty when the camera's or the locator's p50 is unknown."""
    cam, loc = camera_ms.get("p50"), locate_ms.get("p50")
    if cam is None or loc is None:
        return {}
    p50 = cam + loc + servo_period_ms + LATENCY_HANDOVER_MS
    return {"p50": round(p50, 3), "p99": round(p50 + LATENCY_P99_MARGIN_MS, 3)}


def _warm_until(t0: float, minutes: float) -> float:
    """The end of the memory figures' warm-up (monotonic s): the first quarter of the compensation
    time from ``t0``, at most 30 s (module doc)."""
    return t0 + min(30.0, 0.25 * minutes * 60.0)


def _rss_figures(rss: list[tuple[float, float]], t_comp: float | None,
                 minutes: float) -> dict[str, float | None]:
    if not rss:
        return {}
    t0 = t_comp or rss[0][0]
    warm = _warm_until(t0, minutes)
    after = [(t, m) for t, m in rss if t >= warm] or rss[-1:]
    slope = None
    if len(after) >= 3:
        ts = np.array([t for t, _ in after]) / 60.0
        ms = np.array([m for _, m in after])
        slope = round(float(np.polyfit(ts - ts[0], ms, 1)[0]), 4)
    window_s = min(60.0, 0.25 * minutes * 60.0)
    first = [m for t, m in after if t < after[0][0] + window_s]
    last = [m for t, m in after if t > after[-1][0] - window_s]
    return {
        "start": round(rss[0][1], 2),
        "after_warmup": round(after[0][1], 2),
        "end": round(rss[-1][1], 2),
        "growth": round(float(np.median(last)) - float(np.median(first)), 2),
        "window_s": window_s,
        "slope_mb_per_min": slope,
    }


def analyse(
    rate_hz: float,
    minutes: float,
    figs: LoopFigures,
    ctl: Controller,
    operator: SoakOperator,
    rss: list[tuple[float, float, float]],
    final_state: str,
    states: list[str],
    faults: list[str],
    session_log: str,
) -> SoakResult:
    """The soak figures from the servo loop's figures of the compensation window (module doc);
    ``rss``: (monotonic s, supervisor MB, servo process MB) samples."""
    res = SoakResult(
        rate_hz,
        minutes,
        final_state=final_state,
        states=states,
        faults=faults,
        resumes=operator.resumes,
        session_log=session_log,
    )
    if operator.t_comp is not None:
        res.compensate_s = round(time.monotonic() - operator.t_comp, 3)
    res.servo_commands = figs.commands
    res.limit_violations = figs.refusals
    res.intervals = figs.intervals
    res.period_ms = figs.period_ms
    res.jitter_ms = figs.jitter_ms
    res.missed_deadlines = figs.late
    res.missed_fraction = figs.late_fraction
    res.longest_gap_ms = figs.longest_ms
    res.late_causes = {"woke_late": figs.late_wakes, "overran": figs.overruns,
                       "overran_off_cpu": figs.overruns_off_cpu,
                       "longest_wake_delay_ms": figs.wake_late_max_ms, "longest_step_ms": figs.step_max_ms,
                       "longest_step_cpu_ms": figs.step_cpu_max_ms,
                       "longest_off_cpu_ms": figs.step_off_cpu_max_ms,
                       "longest_overrun_ms": figs.overrun_max_ms}
    res.frame_to_command_ms = figs.latency_ms
    res.stale_periods, res.read_errors, res.command_errors = figs.stale_periods, figs.read_errors, \
        figs.command_errors
    res.setpoint_busy_periods = figs.setpoint_busy
    res.stream_deadlines_missed = ctl.servo_deadlines_missed
    res.compensation_frames = len(ctl.latency_ms)
    res.frame_to_setpoint_ms = _stats(list(ctl.latency_ms))
    if ctl.latency_ms:   # beyond the series' capacity its percentiles are estimates; the max is exact
        res.frame_to_setpoint_ms["max"] = round(float(ctl.latency_ms.max or 0.0), 4)
    costs = ctl.pair_costs
    res.setpoint_us, res.change_fit_us = costs.setpoint.to_dict(), costs.change_fit.to_dict()
    res.pair_model_us = costs.pair_model.to_dict()
    res.heap_trim = ctl.heap.figures().to_dict()
    res.frames_overwritten = ctl.frames_overwritten
    res.rss_mb = _rss_figures([(t, m) for t, m, _ in rss], operator.t_comp, minutes)
    res.servo_rss_mb = _rss_figures([(t, m) for t, _, m in rss], operator.t_comp, minutes)
    res.rss_mb_by_minute = rss_by_minute([(t, m) for t, m, _ in rss], operator.t_comp)
    return res


def heap_by_minute(heap: list[tuple[float, HeapBreakdown]],
                   t_comp: float | None) -> list[dict[str, float | int | None]]:
    """``SoakResult.heap_by_minute`` from the sampler's (monotonic s, breakdown) readings:
    ``t_min`` counts from ``t_comp`` (None: the first reading)."""
    if not heap:
        return []
    t0 = heap[0][0] if t_comp is None else t_comp
    return [{"t_min": round((t - t0) / 60.0, 2), **b.to_dict()} for t, b in heap]


def rss_by_minute(rss: list[tuple[float, float]], t_comp: float | None) -> list[float]:
    """The first sample at or after each whole minute from ``t_comp`` (monotonic s; None: the
    first sample), MB rounded to 0.01; ``rss`` is (monotonic s, MB) in time order."""
    if not rss:
        return []
    t0 = rss[0][0] if t_comp is None else t_comp
    out: list[float] = []
    for t, mb in rss:
        if t >= t0 + 60.0 * len(out):
            out.append(round(mb, 2))
    return out
