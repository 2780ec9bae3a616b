"""The Controller: one tick per stereo frame, on an injected clock, through interfaces only.

Each tick: operator input -> read devices (camera grab blocks until the next pair; robot state;
tracker) -> watchdogs and robot safety status -> perception (markers in the optical frame,
identified against the reference and the flange layout) -> the current state's step, which may
produce an event -> the state machine. Entering a state runs its entry action (a move, a stop,
a breath-hold request). Every motion command goes through :class:`hil.safety.SafetyLayer`.
Any exception from a device, the safety layer or a step becomes FAULT_DETECTED with the reason
and the robot is stopped.

Real time (the wall clock, ``procedure.camera_prefetch``): the grab and the marker location run
in a prefetch thread (:mod:`hil.controller.prefetch`) and the tick takes its result; COMPENSATE
keeps streaming servo commands until the next result is ready. Everything else, every command
included, stays on the control thread. With a manual clock (simulation) nothing of this is used.

Latency budget, per compensation command, on the controller clock: frame exposure
(``Frame.t_ns``) -> markers detected -> registration (rigid change) updated -> command sent.

Resumption (after pause, protective stop, reconnect or fault recovery) always starts from the
pose the robot reports *now*: APPROACH issues a fresh move from there; COMPENSATE restarts its
rate limiter from the actual pose at rest, with a speed ramp; no stored target is replayed.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.camera import StereoCamera, StereoFrame
from drivers.interfaces.errors import DriverError
from drivers.interfaces.robot import MotionLimits, Robot, RobotMode, RobotState, SafetyStatus
from drivers.interfaces.tracker import PoseTracker, TrackerSample
from hil.clock import Clock, MonotonicClock
from hil.controller.compensation import (
    MotionFilter,
    RateLimiter,
    correction_out_of_bounds,
    interpolate_pose,
    rigid_change,
)
from hil.controller.config import ProcedureConfig
from hil.controller.fsm import HALT_STATES, Event, FireResult, Fsm, State
from hil.controller.gate import BreathHoldGate, rms_deviation_mm
from hil.controller.plan_file import ProcedurePlan
from hil.controller.planning import GuidePlan, PlanRefusedError, RigGeometry, plan_guide
from hil.controller.prefetch import FramePrefetcher, Prefetched, realtime_switch_interval
from hil.controller.registration import (
    PatientRegistration,
    RegistrationFailedError,
    RobotRegistration,
    identify,
    register_patient,
    register_robot,
    register_robot_via_stereotaxy,
    track,
)
from hil.controller.tracker_use import TrackerUse, entry_disagreement_mm
from hil.controller.truth import BreathHoldCoach, GroundTruth
from hil.errors import HilError
from hil.geometry.collinear import PathError
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform
from hil.log import get_logger
from hil.safety.layer import SafetyLayer, SafetyViolationError
from hil.safety.watchdog import WatchdogSet
from hil.session.log import SessionLog

FloatArray = NDArray[np.float64]
_log = get_logger(__name__)

#: Stereo frame -> triangulated marker centres (M, 3), optical frame, mm (any order).
MarkerLocator = Callable[[StereoFrame], FloatArray]
#: Needle-axis check (seed 004 §III): (frame, expected visible segment start, end, entry, target;
#: optical frame, mm) -> the measured axis and its error against the path. Raises HilError
#: (VisionError, DegenerateConfigurationError) when the needle cannot be measured.
NeedleAxisChecker = Callable[[StereoFrame, FloatArray, FloatArray, FloatArray, FloatArray],
                             "NeedleAxisMeasurement"]


class NeedleAxisMeasurement(Protocol):
    """What the procedure needs of a needle-axis measurement (cylinder contours,
    :class:`hil.vision.lines.NeedleAxisMeasurement`, or collinear beads,
    :class:`hil.vision.beads.BeadAxisMeasurement`): its error against the path."""

    @property
    def path_error(self) -> PathError: ...


_TRACK_TOL_MM = 6.0
_STILL_WINDOW_S = 0.3
_STILL_MM = 0.25
# States in which the arm must be able to execute commands (or hold under control).
_ROBOT_COMMANDED_STATES = frozenset({State.APPROACH, State.GATE, State.COMPENSATE, State.LOCK, State.RETRACT})
_ARRIVED_MM = 0.5
_APPROACH_MEASURE_FRAMES = 5


@dataclass(frozen=True)
class OperatorView:
    """What an operator sees each tick."""

    state: State
    pending: str | None
    last_reason: str
    t_s: float
    started: bool


class Operator(Protocol):
    """Operator input: one command (an ``*_REQUESTED`` event) or None per tick."""

    def poll(self, view: OperatorView) -> Event | None: ...

    def finished(self, view: OperatorView) -> bool:
        """True when the run should end (nothing more will be asked)."""
        ...


class AutoOperator:
    """``--auto``: starts, confirms every pending transition, re-registers after an
    out-of-bounds pause (at most ``max_reregistrations`` times); ends the run in DONE, FAULT,
    SAFE_STOP, a failed start (back in IDLE), or a pause it will not resolve."""

    def __init__(self, max_reregistrations: int = 1) -> None:
        self.reregs_left = max_reregistrations
        self._started = False

    def poll(self, view: OperatorView) -> Event | None:
        if not self._started and view.state is State.IDLE:
            self._started = True
            return Event.START_REQUESTED
        if view.pending is not None:
            return Event.CONFIRM_REQUESTED
        if view.state is State.PAUSED and self.reregs_left > 0:
            self.reregs_left -= 1
            return Event.START_REQUESTED
        return None

    def finished(self, view: OperatorView) -> bool:
        if view.state in HALT_STATES or view.state is State.DONE:
            return True
        if view.state is State.IDLE and view.started and self._started:
            return True
        return view.state is State.PAUSED and self.reregs_left <= 0


@dataclass
class _Phase:
    """Per-state scratch data, reset on every state entry."""

    entered_ns: int
    sub: str = ""
    frames: list[FloatArray] = field(default_factory=list)
    flange: list[FloatArray] = field(default_factory=list)
    poses: list[RigidTransform] = field(default_factory=list)
    centroids: deque[tuple[int, FloatArray]] = field(default_factory=lambda: deque(maxlen=64))
    settle_since_ns: int | None = None
    corrections: int = 0
    target: RigidTransform | None = None
    biases: list[RigidTransform] = field(default_factory=list)
    alarmed: bool = False
    needle_alarmed: bool = False
    resumed: bool = False


class DeadlineTimer:
    """Absolute periodic deadlines on a clock (a servo stream at the robot's rate).

    After :meth:`start` (``t0_ns``), each :meth:`wait` moves the deadline one period on
    (``next = previous deadline + period``) and sleeps until it, so the time spent working between
    waits does not accumulate into the period. When the caller is already late by more than a
    period, the missed slots are skipped (the grid is kept), ``missed`` is incremented and the wait
    returns at once; late by less than a period it returns at once without counting.

    Args:
        clock: the controller clock (blocking ``sleep``).
        period_s: the period, s (> 0).

    Raises:
        ValueError: the period is not a finite positive number.
    """

    def __init__(self, clock: Clock, period_s: float) -> None:
        if not (math.isfinite(period_s) and period_s > 0):
            raise ValueError(f"deadline period must be > 0 s, got {period_s}")
        self.clock = clock
        self.period_ns = max(1, round(period_s * 1e9))
        self.deadline_ns = clock.now_ns()
        self.missed = 0

    def start(self, t0_ns: int) -> None:
        """Anchor the grid: the first deadline is ``t0_ns`` + one period."""
        self.deadline_ns = t0_ns

    def next_ns(self) -> int:
        """The deadline the next :meth:`wait` will wait for (before any skipping)."""
        return self.deadline_ns + self.period_ns

    def wait(self) -> int:
        """Sleep until the next deadline (blocking on the clock); see the class doc. Returns the
        number of slots skipped (0 when the deadline was met or missed by less than a period)."""
        self.deadline_ns += self.period_ns
        now = self.clock.now_ns()
        late_ns = now - self.deadline_ns
        if late_ns > self.period_ns:
            skipped = late_ns // self.period_ns
            self.deadline_ns += skipped * self.period_ns
            self.missed += 1
            return int(skipped)
        if late_ns < 0:
            self.clock.sleep(-late_ns * 1e-9)
        return 0


@dataclass
class RunSummary:
    """What ``hil run`` reports (see docs/run.md)."""

    final_state: str
    states: list[str]
    timeline: list[dict[str, Any]]
    fre_mm: float | None
    tre_expected_mm: float | None
    robot_fre_mm: float | None
    lock_error_mm: float | None
    lock_error_max_mm: float | None
    lock_direction_error_deg: float | None
    comp_error_rms_mm: float | None
    comp_error_p95_mm: float | None
    comp_error_max_mm: float | None
    latency_ms: dict[str, float | None]
    processing_ms: dict[str, float | None]
    gate_open_fraction: float | None
    time_to_lock_s: float | None
    duration_s: float
    frames: int
    commands_sent: int
    commands_refused: int
    faults: list[str]
    session_log: str
    needle_direction_error_deg: float | None = None
    #: the published chain head: SHA-256 of the session log's last line (set once it is closed)
    session_log_sha256: str | None = None
    #: the HTML report built after the run (``hil run``; None when not built)
    report: str | None = None
    #: the tracked needle tip against the planned target while locked (last sample; see docs/run.md)
    tracked_needle: dict[str, float] | None = None
    comp_errors_mm: list[float] = field(default_factory=list, repr=False)
    comp_error_age_s: list[float] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """The JSON summary (docs/run.md); the per-tick error series is left out."""
        d = dict(self.__dict__)
        d.pop("comp_errors_mm")
        d.pop("comp_error_age_s")
        return d


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


class Controller:
    """The procedure controller.

    Args:
        camera, robot, tracker: ACTIVE devices (tracker optional; it is watched, not used to steer).
        clock: the controller clock (the devices' clock).
        locate: perception, stereo frame -> marker centres in the optical frame.
        plan: the procedure plan (image frame).
        rig: end-effector geometry (guide frame, flange markers, TCP).
        procedure: tolerances and policies.
        limits: the safety layer's motion limits.
        watchdog_ages_s: ``{"camera": s, "robot": s, "tracker": s}``.
        session: the session log (every event, transition, command, measurement, fault).
        observers: called with the controller at the end of every tick (display, OpenIGTLink);
            read-only, in the controller's thread; their exceptions are logged
            (``observer_failed``) and never stop the control loop.
        tracker_use: the magnetic tracker's part (``[procedure.tracking]``, issue 7): the
            tracked needle tip against the target while LOCKed, the patient reference sensor as
            a stand-in for / check on the skin markers; None (or no tracker): not used.
        operator: operator input.
        coach: asks the patient for breath-holds (the simulated world, or None on a rig where
            the operator asks).
        truth: ground truth for error measurement (simulation only).
        needle_check: the optical needle-axis check (seed 004), used when
            ``procedure.lock.needle_check`` is set; None: the check is never made.
    """

    def __init__(
        self, *, camera: StereoCamera, robot: Robot, tracker: PoseTracker | None, clock: Clock,
        locate: MarkerLocator, plan: ProcedurePlan, rig: RigGeometry, procedure: ProcedureConfig,
        limits: MotionLimits, watchdog_ages_s: dict[str, float], session: SessionLog,
        operator: Operator, coach: BreathHoldCoach | None = None, truth: GroundTruth | None = None,
        needle_check: NeedleAxisChecker | None = None,
        observers: Sequence[Callable[[Controller], None]] = (),
        tracker_use: TrackerUse | None = None,
    ) -> None:
        self.camera, self.robot, self.tracker, self.clock = camera, robot, tracker, clock
        self.observers = tuple(observers)
        self._observer_errors: dict[int, str] = {}
        self.tracker_use = tracker_use if tracker is not None else None
        self.tracker_samples: dict[str, TrackerSample] = {}
        self.tracked_needle: dict[str, float] | None = None
        self._reference_in_use = False
        self._reference_disagrees = False
        self.locate, self.plan, self.rig, self.cfg = locate, plan, rig, procedure
        self.session, self.operator, self.coach, self.truth = session, operator, coach, truth
        self.fsm = Fsm(procedure.confirm, listener=self._on_fire)
        self.safety = SafetyLayer(robot, limits, clock,
                                  robot_state_max_age_s=watchdog_ages_s.get("robot", 0.05),
                                  log=lambda ev, f: session.write(ev, **f))
        ages = {k: v for k, v in watchdog_ages_s.items() if k != "tracker" or tracker is not None}
        self.watchdogs = WatchdogSet(ages)
        self.frame_period_s = 1.0 / camera.frame_rate_hz
        self.t0_ns = clock.now_ns()
        # results of the steps
        self.patient_reg: PatientRegistration | None = None
        self.robot_reg: RobotRegistration | None = None
        self.guide_plan: GuidePlan | None = None
        self.T_bias = RigidTransform.identity()   # robot-frame closed-loop correction (seed 001 2.3)
        self.gate: BreathHoldGate | None = None
        self.filter = MotionFilter(procedure.compensation.filter_alpha, procedure.compensation.filter_beta)
        comp = procedure.compensation
        self.limiter = RateLimiter(comp.max_speed_mm_s, comp.max_accel_mm_s2, comp.max_angular_speed_rad_s)
        # live data
        self.live_mm: FloatArray | None = None      # skin markers, reference order
        self.flange_mm: FloatArray | None = None    # flange markers, layout order
        self.last_frame: StereoFrame | None = None
        self.last_state: RobotState | None = None
        self.state_history: deque[RobotState] = deque(maxlen=8)
        self.T_change_meas: RigidTransform | None = None
        # the change is filtered and bounded about the planned entry point (optical frame): its
        # translation is then the entry's displacement, not a lever-arm artefact of the camera origin
        self.T_center = RigidTransform.identity()
        self._phase = _Phase(self.t0_ns)
        self._last_reason = ""
        self._started = False
        self._last_cmd_ns: int | None = None
        self._resumed_ns: int | None = None
        self._stop_owed: tuple[str, int] | None = None   # (reason, attempts) of an undelivered stop
        self.servo_deadlines_missed = 0   # servo-stream slots skipped because a command was late
        self._primed = False   # the camera pipeline's first (late) pair has been consumed
        # real time only (run() on the wall clock): grab + locate in a background thread
        self._prefetch: FramePrefetcher | None = None
        self._prefetched: Prefetched | None = None   # the result the current tick perceives
        self.frames_overwritten = 0   # prefetched pairs replaced before a tick took them (latest wins)
        # measurements for the summary
        self.timeline: list[dict[str, Any]] = []
        self.latency_ms: list[float] = []
        self.detect_ms: list[float] = []
        self.processing_ms: list[float] = []
        self.comp_errors_mm: list[float] = []
        self.comp_error_age_s: list[float] = []   # time since COMPENSATE was entered, per sample
        self.lock_errors: list[tuple[float, float]] = []
        self.gate_samples = 0
        self.gate_open_samples = 0
        self.faults: list[str] = []
        self.frames = 0
        self.lock_time_s: float | None = None
        self.needle_check = needle_check
        self.needle_errors_deg: list[tuple[str, float]] = []   # (state, direction error) per measurement
        self.timeline.append({"t_s": 0.0, "state": State.IDLE.value, "event": None, "reason": "initial"})

    # ------------------------------------------------------------------ helpers
    def t_s(self, t_ns: int | None = None) -> float:
        return ((self.clock.now_ns() if t_ns is None else t_ns) - self.t0_ns) * 1e-9

    @property
    def state(self) -> State:
        return self.fsm.state

    def view(self) -> OperatorView:
        p = self.fsm.pending
        return OperatorView(self.state, None if p is None else p.goto.name, self._last_reason, self.t_s(),
                            self._started)

    def _on_fire(self, r: FireResult) -> None:
        if r.kind == "stay" and r.event.value.endswith("_received"):
            return  # data events are summarised by the measurement records
        name = {"transition": "transition_applied", "rejected": "transition_rejected",
                "pending": "transition_pending", "stay": "event_handled"}[r.kind]
        self.session.write(name, source=r.source, target=r.target, input=r.event, reason=r.reason,
                           transition=r.transition_name)
        if r.kind == "rejected":
            _log.info("transition_rejected", source=r.source.value, input=r.event.value, reason=r.reason)
        elif r.kind == "transition":
            _log.info("transition_applied", source=r.source.value, target=r.target.value,
                      input=r.event.value, reason=r.reason)

    def fire(self, event: Event, reason: str = "") -> FireResult:
        """Feed an event; on a transition run the new state's entry action."""
        res = self.fsm.fire(event, reason=reason, guards={"has_plan": self.guide_plan is not None})
        if res.changed:
            self._last_reason = reason or res.transition_name
            confirmed = event is Event.CONFIRM_REQUESTED
            self.timeline.append({"t_s": round(self.t_s(), 4), "state": res.target.value,
                                  "event": res.event.value, "confirmed": confirmed,
                                  "reason": res.reason if confirmed else reason})
            self._enter(res)
        return res

    def fault(self, reason: str) -> None:
        """Record a fault, enter FAULT (or stay there) and stop the robot. A fault repeating while
        already in FAULT is recorded once."""
        if self.state is State.FAULT and self.faults and self.faults[-1] == reason:
            return
        self.faults.append(reason)
        self.session.write("fault_detected", reason=reason, state=self.state)
        _log.warning("fault_detected", reason=reason, state=self.state.value)
        if self.state is State.FAULT:
            self.fire(Event.FAULT_DETECTED, reason)
            self._stop_robot("fault: " + reason)
        else:
            self.fire(Event.FAULT_DETECTED, reason)

    def _stop_robot(self, reason: str) -> None:
        """Send a stop. When it cannot be delivered (``stop_failed``: the connection is down) it
        stays owed and :meth:`_retry_stop` re-sends it every tick until one is delivered
        (``stop_delivered`` with the number of attempts) or a later state entry supersedes it."""
        attempts = 1 if self._stop_owed is None else self._stop_owed[1] + 1
        try:
            self.safety.stop(reason)
        except DriverError as exc:
            self._stop_owed = (reason, attempts)
            self.session.write("stop_failed", reason=str(exc), stop_reason=reason, attempt=attempts)
            _log.error("stop_failed", reason=str(exc), attempt=attempts)
            return
        self._stop_owed = None
        if attempts > 1:
            self.session.write("stop_delivered", reason=reason, attempts=attempts)
            _log.warning("stop_delivered", reason=reason, attempts=attempts)

    def _retry_stop(self) -> None:
        """Re-send a stop that could not be delivered (once per tick)."""
        if self._stop_owed is not None:
            self._stop_robot(self._stop_owed[0])

    def _robot_ready_for(self, cmd: Event) -> bool:
        """Before an accepted RESET or START: when the robot needs recovering - a protective stop,
        a stopped program with normal safety (an e-stop released, a script stopped by its
        watchdog or the pendant), or a state that cannot be read (a dropped link) - try
        ``robot.recover()`` (``robot_recover_attempted`` with the outcome). START is refused
        (``start_refused`` with the reason; returns False) while the robot is still not in normal
        safety status with its program running, or its state cannot be read; RESET always
        proceeds (IDLE stops the robot). Never raises."""
        if cmd not in (Event.START_REQUESTED, Event.RESET_REQUESTED) or not self.fsm.accepts(cmd):
            return True
        why = ""
        try:
            st: RobotState | None = self.robot.state_now()
            read_error = ""
        except DriverError as exc:
            st, read_error = None, str(exc)
        if st is None or st.safety is SafetyStatus.PROTECTIVE_STOP or (
                st.safety is SafetyStatus.NORMAL and st.mode is RobotMode.STOPPED):
            error = ""
            try:
                self.robot.recover()
            except DriverError as exc:
                error = str(exc)
            try:
                st = self.robot.state_now()
            except DriverError as exc:
                st, error = None, error or str(exc)
            ok = st is not None and st.safety is SafetyStatus.NORMAL and st.mode is not RobotMode.STOPPED
            self.session.write("robot_recover_attempted", input=cmd, ok=ok,
                               safety=None if st is None else st.safety,
                               mode=None if st is None else st.mode, error=error, state_error=read_error)
            (_log.info if ok else _log.warning)("robot_recover_attempted", input=cmd.value, ok=ok,
                                                error=error)
            if not ok:
                why = ("robot state unavailable after recover()" if st is None
                       else f"robot still {st.safety.value} / {st.mode.value} after recover()")
                why += f": {error}" if error else ""
        elif st.safety is not SafetyStatus.NORMAL:
            why = f"robot in {st.safety.value}"
        if not why or cmd is Event.RESET_REQUESTED:
            return True
        self._last_reason = why
        self.session.write("start_refused", reason=why, state=self.state)
        _log.warning("start_refused", reason=why, state=self.state.value)
        return False

    # ------------------------------------------------------------------ the loop
    def run(self, max_duration_s: float | None = None) -> RunSummary:
        """Tick until the operator says the run is over or the time budget is spent."""
        limit = self.cfg.max_duration_s if max_duration_s is None else max_duration_s
        self.prime()
        self.watchdogs.arm(self.clock.now_ns())
        with self._camera_prefetch():
            while not self.operator.finished(self.view()):
                if self.t_s() > limit:
                    self.session.write("run_time_exceeded", limit_s=limit, state=self.state)
                    if self.state not in HALT_STATES:
                        self.fire(Event.ABORT_REQUESTED, f"procedure exceeded {limit} s")
                        self._notify_observers()  # the abort happened outside a tick: show it
                    break
                self.tick()
        return self.summary()

    def _grab_timeout_s(self) -> float:
        return max(4 * self.frame_period_s, 0.2)

    @contextlib.contextmanager
    def _camera_prefetch(self) -> Iterator[None]:
        """For :meth:`run`: on the wall clock (MonotonicClock) with ``procedure.camera_prefetch``,
        grab and locate the next pair in a :class:`~hil.controller.prefetch.FramePrefetcher` thread
        (so COMPENSATE keeps streaming meanwhile) with the GIL switch interval lowered
        (:func:`~hil.controller.prefetch.realtime_switch_interval`); otherwise (a manual clock: a
        deterministic simulation) nothing changes. The worker is stopped and joined when the block
        ends, however it ends, before the caller can close the camera; ``frame_prefetch_stopped``
        records its counts."""
        if not (self.cfg.camera_prefetch and isinstance(self.clock, MonotonicClock)):
            yield
            return
        pf = FramePrefetcher(self.camera, self.locate, self._grab_timeout_s())
        self._prefetch = pf
        try:
            with realtime_switch_interval():
                pf.start()
                yield
        finally:
            self._prefetch = None
            self._prefetched = None
            pf.stop()
            self.frames_overwritten += pf.overwritten
            self.session.write("frame_prefetch_stopped", pairs=pf.produced, overwritten=pf.overwritten)

    def prime(self, timeout_s: float = 2.0) -> None:
        """Grab and discard one stereo pair, once, before the first tick judges any (:meth:`run`
        calls it before arming the watchdogs; the first :meth:`tick` calls it when nobody did).

        A camera's first buffer or a simulator's first render is late (caches, buffers): it is
        consumed here, so the first pair the controller judges is a fresh one and the watchdogs
        stay strict for every pair. Logs ``pipeline_primed`` (the discarded pair's age) or
        ``pipeline_prime_failed`` (then the camera watchdog reports the missing data). Blocks up to
        ``timeout_s`` plus the grab's own work; never raises for a device error.
        """
        if self._primed:
            return
        self._primed = True
        t_ns = self.clock.now_ns()
        try:
            frame = self.camera.grab(timeout_s=max(timeout_s, 4 * self.frame_period_s))
        except DriverError as exc:
            self.session.write("pipeline_prime_failed", reason=str(exc))
            _log.warning("pipeline_prime_failed", reason=str(exc))
            return
        now = self.clock.now_ns()
        self.session.write("pipeline_primed", frame_seq=frame.left.seq,
                           first_frame_age_s=(now - frame.left.t_ns) * 1e-9, took_s=(now - t_ns) * 1e-9)

    def tick(self) -> None:
        """One control cycle (see module doc). Never raises: every device, safety or internal
        error becomes FAULT_DETECTED with the reason (the robot is stopped)."""
        self.prime()  # once (run() already did)
        t_start_wall = time.perf_counter_ns()  # profiling only, never used for control
        try:
            self._tick()
        except (DriverError, SafetyViolationError) as exc:
            self.fault(str(exc))
        except HilError as exc:  # a step could not compute (geometry, config): stop safely
            self.fault(f"{type(exc).__name__}: {exc}")
        except Exception as exc:  # noqa: BLE001 - the tick boundary: an unexpected error must stop the robot
            _log.exception("tick_failed", state=self.state.value)
            self.fault(f"internal error: {type(exc).__name__}: {exc}")
        self.processing_ms.append((time.perf_counter_ns() - t_start_wall) * 1e-6)
        self._measure_truth()
        self._notify_observers()

    def _notify_observers(self) -> None:
        """Call every observer with the controller, after the tick (whatever it did). An
        observer's exception is logged (``observer_failed``) and never reaches the control loop."""
        for i, obs in enumerate(self.observers):
            try:
                obs(self)
            except Exception as exc:  # noqa: BLE001 - an observer (display, stream) must not stop control
                name, error = getattr(obs, "__name__", repr(obs)), f"{type(exc).__name__}: {exc}"
                _log.warning("observer_failed", observer=name, error=error)
                if self._observer_errors.get(i) != error:  # once per distinct error, not every tick
                    self._observer_errors[i] = error
                    self.session.write("observer_failed", observer=name, error=error)

    def _tick(self) -> None:
        self._retry_stop()
        cmd = self.operator.poll(self.view())
        if cmd is not None:
            self.session.write("operator_command", input=cmd)
            if cmd is Event.START_REQUESTED:
                self._started = True
            if self._robot_ready_for(cmd):
                self.fire(cmd, "operator")
        try:
            self._read_devices()
        except DriverError as exc:
            self.clock.sleep(self.frame_period_s)  # time moves on even when a device is gone
            self.fault(f"{exc.device}: {exc.message}")
            return
        now = self.clock.now_ns()
        for reason in self.watchdogs.check(now):  # every pair (run() primed the pipeline before arming)
            self.fault(reason)
            return
        st = self.last_state
        if st is not None and st.safety is not SafetyStatus.NORMAL and self.state is not State.FAULT:
            self.fault(f"robot: {st.safety.value}")
            return
        if st is not None and st.mode is RobotMode.STOPPED and self.state in _ROBOT_COMMANDED_STATES:
            # Safety normal but the arm's program is not running (a UR script stopped by its RTDE
            # watchdog, by the pendant, ...): it cannot execute or correct anything, so the
            # procedure must not wait on it. recover() (operator `recover`) restarts the program.
            self.fault(f"robot: program not running in {self.state.value} (mode stopped)")
            return
        frame = self.last_frame
        if frame is None:
            return
        self._perceive(frame)
        if self.patient_reg is not None and self.state is not State.REGISTER:
            self.gate_samples += 1
            self.gate_open_samples += int(self._gate_deviation() <= self.cfg.gate.tolerance_mm)
        self.detect_ms.append((self.clock.now_ns() - frame.left.t_ns) * 1e-6)
        self.session.write("frame_measured", frame_seq=frame.left.seq, exposure_t_ns=frame.left.t_ns,
                           skin_markers=_count(self.live_mm), flange_markers=_count(self.flange_mm),
                           gate_deviation_mm=self._gate_deviation(),
                           robot_tcp_mm=None if st is None else st.T_robot_from_tcp.t,
                           tcp_speed_mm_s=None if st is None else st.tcp_speed_mm_s,
                           live_mm=self.live_mm)
        self.fire(Event.FRAME_RECEIVED)
        self._step(frame)

    def _read_devices(self) -> None:
        """The next stereo pair (blocking up to the grab timeout: from the camera, or the pair the
        prefetcher has ready), the robot state and the tracker's latest samples. Raises the
        devices' DriverError (DeviceTimeoutError naming the camera when no pair arrives)."""
        self._prefetched = None
        if self._prefetch is not None:
            got = self._prefetch.take(self._grab_timeout_s())
            self._prefetched, frame = got, got.frame
        else:
            frame = self.camera.grab(timeout_s=self._grab_timeout_s())
        now = self.clock.now_ns()
        self.frames += 1
        self.last_frame = frame
        self.watchdogs["camera"].feed(frame.left.t_ns, now)
        st = self.robot.state_now()
        self.last_state = st
        self.state_history.append(st)
        self.watchdogs["robot"].feed(st.t_ns, now)
        if self.tracker is not None:
            samples = self.tracker.latest()
            self.tracker_samples = samples
            fresh = [s.t_ns for s in samples.values() if not s.missing]
            if fresh:
                self.watchdogs["tracker"].feed(max(fresh), now)

    def _perceive(self, frame: StereoFrame) -> None:
        """Locate markers; identify skin markers (against the reference once registered, else
        the CT layout) and flange markers (against their layout). A prefetched pair comes with its
        marker centres (or the error ``locate`` raised on it, raised here)."""
        got = self._prefetched
        if got is not None and got.frame is frame:
            if got.error is not None:
                raise got.error
            located = got.points_mm if got.points_mm is not None else np.zeros((0, 3))
        else:
            located = self.locate(frame)
        pts = np.asarray(located, dtype=np.float64).reshape(-1, 3)
        tol = self.cfg.registration.match_tolerance_mm
        if self.patient_reg is not None:
            ref = self.patient_reg.reference_optical_mm
            prev = self.live_mm
            predicted = ref if prev is None else np.where(np.isfinite(prev), prev, ref)
            live = track(pts, predicted, _TRACK_TOL_MM)
            if int(np.all(np.isfinite(live), axis=1).sum()) < 3:
                found = identify(pts, np.nan_to_num(ref), tol)
                live = found if found is not None else live
            self.live_mm = live
            reg = rigid_change(ref, live)
            self.T_change_meas = None if reg is None else reg.T_fixed_from_moving
            self._use_reference_sensor(frame)
            if self.T_change_meas is not None:
                self.filter.update(self._local(self.T_change_meas), frame.left.t_ns)
        else:
            self.live_mm = identify(pts, self.plan.fiducials_mm, tol)
        layout = self.rig.flange_markers_tcp_mm
        if self.flange_mm is not None and int(np.all(np.isfinite(self.flange_mm), axis=1).sum()) >= 3:
            fl = track(pts, self.flange_mm, _TRACK_TOL_MM)
            if int(np.all(np.isfinite(fl), axis=1).sum()) < 3:
                fl2 = identify(pts, layout, tol)
                fl = fl2 if fl2 is not None else fl
        else:
            fl2 = identify(pts, layout, tol)
            fl = fl2 if fl2 is not None else np.full(layout.shape, np.nan)
        self.flange_mm = fl

    # ------------------------------------------------------------------ geometry helpers
    def _robot_state_at(self, t_ns: int) -> RigidTransform | None:
        """The robot's reported TCP pose at ``t_ns``, interpolated in the recent state history."""
        hist = list(self.state_history)
        if not hist:
            return None
        if t_ns <= hist[0].t_ns:
            return hist[0].T_robot_from_tcp
        for a, b in itertools.pairwise(hist):
            if a.t_ns <= t_ns <= b.t_ns:
                f = (t_ns - a.t_ns) / max(b.t_ns - a.t_ns, 1)
                return interpolate_pose(a.T_robot_from_tcp, b.T_robot_from_tcp, f)
        return hist[-1].T_robot_from_tcp

    def _T_optical_from_tcp_measured(self) -> RigidTransform | None:
        """The TCP pose measured by the camera from the flange markers (optical frame)."""
        fl = self.flange_mm
        if fl is None:
            return None
        ok = np.all(np.isfinite(fl), axis=1)
        if int(ok.sum()) < 3:
            return None
        return register_horn(fl[ok], self.rig.flange_markers_tcp_mm[ok]).T_fixed_from_moving

    def _local(self, T_change: RigidTransform) -> RigidTransform:
        """The change expressed about the planned entry point (translation = its displacement)."""
        return self.T_center.inverse() @ T_change @ self.T_center

    def _global(self, T_local: RigidTransform) -> RigidTransform:
        return self.T_center @ T_local @ self.T_center.inverse()

    def _T_optical_from_tcp_planned(self) -> RigidTransform:
        assert self.robot_reg is not None
        assert self.guide_plan is not None
        return self.robot_reg.T_robot_from_optical.inverse() @ self.guide_plan.T_robot_from_tcp

    def _bias_measurement(self, frame: StereoFrame) -> RigidTransform | None:
        """``D = E @ O^-1``: the robot-frame correction that maps where the camera sees the TCP
        (O, through the registration) onto where the robot says it is (E), at frame time."""
        O_opt = self._T_optical_from_tcp_measured()
        E = self._robot_state_at(frame.left.t_ns)
        if O_opt is None or E is None or self.robot_reg is None:
            return None
        return E @ (self.robot_reg.T_robot_from_optical @ O_opt).inverse()

    def _guide_error_optical_mm(self) -> float | None:
        """Distance between the camera-measured guide and where the guide should be for the
        patient as seen in the same frame (optical frame; no registration in the loop)."""
        O_opt = self._T_optical_from_tcp_measured()
        if O_opt is None or self.T_change_meas is None or self.guide_plan is None or self.robot_reg is None:
            return None
        desired = self.T_change_meas @ self._T_optical_from_tcp_planned() @ self.rig.T_tcp_from_guide
        measured = O_opt @ self.rig.T_tcp_from_guide
        return float(np.linalg.norm(measured.t - desired.t))

    def guide_error_optical_mm(self) -> float | None:
        """Public read-only probe (console, IGTL): the camera-measured guide error against the
        patient as seen in the latest frame, mm; None before registration/plan or without markers."""
        return self._guide_error_optical_mm()

    def _needle_axis(self, frame: StereoFrame) -> NeedleAxisMeasurement | None:
        """The needle-axis check (seed 004 §III) on ``frame`` against the planned path as the
        patient is seen now (plan -> optical with the patient registration, then the measured
        change). Logs ``needle_axis_measured`` or ``needle_axis_unavailable`` (with the reason);
        returns None when the check is off, cannot be set up or the needle is not measured."""
        nc = self.cfg.lock.needle_check
        if nc is None or self.needle_check is None:
            return None
        if self.patient_reg is None or self.T_change_meas is None:
            self.session.write("needle_axis_unavailable", state=self.state,
                               reason="no patient registration or no live skin markers")
            return None
        T = self.T_change_meas @ self.patient_reg.T_optical_from_image
        entry = T.apply(self.plan.entry_mm).reshape(3)
        target = T.apply(self.plan.target_mm).reshape(3)
        u = (target - entry) / np.linalg.norm(target - entry)
        start, end = entry - nc.visible_to_mm * u, entry - nc.visible_from_mm * u
        try:
            m = self.needle_check(frame, start, end, entry, target)
        except HilError as exc:
            self.session.write("needle_axis_unavailable", state=self.state, frame_seq=frame.left.seq,
                               reason=f"{type(exc).__name__}: {exc}")
            return None
        pe = m.path_error
        self.needle_errors_deg.append((self.state.value, pe.direction_error_deg))
        self.session.write("needle_axis_measured", state=self.state, frame_seq=frame.left.seq,
                           direction_error_deg=pe.direction_error_deg, entry_offset_mm=pe.entry_offset_mm,
                           target_offset_mm=pe.target_offset_mm,
                           within=pe.within(nc.max_direction_deg, nc.max_offset_mm))
        return m

    def _desired_tcp_robot(self, T_change: RigidTransform) -> RigidTransform:
        assert self.robot_reg is not None
        T_robot_from_optical = self.robot_reg.T_robot_from_optical
        return self.T_bias @ T_robot_from_optical @ T_change @ self._T_optical_from_tcp_planned()

    def _gate_deviation(self) -> float:
        if self.patient_reg is None or self.live_mm is None:
            return math.inf
        return rms_deviation_mm(self.patient_reg.reference_optical_mm, self.live_mm)[0]

    # ------------------------------------------------------------------ state entry actions
    def _enter(self, res: FireResult) -> None:
        now = self.clock.now_ns()
        resumed = res.transition_name in ("resume", "recover")
        if resumed:
            self._resumed_ns = now
        self._phase = _Phase(now, resumed=resumed)
        self._stop_owed = None  # the new state's entry action commands the robot itself
        s = res.target
        self.session.write("state_entered", state=s, reason=res.reason, transition=res.transition_name)
        try:
            if s is State.REGISTER:
                self.patient_reg = None
                self.live_mm = None
                self.filter.reset()
                self.T_bias = RigidTransform.identity()
                self._request_hold("registration", self.cfg.registration.hold_request_s)
                self._phase.sub = "wait_still"
            elif s is State.APPROACH:
                if res.transition_name == "recover":
                    self.robot.recover()
                self._approach_move(resumed)
            elif s is State.GATE:
                assert self.patient_reg is not None
                if self.gate is None:
                    self.gate = BreathHoldGate(self.cfg.gate, self.patient_reg.reference_optical_mm)
                self.gate.restart(now)
                self._stop_robot("gate: hold position while waiting for the breath-hold")
                self._request_hold("gate", self.cfg.gate.hold_request_s)
            elif s is State.COMPENSATE:
                st = self.robot.state_now()
                self.limiter.reset(st.T_robot_from_tcp)
                self.safety.forget_stream()
                self._last_cmd_ns = None
            elif s is State.LOCK:
                self._stop_robot("lock")
                if self.lock_time_s is None:
                    self.lock_time_s = self.t_s()
            elif s is State.RETRACT:
                st = self.robot.state_now()
                axis = (st.T_robot_from_tcp @ self.rig.T_tcp_from_guide).R[:, 2]
                target = RigidTransform(st.T_robot_from_tcp.R,
                                        st.T_robot_from_tcp.t - self.cfg.lock.retract_mm * axis)
                self._phase.target = target
                self.safety.move_linear(target, self.cfg.lock.retract_speed_mm_s,
                                        self.cfg.approach.accel_mm_s2)
            elif s in (State.PAUSED, State.SAFE_STOP, State.DONE, State.IDLE):
                self._stop_robot(s.value)
            elif s is State.FAULT:
                self._stop_robot("fault: " + res.reason)
        except (DriverError, SafetyViolationError) as exc:
            if s is not State.FAULT:
                self.fault(f"entering {s.value}: {exc}")

    # ------------------------------------------------------------------ the tracker (issue 7)
    def _path_optical_now(self) -> tuple[FloatArray, FloatArray] | None:
        """The planned entry and target where they are now (optical frame): the registration
        moved by the patient's current rigid change."""
        if self.patient_reg is None:
            return None
        T = self.patient_reg.T_optical_from_image
        if self.T_change_meas is not None:
            T = self.T_change_meas @ T
        return T.apply(self.plan.entry_mm).reshape(3), T.apply(self.plan.target_mm).reshape(3)

    def _use_reference_sensor(self, frame: StereoFrame) -> None:
        """The patient reference sensor backs up the skin markers: when they give no rigid change
        this tick its change stands in (``reference_in_use``); when both give one, a difference
        at the entry beyond the configured bound is logged (``reference_disagreement``)."""
        tu = self.tracker_use
        if tu is None or tu.cfg.reference_sensor is None or self.patient_reg is None:
            return
        got = tu.reference_change(self.tracker_samples)
        if got is None:
            return
        M, t_ns = got
        entry = self.patient_reg.T_optical_from_image.apply(self.plan.entry_mm).reshape(3)
        if self.T_change_meas is None:
            if tu.cfg.reference_backup:
                self.T_change_meas = M
                if not self._reference_in_use:
                    self.session.write("reference_in_use", sensor=tu.cfg.reference_sensor, state=self.state,
                                       reason="skin markers give no rigid change", sample_t_ns=t_ns)
                self._reference_in_use = True
            return
        if self._reference_in_use:
            self.session.write("reference_released", sensor=tu.cfg.reference_sensor, state=self.state)
            self._reference_in_use = False
        d = entry_disagreement_mm(M, self.T_change_meas, entry)
        disagrees = d > tu.cfg.reference_disagreement_mm
        if disagrees != self._reference_disagrees:
            self._reference_disagrees = disagrees
            self.session.write("reference_disagreement" if disagrees else "reference_agrees",
                               sensor=tu.cfg.reference_sensor, entry_difference_mm=d,
                               limit_mm=tu.cfg.reference_disagreement_mm, state=self.state)

    def _track_needle(self) -> None:
        """While locked: the tracked needle tip against the planned target as it is now
        (``needle_tracked``); the last sample goes to the summary."""
        tu = self.tracker_use
        path = self._path_optical_now()
        if tu is None or tu.cfg.needle_sensor is None or path is None:
            return
        e = tu.needle_error(self.tracker_samples, path[0], path[1])
        if e is None:
            self.session.write("needle_tracked", sensor=tu.cfg.needle_sensor, available=False)
            return
        self.tracked_needle = {
            "distance_to_target_mm": e.distance_to_target_mm, "lateral_error_mm": e.lateral_error_mm,
            "depth_to_target_mm": e.depth_to_target_mm,
            "direction_error_deg": math.degrees(e.direction_error_rad)}
        self.session.write("needle_tracked", sensor=tu.cfg.needle_sensor, available=True,
                           tip_optical_mm=e.tip_optical_mm, **self.tracked_needle)

    def _request_hold(self, why: str, duration_s: float) -> None:
        self.session.write("breath_hold_requested", purpose=why, duration_s=duration_s)
        if self.coach is not None:
            self.coach.request_breath_hold(duration_s)

    def _approach_move(self, resumed: bool) -> None:
        assert self.guide_plan is not None
        target = self.T_bias @ self.guide_plan.T_robot_from_tcp
        self._phase.target = target
        self._phase.sub = "moving"
        a = self.cfg.approach
        f = self.cfg.resume.initial_speed_fraction if resumed else 1.0
        self.safety.move_linear(target, a.speed_mm_s * f if resumed else a.speed_mm_s, a.accel_mm_s2 * f)

    # ------------------------------------------------------------------ state steps
    def _step(self, frame: StereoFrame) -> None:
        s = self.state
        if s is State.REGISTER:
            self._step_register(frame)
        elif s is State.PLAN:
            self._step_plan()
        elif s is State.APPROACH:
            self._step_approach(frame)
        elif s is State.GATE:
            self._step_gate(frame)
        elif s is State.COMPENSATE:
            self._step_compensate(frame)
        elif s is State.LOCK:
            self._step_lock(frame)
        elif s is State.RETRACT:
            self._step_retract()

    def _elapsed_s(self) -> float:
        return (self.clock.now_ns() - self._phase.entered_ns) * 1e-9

    def _step_register(self, frame: StereoFrame) -> None:
        ph = self._phase
        limit = self.cfg.registration.timeout_s
        if self._elapsed_s() > limit:
            self.fire(Event.TIMED_OUT, f"no still breath-hold with visible markers within {limit} s")
            return
        live = self.live_mm
        t = frame.left.t_ns
        if live is None or int(np.all(np.isfinite(live), axis=1).sum()) < self.cfg.registration.min_markers:
            ph.centroids.clear()
            ph.frames.clear()
            return
        c = np.nanmean(live, axis=0)
        ph.centroids.append((t, c))
        window = [p for (tt, p) in ph.centroids if (t - tt) * 1e-9 <= _STILL_WINDOW_S]
        span = (t - ph.centroids[0][0]) * 1e-9
        still = span >= _STILL_WINDOW_S and float(np.max(np.linalg.norm(
            np.array(window) - np.mean(window, axis=0), axis=1))) < _STILL_MM
        if not still:
            ph.frames.clear()
            ph.flange.clear()
            ph.poses.clear()
            return
        ph.frames.append(live.copy())
        pose = self._robot_state_at(t)
        if self.flange_mm is not None and pose is not None:
            ph.flange.append(self.flange_mm.copy())
            ph.poses.append(pose)
        if len(ph.frames) < self.cfg.registration.frames_averaged:
            return
        try:
            preg = register_patient(ph.frames, self.plan, self.cfg.registration)
            st_cfg = self.cfg.registration.stereotaxy
            if self.cfg.registration.robot_method == "stereotaxy" and st_cfg is not None:
                rreg = register_robot_via_stereotaxy(st_cfg, preg.T_optical_from_image)
            else:
                rreg = register_robot(ph.flange, ph.poses, self.rig.flange_markers_tcp_mm)
        except RegistrationFailedError as exc:
            self.session.write("registration_failed", reason=exc.reason)
            self.fire(Event.REGISTRATION_FAILED, exc.reason)
            return
        self.patient_reg, self.robot_reg = preg, rreg
        self.T_center = RigidTransform.from_translation(preg.T_optical_from_image.apply(self.plan.entry_mm))
        self.gate = None
        if self.tracker_use is not None and self.tracker_use.cfg.reference_sensor is not None:
            ok = self.tracker_use.record_reference(self.tracker_samples)
            self.session.write("reference_sensor_recorded", sensor=self.tracker_use.cfg.reference_sensor,
                               available=ok)
        self.live_mm = preg.reference_optical_mm.copy()
        self.filter.reset()
        self.session.write("registration_done", fre_mm=preg.fre_rms_mm, tre_expected_mm=preg.tre_expected_mm,
                           markers=preg.markers_used, frames=preg.frames,
                           T_optical_from_image=preg.T_optical_from_image,
                           robot_fre_mm=rreg.fre_rms_mm, T_robot_from_optical=rreg.T_robot_from_optical,
                           robot_method=rreg.method, robot_residual_mm=rreg.fre_rms_mm,
                           reference_optical_mm=preg.reference_optical_mm,
                           residuals_mm=np.linalg.norm(preg.T_optical_from_image.apply(self.plan.fiducials_mm)
                                                       - preg.reference_optical_mm, axis=1))
        self.fire(Event.REGISTERED,
                  f"FRE {preg.fre_rms_mm:.3f} mm, expected TRE {preg.tre_expected_mm:.3f} mm")

    def _step_plan(self) -> None:
        if self.fsm.pending is not None:
            return
        assert self.patient_reg is not None
        assert self.robot_reg is not None
        T_robot_from_image = self.robot_reg.T_robot_from_optical @ self.patient_reg.T_optical_from_image
        entry = T_robot_from_image.apply(self.plan.entry_mm).reshape(3)
        target = T_robot_from_image.apply(self.plan.target_mm).reshape(3)
        st = self.last_state
        x_hint = None if st is None else (st.T_robot_from_tcp @ self.rig.T_tcp_from_guide).R[:, 0]
        try:
            gp = plan_guide(entry, target, self.rig, self.cfg.planning, self.safety.limits,
                            q_near=None if st is None else st.q_rad, x_hint=x_hint)
        except PlanRefusedError as exc:
            self.session.write("plan_refused", reason=exc.reason, entry_robot_mm=entry,
                               target_robot_mm=target)
            self.fire(Event.PLAN_REFUSED, exc.reason)
            return
        self.guide_plan = gp
        self.session.write("plan_accepted", entry_robot_mm=entry, target_robot_mm=target,
                           T_robot_from_tcp=gp.T_robot_from_tcp, q_rad=gp.q_rad, standoff_mm=gp.standoff_mm)
        self.fire(Event.PLAN_ACCEPTED, "reachable")

    def _step_approach(self, frame: StereoFrame) -> None:
        ph, a = self._phase, self.cfg.approach
        st = self.last_state
        assert st is not None
        assert ph.target is not None
        assert self.guide_plan is not None
        if self._elapsed_s() > a.timeout_s:
            self.fire(Event.TIMED_OUT, f"stand-off not reached within {a.timeout_s} s")
            return
        if ph.sub == "moving":
            arrived = (st.mode is not RobotMode.MOVING and st.tcp_speed_mm_s < 0.5
                       and float(np.linalg.norm(st.T_robot_from_tcp.t - ph.target.t)) < _ARRIVED_MM)
            if arrived:
                ph.sub = "measuring"
                ph.biases.clear()
            return
        if ph.sub == "measuring":
            D = self._bias_measurement(frame)
            if D is not None:
                ph.biases.append(D)
            if len(ph.biases) < _APPROACH_MEASURE_FRAMES:
                return
            D_mean = _mean_transform(ph.biases)
            # error of the guide as the camera sees it, in the robot frame
            commanded = self.T_bias @ self.guide_plan.T_robot_from_tcp
            err = D_mean.inverse() @ commanded @ self.rig.T_tcp_from_guide
            want = self.guide_plan.T_robot_from_tcp @ self.rig.T_tcp_from_guide
            e_mm = float(np.linalg.norm(err.t - want.t))
            self.session.write("approach_measured", guide_error_mm=e_mm, correction=ph.corrections,
                               T_bias=D_mean)
            if e_mm <= a.tolerance_mm:
                self.fire(Event.STANDOFF_REACHED,
                          f"guide within {e_mm:.3f} mm of the stand-off pose (optical)")
                return
            if ph.corrections >= a.max_corrections:
                self.fire(Event.APPROACH_FAILED,
                          f"guide still {e_mm:.3f} mm off after {ph.corrections} optical corrections")
                return
            ph.corrections += 1
            self.T_bias = interpolate_pose(self.T_bias, D_mean, a.correction_gain)
            self._approach_move(False)

    def _step_gate(self, frame: StereoFrame) -> None:
        assert self.gate is not None
        status = self.gate.update(self.live_mm, frame.left.t_ns)
        self.session.write("gate_measured", deviation_rms_mm=status.deviation_rms_mm, markers=status.markers,
                           dwell_s=status.dwell_s, open=status.open)
        if status.open:
            self.fire(Event.GATE_OPENED, status.justification)
        elif status.timed_out:
            self.session.write("gate_timed_out", message=status.justification)
            self.fire(Event.TIMED_OUT, status.justification)

    def _step_compensate(self, frame: StereoFrame) -> None:
        c = self.cfg.compensation
        now = self.clock.now_ns()
        if self._elapsed_s() > c.timeout_s:
            self.fire(Event.TIMED_OUT, f"not aligned within {c.timeout_s} s")
            return
        if self.T_change_meas is None or not self.filter.initialised:
            return  # markers not seen this frame: hold the last command (watchdogs cover staleness)
        t_reg = self.clock.now_ns()
        est = self.filter.estimate()  # about the entry point
        why = correction_out_of_bounds(est, c)
        if why is not None:
            self.session.write("correction_out_of_bounds", reason=why, T_change=est)
            self.fire(Event.CORRECTION_OUT_OF_BOUNDS, why + "; operator decision needed")
            return
        servo_dt = 1.0 / self.robot.control_rate_hz if c.servo_at_robot_rate else self.frame_period_s
        dt = servo_dt if self._last_cmd_ns is None else \
            min(max((now - self._last_cmd_ns) * 1e-9, servo_dt), 2.0 * self.frame_period_s)
        # slow closed-loop correction from the optical measurement of the flange (seed 001 2.3)
        st = self.last_state
        if (c.bias_gain > 0 and self.filter.speed_mm_s < c.bias_max_speed_mm_s and st is not None
                and st.tcp_speed_mm_s < c.bias_max_speed_mm_s):
            D = self._bias_measurement(frame)
            if D is not None:
                self.T_bias = interpolate_pose(self.T_bias, D, c.bias_gain)
        hold_s = servo_dt if c.servo_at_robot_rate else self.frame_period_s
        t_send = self.clock.now_ns()  # the stream's deadlines count from this command's slot
        horizon_s, cmd = self._servo_once(frame, dt, hold_s)
        t_cmd = self.clock.now_ns()
        self.latency_ms.append((t_cmd - frame.left.t_ns) * 1e-6)
        if c.servo_at_robot_rate:
            # stream at the robot's rate until the next frame is due, on the predicted motion
            # on absolute deadlines one servo period apart from the frame's command: the work per
            # command does not stretch the period; a slot missed by more than a period is skipped
            timer = DeadlineTimer(self.clock, servo_dt)
            timer.start(t_send)
            half_ns = timer.period_ns // 2
            pf = self._prefetch
            if pf is None:  # the next grab blocks this thread: stop half a period before it is due
                next_ready_ns = now + round(self.frame_period_s * 1e9)

                def more() -> bool:
                    return max(timer.next_ns(), self.clock.now_ns()) + half_ns <= next_ready_ns
            else:  # real time: stream until the prefetcher has the next pair (or an error) ready;
                # capped, and never on a frame the camera watchdog would call stale, so the tick
                # judges a missing or late pair as it would without the prefetcher
                cap_ns = min(now + round((2 * self.frame_period_s + self._grab_timeout_s()) * 1e9),
                             frame.left.t_ns + round(self.watchdogs["camera"].max_age_s * 1e9))

                def more() -> bool:
                    return not pf.ready() and max(timer.next_ns(), self.clock.now_ns()) <= cap_ns
            while more():
                skipped = timer.wait()
                if skipped:
                    self.servo_deadlines_missed += 1
                    self.session.write("servo_deadline_missed", slots_skipped=skipped, period_s=servo_dt)
                self._servo_once(frame, servo_dt, servo_dt)
        err = self._guide_error_optical_mm()
        dev = self._gate_deviation()
        self.session.write("compensation_step", exposure_t_ns=frame.left.t_ns,
                           latency_detect_ms=(t_reg - frame.left.t_ns) * 1e-6,
                           latency_command_ms=(t_cmd - frame.left.t_ns) * 1e-6,
                           change_mm=est.translation_norm(), predicted_s=horizon_s,
                           command_mm=cmd.t, guide_error_mm=err, gate_deviation_mm=dev)
        tol = self.cfg.lock.tolerance_mm
        if err is not None and err <= tol and dev <= self.cfg.gate.tolerance_mm:
            if not self._needle_ok_for_lock(frame):
                self._phase.settle_since_ns = None
                return
            if self._phase.settle_since_ns is None:
                self._phase.settle_since_ns = frame.left.t_ns
            if (frame.left.t_ns - self._phase.settle_since_ns) * 1e-9 >= c.settle_s:
                self.fire(Event.ALIGNED, f"guide within {err:.3f} mm for {c.settle_s} s, gate open")
        else:
            self._phase.settle_since_ns = None

    def _needle_ok_for_lock(self, frame: StereoFrame) -> bool:
        """Before LOCK: True unless ``lock.needle_check.required_before_lock`` and the needle axis
        is not measured or out of bounds (then ``needle_check_refused`` is logged with the reason)."""
        nc = self.cfg.lock.needle_check
        if nc is None or not nc.required_before_lock:
            return True
        if self.needle_check is None:
            reason = "needle check required but no needle checker (camera model) is configured"
            self.session.write("needle_check_refused", reason=reason)
            return False
        m = self._needle_axis(frame)
        if m is None:
            self.session.write("needle_check_refused", reason="needle axis not measured in this frame")
            return False
        pe = m.path_error
        if not pe.within(nc.max_direction_deg, nc.max_offset_mm):
            reason = (f"needle axis {pe.direction_error_deg:.2f} deg / entry {pe.entry_offset_mm:.2f} mm / "
                      f"target {pe.target_offset_mm:.2f} mm off the plan "
                      f"(limits {nc.max_direction_deg} deg, {nc.max_offset_mm} mm)")
            self.session.write("needle_check_refused", reason=reason,
                               direction_error_deg=pe.direction_error_deg, entry_offset_mm=pe.entry_offset_mm,
                               target_offset_mm=pe.target_offset_mm)
            return False
        return True

    def _servo_once(self, frame: StereoFrame, dt: float, hold_s: float) -> tuple[float, RigidTransform]:
        """One rate-limited servo command on the motion predicted for when it takes effect:
        now + half the time it is held + the robot's actuation lag (capped). Returns (prediction
        horizon after the frame, s; the command)."""
        c = self.cfg.compensation
        now = self.clock.now_ns()
        horizon_ns = 0
        if c.predict_latency:
            lead_s = (now - frame.left.t_ns) * 1e-9 + 0.5 * hold_s + c.actuation_lag_s
            horizon_ns = round(min(lead_s, c.max_prediction_s) * 1e9)
        T_pred = self._global(self.filter.estimate(frame.left.t_ns + horizon_ns, c.max_prediction_s))
        cmd = self.limiter.step(self._desired_tcp_robot(T_pred), dt, self._ramp_scale())
        self.safety.servo(cmd, dt)
        self._last_cmd_ns = self.clock.now_ns()
        return horizon_ns * 1e-9, cmd

    def _ramp_scale(self) -> float:
        """Speed scale of the servo stream: ramps from ``initial_speed_fraction`` to 1 over
        ``ramp_s`` after the last resume / recovery (1 when there was none)."""
        if self._resumed_ns is None:
            return 1.0
        r = self.cfg.resume
        f0 = r.initial_speed_fraction
        since_s = (self.clock.now_ns() - self._resumed_ns) * 1e-9
        return min(1.0, f0 + (1.0 - f0) * since_s / r.ramp_s)

    def _step_lock(self, frame: StereoFrame) -> None:
        lk, ph = self.cfg.lock, self._phase
        if self.T_change_meas is not None:
            why = correction_out_of_bounds(self._local(self.T_change_meas), self.cfg.compensation)
            if why is not None:
                self.fire(Event.CORRECTION_OUT_OF_BOUNDS, why + "; operator decision needed")
                return
        err = self._guide_error_optical_mm()
        self.session.write("lock_measured", guide_error_mm=err, gate_deviation_mm=self._gate_deviation())
        self._track_needle()
        if err is not None and err > lk.drift_alarm_mm:
            if not ph.alarmed:
                ph.alarmed = True
                self.session.write("drift_alarm", guide_error_mm=err, limit_mm=lk.drift_alarm_mm,
                                   policy=lk.on_drift)
                _log.warning("drift_alarm", guide_error_mm=err, policy=lk.on_drift)
            if lk.on_drift == "retract":
                self.fire(Event.DRIFT_DETECTED, f"guide {err:.2f} mm off the moving entry while locked")
                return
            if lk.on_drift == "compensate":
                self.fire(Event.LOCK_LOST, f"guide {err:.2f} mm off the moving entry while locked")
                return
        if self._needle_alarm(frame):
            return
        if lk.hold_s > 0 and self._elapsed_s() >= lk.hold_s and self.fsm.pending is None:
            self.fire(Event.LOCK_COMPLETED, f"held {lk.hold_s} s")

    def _needle_alarm(self, frame: StereoFrame) -> bool:
        """While locked: measure the needle axis; when it is out of bounds and
        ``alarm_while_locked``, log ``needle_axis_alarm`` (once per LOCK) and apply
        ``lock.on_drift``. Returns True when a transition was fired."""
        nc, lk, ph = self.cfg.lock.needle_check, self.cfg.lock, self._phase
        m = self._needle_axis(frame)
        if nc is None or m is None or not nc.alarm_while_locked:
            return False
        pe = m.path_error
        if pe.within(nc.max_direction_deg, nc.max_offset_mm):
            return False
        why = (f"needle axis {pe.direction_error_deg:.2f} deg / entry {pe.entry_offset_mm:.2f} mm / "
               f"target {pe.target_offset_mm:.2f} mm off the plan while locked")
        if not ph.needle_alarmed:
            ph.needle_alarmed = True
            self.session.write("needle_axis_alarm", reason=why, direction_error_deg=pe.direction_error_deg,
                               entry_offset_mm=pe.entry_offset_mm, target_offset_mm=pe.target_offset_mm,
                               limit_deg=nc.max_direction_deg, limit_mm=nc.max_offset_mm, policy=lk.on_drift)
            _log.warning("needle_axis_alarm", direction_error_deg=pe.direction_error_deg, policy=lk.on_drift)
        if lk.on_drift == "retract":
            self.fire(Event.DRIFT_DETECTED, why)
            return True
        if lk.on_drift == "compensate":
            self.fire(Event.LOCK_LOST, why)
            return True
        return False

    def _step_retract(self) -> None:
        st, ph = self.last_state, self._phase
        assert st is not None
        assert ph.target is not None
        if self._elapsed_s() > 30.0:
            self.fire(Event.TIMED_OUT, "retract not finished within 30 s")
            return
        left_mm = float(np.linalg.norm(st.T_robot_from_tcp.t - ph.target.t))
        if st.mode is not RobotMode.MOVING and left_mm < 1.0:
            self.fire(Event.RETRACTED, f"backed off {self.cfg.lock.retract_mm} mm along the guide axis")

    # ------------------------------------------------------------------ truth and summary
    def _true_errors(self) -> tuple[float, float] | None:
        """(position error mm, direction error deg) of the real guide against the real moving
        path, from the simulator's truth."""
        if self.truth is None or self.guide_plan is None:
            return None
        try:
            state = self.robot.state_now()  # the arm now, at the same instant as the truth
        except DriverError:
            return None
        now = state.t_ns
        T_robot_from_guide = state.T_robot_from_tcp @ self.rig.T_tcp_from_guide
        T_guide = self.truth.T_optical_from_robot @ T_robot_from_guide
        true_flange = getattr(self.truth, "T_optical_from_flange", None)  # the real arm, not its report
        if callable(true_flange) and (T_of := true_flange(now := self.clock.now_ns())) is not None:
            T_guide = T_of @ self.rig.T_flange_from_guide
        entry = np.asarray(self.truth.entry_optical(now), dtype=np.float64)
        target = np.asarray(self.truth.target_optical(now), dtype=np.float64)
        u = (target - entry) / np.linalg.norm(target - entry)
        ideal = entry - self.guide_plan.standoff_mm * u
        pos = float(np.linalg.norm(T_guide.t - ideal))
        cosang = float(np.clip(T_guide.R[:, 2] @ u, -1.0, 1.0))
        return pos, math.degrees(math.acos(cosang))

    def _measure_truth(self) -> None:
        if self.state not in (State.COMPENSATE, State.LOCK):
            return
        errs = self._true_errors()
        if errs is None:
            return
        if self.state is State.COMPENSATE:
            self.comp_errors_mm.append(errs[0])
            self.comp_error_age_s.append(self._elapsed_s())
        else:
            self.lock_errors.append(errs)
        self.session.write("truth_error", state=self.state, position_mm=errs[0], direction_deg=errs[1])

    def summary(self) -> RunSummary:
        states: list[str] = []
        for row in self.timeline:
            if not states or states[-1] != row["state"]:
                states.append(row["state"])
        lock = self.lock_errors[0] if self.lock_errors else None  # at the moment of locking
        comp = self.comp_errors_mm
        lat = list(self.latency_ms)
        return RunSummary(
            final_state=self.state.value, states=states, timeline=self.timeline,
            fre_mm=None if self.patient_reg is None else self.patient_reg.fre_rms_mm,
            tre_expected_mm=None if self.patient_reg is None else self.patient_reg.tre_expected_mm,
            robot_fre_mm=None if self.robot_reg is None else self.robot_reg.fre_rms_mm,
            lock_error_mm=None if lock is None else lock[0],
            lock_error_max_mm=max(e[0] for e in self.lock_errors) if self.lock_errors else None,
            lock_direction_error_deg=None if lock is None else lock[1],
            comp_error_rms_mm=float(np.sqrt(np.mean(np.square(comp)))) if comp else None,
            comp_error_p95_mm=_pct(comp, 95), comp_error_max_mm=max(comp) if comp else None,
            latency_ms={"p50": _pct(lat, 50), "p95": _pct(lat, 95)},
            processing_ms={"p50": _pct(self.processing_ms, 50), "p95": _pct(self.processing_ms, 95)},
            gate_open_fraction=(self.gate_open_samples / self.gate_samples) if self.gate_samples else None,
            time_to_lock_s=self.lock_time_s, duration_s=self.t_s(), frames=self.frames,
            commands_sent=self.safety.commands_sent, commands_refused=self.safety.commands_refused,
            faults=list(self.faults), session_log=str(self.session.path), comp_errors_mm=list(comp),
            comp_error_age_s=list(self.comp_error_age_s),
            needle_direction_error_deg=self._needle_summary_deg(),
            tracked_needle=self.tracked_needle,
        )

    def _needle_summary_deg(self) -> float | None:
        """The needle-axis direction error for the summary: the first measurement while locked,
        else the last one made (before LOCK), else None."""
        locked = [e for s, e in self.needle_errors_deg if s == State.LOCK.value]
        if locked:
            return locked[0]
        return self.needle_errors_deg[-1][1] if self.needle_errors_deg else None


def _count(markers: FloatArray | None) -> int:
    """Markers with a position (finite rows)."""
    return 0 if markers is None else int(np.all(np.isfinite(markers), axis=1).sum())


def _mean_transform(ts: list[RigidTransform]) -> RigidTransform:
    """Mean of nearby rigid transforms (translation mean; rotation by rotation-vector mean about
    the first)."""
    base = ts[0]
    rv = np.mean([(base.inverse() @ T).as_rotvec() for T in ts], axis=0)
    R = base.R @ RigidTransform.from_rotvec(rv).R
    return RigidTransform(R, np.mean([T.t for T in ts], axis=0))
