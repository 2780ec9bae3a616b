"""The controller's parts and everything that is not the tick: construction (estimate, phases,
supervisor, pipeline, meters), the operator's commands and their verdicts, read-only accessors
for observers and tests, and the run summary. :class:`~hil.controller.controller.Controller`
adds the tick and the event processing."""

from __future__ import annotations

import abc
import collections
import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from drivers.interfaces.camera import StereoCamera, StereoFrame
from drivers.interfaces.errors import DriverError
from drivers.interfaces.robot import MotionLimits, Robot, RobotState
from drivers.interfaces.tracker import PoseTracker
from hil.clock import Clock
from hil.controller import events as ev
from hil.controller.commands import Command
from hil.controller.compensation import limiter_args
from hil.controller.config import ProcedureConfig
from hil.controller.cost import PairCosts
from hil.controller.crosscheck import CameraCrossCheck, CrossCheckBounds
from hil.controller.estimate import Estimate, FloatArray, count_seen
from hil.controller.fsm import Event, FireResult, Fsm, State
from hil.controller.markers import MarkerTracker
from hil.controller.metrics import RunMetrics, RunSummary, TruthMeter, percentile
from hil.controller.needle import NeedleAxisChecker, NeedleCheck
from hil.controller.observers import HookCaller, Observers, TickObserver
from hil.controller.operator_input import (
    AcknowledgingOperator,
    CommandResult,
    Operator,
    OperatorCommand,
    OperatorView,
    Outcome,
)
from hil.controller.phases.approach import ApproachPhase
from hil.controller.phases.base import Phase, PhaseContext, ServoTiming
from hil.controller.phases.compensate import CompensatePhase
from hil.controller.phases.gate import GatePhase
from hil.controller.phases.halt import HaltPhase
from hil.controller.phases.lock import LockPhase
from hil.controller.phases.plan import PlanPhase
from hil.controller.phases.register import RegisterPhase
from hil.controller.phases.retract import RetractPhase
from hil.controller.pipeline import DevicePipeline, MarkerLocator
from hil.controller.plan_file import ProcedurePlan
from hil.controller.planning import GuidePlan, RigGeometry
from hil.controller.registration import PatientRegistration, RobotRegistration
from hil.controller.series import SampleSeries
from hil.controller.snapshot import (
    ControllerSnapshot,
    TimelineRow,
    frozen_array,
    frozen_transform,
    guide_in_image,
)
from hil.controller.supervisor import Supervisor
from hil.controller.tracker_roles import TrackerRoles
from hil.controller.tracker_use import TrackerUse
from hil.controller.truth import BreathHoldCoach, GroundTruth
from hil.geometry.transform import RigidTransform
from hil.heap import HeapTrimmer
from hil.log import get_logger
from hil.safety.layer import SafetyLayer
from hil.safety.watchdog import WatchdogSet
from hil.servo.client import ServoRobot, in_process_servo, servo_event_logger
from hil.servo.figures import StatsEverySecond
from hil.servo.limiter import RateLimiter
from hil.servo.link import InProcessLink
from hil.session.log import SessionLog

_log = get_logger(__name__)


def _finite(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


def _target_fields(est: Estimate) -> dict[str, Any]:
    """The snapshot's ``target_*`` fields (the rigid direction: the defaults)."""
    steer = est.target_steer
    if est.comp_cfg.target_model == "rigid":
        return {}
    sensed = None if est.target_sensor is None else steer   # the sensor's fields: only with one
    return {"target_model": est.comp_cfg.target_model,
            "target_shift_mm": None if steer is None else steer.target_shift_mm,
            "target_turn_deg": None if steer is None else steer.turn_deg,
            "target_fallback": None if steer is None else steer.fallback,
            "target_limited": None if steer is None else steer.limited,
            "target_source": None if sensed is None else sensed.source,
            "target_sensor_why_not": None if sensed is None else sensed.sensor_why_not}


def _breathing_fields(preg: PatientRegistration | None) -> dict[str, Any]:
    """The snapshot's ``breathing_*`` fields (none without a 4D CT's breathing model)."""
    b = None if preg is None else preg.breathing
    if b is None:
        return {}
    return {"breathing_entry_shift_mm": b.entry_shift_mm, "breathing_target_shift_mm": b.target_shift_mm,
            "breathing_kept_rigid_because": b.kept_rigid_because}


def _path_fields(est: Estimate) -> dict[str, Any]:
    """The snapshot's ``path_*`` fields (none before a change was measured)."""
    preg, change, t_ns = est.patient_reg, est.T_change_meas, est.change_t_ns
    if preg is None or change is None or t_ns is None:
        return {}
    planned = preg.T_optical_from_image.apply(np.vstack([est.plan.entry_mm, est.plan.target_mm]))
    return {"path_optical_mm": frozen_array(change.apply(planned)), "path_t_ns": t_ns}


def _predictor_fields(est: Estimate) -> dict[str, Any]:
    """The snapshot's ``predictor*`` fields (alpha-beta alone: the defaults)."""
    cp = est.filter.predictor
    if cp is None:
        return {}
    return {"predictor": cp.name, "predictor_active": cp.predicting, "predictor_fallbacks": cp.fallbacks,
            "predictor_fallback_reason": cp.last_fallback_reason}


class ControllerParts(abc.ABC):
    """Builds the controller's parts.

    Args:
        camera, robot, tracker: ACTIVE devices (tracker optional; it is watched, not used to steer).
        clock: the controller clock (the devices' clock).
        locate: perception, stereo frame -> marker centres in the optical frame.
        plan: the procedure plan (image frame).
        rig: end-effector geometry (guide frame, flange markers, TCP).
        procedure: tolerances and policies.
        limits: the safety layer's motion limits.
        watchdog_ages_s: ``{"camera": s, "robot": s, "tracker": s}``.
        camera_silence_s: how long no stereo pair may arrive before the camera is lost, s (None:
            4 frame periods, at least 0.2 s; :meth:`DevicePipeline.grab_timeout_s`).
        session: the session log (every event, transition, command, measurement, fault).
        observers: called with a frozen snapshot at the end of every tick (display, stream), in
            the controller's thread; their exceptions are logged (``observer_failed``) and never
            stop the control loop (:mod:`hil.controller.observers`).
        hooks: the plugins' runtime hooks (``hil_on_tick``, ``hil_on_transition``), same rules.
        tracker_use: the magnetic tracker's part (``[procedure.tracking]``); None: not used.
        operator: operator input.
        coach: asks the patient for breath-holds (the simulated world, or None on a rig).
        truth: ground truth for error measurement (simulation only).
        needle_check: the optical needle-axis check (seed 004); None: never made.
    """

    def __init__(
        self, *, camera: StereoCamera, robot: Robot, tracker: PoseTracker | None, clock: Clock,
        locate: MarkerLocator, plan: ProcedurePlan, rig: RigGeometry, procedure: ProcedureConfig,
        limits: MotionLimits, watchdog_ages_s: dict[str, float], session: SessionLog,
        operator: Operator, coach: BreathHoldCoach | None = None, truth: GroundTruth | None = None,
        needle_check: NeedleAxisChecker | None = None,
        observers: Sequence[TickObserver] = (),
        tracker_use: TrackerUse | None = None,
        hooks: HookCaller | None = None,
        crosscheck: CrossCheckBounds | None = None,
        camera_silence_s: float | None = None,
    ) -> None:
        robot = self._servo_robot(robot, limits, procedure, rig, clock, session)
        self.camera, self.robot, self.tracker, self.clock = camera, robot, tracker, clock
        self.servo_stats = StatsEverySecond(lambda: robot.link.regions.stats)
        self._robot_view = robot.state_view()   # the arm for snapshots: never takes the loop's events
        self.locate, self.plan, self.rig, self.cfg = locate, plan, rig, procedure
        self.session, self.operator, self.coach, self.truth = session, operator, coach, truth
        #: the simulator's truth meter: the first observer of the snapshots (never used for control)
        self.truth_meter = TruthMeter(truth, rig, session)
        self.observing = Observers(([self.truth_meter] if truth is not None else []) + list(observers),
                                   hooks, session)
        self.tracker_use = tracker_use if tracker is not None else None
        self.fsm = Fsm(procedure.confirm, listener=self._on_fire)
        self.safety = SafetyLayer(robot, limits, clock,
                                  robot_state_max_age_s=watchdog_ages_s.get("robot", 0.05),
                                  log=lambda name, f: session.write(name, **f))
        ages = {k: v for k, v in watchdog_ages_s.items() if k != "tracker" or tracker is not None}
        self.watchdogs = WatchdogSet(ages)
        self.frame_period_s = 1.0 / camera.frame_rate_hz
        self.t0_ns = clock.now_ns()
        self.est = Estimate(plan, rig, procedure, camera.frame_rate_hz,
                            None if self.tracker_use is None else self.tracker_use.target_sensor())
        self.metrics = RunMetrics()
        self.heap = HeapTrimmer(procedure.heap_trim_every_s)   # free heap pages back (hil/heap.py)
        sup_ms = procedure.supervisor_period_ms
        self.pipeline = DevicePipeline(camera, robot, tracker, clock, locate, self.watchdogs, session,
                                       self.metrics, None if sup_ms is None else sup_ms / 1e3,
                                       camera_silence_s)
        self.supervisor = Supervisor(robot, self.safety, self.watchdogs, session)
        self.markers = MarkerTracker(procedure.registration.match_tolerance_mm)
        self.crosscheck = CameraCrossCheck(crosscheck or CrossCheckBounds())
        self.roles = TrackerRoles(self.tracker_use, session)
        self.needle = NeedleCheck(procedure.lock.needle_check, needle_check, session)
        self.needle_check = needle_check
        self.ctx = PhaseContext(
            cfg=procedure, est=self.est, clock=clock, session=session, safety=self.safety, robot=robot,
            roles=self.roles, needle=self.needle, coach=coach, frame_period_s=self.frame_period_s,
            pending=self._pending_name, execute=self.execute, servo_timing=self._servo_timing,
            step_servo=robot.link.step if isinstance(robot.link, InProcessLink) else None)
        forward: list[Phase] = [cls(self.ctx) for cls in (RegisterPhase, PlanPhase, ApproachPhase, GatePhase,
                                                          CompensatePhase, LockPhase, RetractPhase)]
        self.phases: dict[State, Phase] = {p.state: p for p in forward}
        for s in HaltPhase.HALTS:
            self.phases[s] = HaltPhase(self.ctx, s)
        self._phase: Phase = self.phases[State.IDLE]
        self._phase.entered_ns = self.t0_ns
        self._queue: collections.deque[tuple[Event, str]] = collections.deque()
        self._processing = False
        self._last_reason = ""
        self._started = False
        #: operator commands taken and decided (each has an ``operator_command_result`` record)
        self.operator_commands_decided = 0
        self.timeline: list[dict[str, Any]] = [
            {"t_s": 0.0, "state": State.IDLE.value, "event": None, "reason": "initial"}]

    # the tick's side (Controller)
    @abc.abstractmethod
    def execute(self, cmd: Command) -> None:
        """Run one command through the safety layer."""

    @abc.abstractmethod
    def fire(self, event: Event, reason: str = "") -> FireResult:
        """Queue an event and process the queue."""

    # ------------------------------------------------------------------ helpers
    def t_s(self, t_ns: int | None = None) -> float:
        return ((self.clock.now_ns() if t_ns is None else t_ns) - self.t0_ns) * 1e-9

    @property
    def state(self) -> State:
        return self.fsm.state

    @property
    def sub_state(self) -> str | None:
        """The current phase's sub-state (None when it has none)."""
        sub = self._phase.sub_state
        return None if sub is None else str(sub.value)

    def _pending_name(self) -> str | None:
        p = self.fsm.pending
        return None if p is None else p.goto.name

    def view(self) -> OperatorView:
        return OperatorView(self.state, self._pending_name(), self._last_reason, self.t_s(), self._started)

    @staticmethod
    def _servo_robot(robot: Robot, limits: MotionLimits, procedure: ProcedureConfig, rig: RigGeometry,
                     clock: Clock, session: SessionLog) -> ServoRobot:
        """The robot behind its servo loop: a :class:`ServoRobot` as given (the servo process,
        started by the assembly), else ``robot`` behind a loop stepped in this process."""
        if isinstance(robot, ServoRobot):
            if robot.on_event is None:
                robot.on_event = servo_event_logger(session)
            return robot
        return in_process_servo(robot, limits, RateLimiter(*limiter_args(procedure, rig.T_tcp_from_guide)),
                                clock, servo_event_logger(session))

    def _servo_timing(self) -> ServoTiming:
        ready = self.pipeline.next_pair_ready
        return ServoTiming(None if self.pipeline.prefetch is None else (lambda: bool(ready())),
                           self.pipeline.grab_timeout_s(), self.watchdogs["camera"].max_age_s)

    def _on_fire(self, r: FireResult) -> None:
        if r.kind == "stay" and r.event.value.endswith("_received"):
            return  # data events are summarised by the measurement records
        self.session.write(ev.FIRE_RECORD[r.kind], source=r.source, target=r.target, input=r.event,
                           reason=r.reason, transition=r.transition_name)
        if r.kind == "rejected":
            _log.info("transition_rejected", source=r.source.value, input=r.event.value, reason=r.reason)
        elif r.kind == "transition":
            _log.info("transition_applied", source=r.source.value, target=r.target.value,
                      input=r.event.value, reason=r.reason)

    def _log_frame(self, frame: StereoFrame, st: RobotState) -> None:
        est = self.est
        cc = self.crosscheck.last
        self.session.write(ev.FRAME_MEASURED, frame_seq=frame.left.seq, exposure_t_ns=frame.left.t_ns,
                           skin_markers=count_seen(est.live_mm), flange_markers=count_seen(est.flange_mm),
                           gate_deviation_mm=est.gate_deviation_mm(), robot_tcp_mm=st.T_robot_from_tcp.t,
                           tcp_speed_mm_s=st.tcp_speed_mm_s, live_mm=est.live_mm,
                           flange_mm=est.flange_mm,
                           T_robot_from_guide=st.T_robot_from_tcp @ est.rig.T_tcp_from_guide,
                           camera_discrepancy_mm=None if cc is None else round(cc[0], 4))

    def _notify_observers(self) -> None:
        """After the tick (whatever it did): the observers and ``hil_on_tick`` get a snapshot."""
        if self.observing.watching_ticks():
            self.observing.on_tick(self.snapshot())

    def _notify_transition(self, res: FireResult) -> None:
        """After an applied transition's entry action: ``hil_on_transition`` gets it with a snapshot."""
        if self.observing.watching_transitions():
            self.observing.on_transition(res, self.snapshot())

    # ------------------------------------------------------------------ operator input
    def _handle_operator(self, cmd: OperatorCommand) -> None:
        """Decide one operator command and record it: ``operator_command`` (what was asked, by
        whom), the state machine's own records, then ``operator_command_result`` (the verdict),
        which an acknowledging operator is also handed. Never raises for a refused command."""
        event = cmd.event
        self.session.write(ev.OPERATOR_COMMAND, input=event, command_seq=cmd.seq, origin=cmd.origin,
                           confirms=cmd.confirms, decline=cmd.decline, posted_ns=cmd.posted_ns or None)
        if event is Event.START_REQUESTED and not cmd.decline:
            self._started = True
        state = self.state
        outcome, reason = self._decide_operator(cmd)
        self.operator_commands_decided += 1
        self._record_result(CommandResult(cmd.seq, cmd.origin, event.value, outcome, reason, state.value))

    def _decide_operator(self, cmd: OperatorCommand) -> tuple[Outcome, str]:
        """The verdict on ``cmd`` (see :mod:`hil.controller.operator_input`): a confirmation
        must name the transition pending now; a start or reset needs a ready robot; anything
        else is the state machine's decision."""
        event = cmd.event
        if event is Event.CONFIRM_REQUESTED and (cmd.confirms is not None or cmd.decline):
            pending = self._pending_name()
            shown = pending if cmd.confirms is None else cmd.confirms
            if pending is None:
                return "rejected", "nothing awaits confirmation" + (
                    f" ({shown} was already decided)" if shown else "")
            if shown != pending:
                if not shown:
                    return "rejected", (f"{pending} awaits confirmation, but no prompt was shown when "
                                        "this was pressed: read the prompt, then confirm")
                return "rejected", (f"the prompt answered was {shown}, but {pending} awaits "
                                    "confirmation now: read the prompt, then confirm")
            if cmd.decline:
                return "declined", f"{pending} still awaits confirmation: c confirm, a abort"
        if event in (Event.START_REQUESTED, Event.RESET_REQUESTED) and self.fsm.accepts(event):
            why = self.supervisor.robot_ready_for(event, self.state)
            if why:
                self._last_reason = why
                return "rejected", why
        res = self.fire(event, "operator")
        if res.kind == "transition":
            return "executed", f"{res.transition_name}: {res.source.value} -> {res.target.value}"
        if res.kind == "pending":
            return "pending", f"{res.transition_name} awaits confirmation"
        if res.kind == "rejected":
            reason = res.reason
            guarded = reason in ("guard has_plan is false", "guard plan_current is false")
            if guarded and self.est.guide_plan is None:
                reason = "no guide plan yet: register first (s)"
            elif reason == "guard plan_current is false":
                reason = ("the guide plan belongs to a registration that was restarted: register and plan "
                          "first (s)")
            return "rejected", reason
        return "executed", res.reason

    def _record_result(self, result: CommandResult) -> None:
        self._write_result(result)
        (_log.info if result.accepted else _log.warning)(
            ev.OPERATOR_COMMAND_RESULT, input=result.input, outcome=result.outcome, reason=result.reason)
        if isinstance(self.operator, AcknowledgingOperator):
            self.operator.acknowledge(result)

    def _write_result(self, result: CommandResult) -> None:
        self.session.write(ev.OPERATOR_COMMAND_RESULT, command_seq=result.seq, origin=result.origin,
                           input=result.input, outcome=result.outcome, reason=result.reason,
                           state=result.state)

    def log_refused_inputs(self) -> None:
        """Write the inputs the operator refused before they reached the controller (a full
        queue, a closing console). Called by the thread that owns the session log: the tick
        does it, and the console once its loop has ended."""
        if isinstance(self.operator, AcknowledgingOperator):
            for result in self.operator.drain_refused():
                self._write_result(result)

    # ------------------------------------------------------------------ read-only accessors
    @property
    def patient_reg(self) -> PatientRegistration | None:
        return self.est.patient_reg

    @property
    def robot_reg(self) -> RobotRegistration | None:
        return self.est.robot_reg

    @property
    def guide_plan(self) -> GuidePlan | None:
        return self.est.guide_plan

    @property
    def T_bias(self) -> RigidTransform:
        return self.est.T_bias

    @property
    def live_mm(self) -> FloatArray | None:
        return self.est.live_mm

    @property
    def flange_mm(self) -> FloatArray | None:
        return self.est.flange_mm

    @property
    def T_change_meas(self) -> RigidTransform | None:
        return self.est.T_change_meas

    @property
    def last_state(self) -> RobotState | None:
        return self.est.last_state

    @property
    def faults(self) -> list[str]:
        return self.supervisor.faults

    @property
    def frames(self) -> int:
        return self.metrics.frames

    @property
    def frames_overwritten(self) -> int:
        return self.metrics.frames_overwritten

    @property
    def latency_ms(self) -> SampleSeries:
        return self.ctx.latency_ms

    @property
    def pair_costs(self) -> PairCosts:
        """COMPENSATE's setpoint work, the change estimator's time and their sum per pair so far, µs."""
        return PairCosts(self.ctx.setpoint_cost.figures(), self.markers.change_cost.figures(),
                         self.ctx.pair_model_cost.figures())

    @property
    def servo_deadlines_missed(self) -> int:
        return self.ctx.servo_deadlines_missed

    @property
    def comp_errors_mm(self) -> SampleSeries:
        return self.truth_meter.comp_errors_mm

    @property
    def lock_errors(self) -> list[tuple[float, float]]:
        return self.truth_meter.lock_errors

    def guide_error_optical_mm(self) -> float | None:
        """The camera-measured guide error against the patient as seen in the latest pair, mm."""
        return self.est.guide_error_optical_mm()

    # ------------------------------------------------------------------ snapshot
    def snapshot(self) -> ControllerSnapshot:
        """The controller now, frozen (:mod:`hil.controller.snapshot`). Call in the controller's
        thread, between ticks; bounded work."""
        est, state = self.est, self.state
        p = self.fsm.pending
        guide_err: float | None = None
        if state in (State.APPROACH, State.GATE, State.COMPENSATE, State.LOCK):
            guide_err = _finite(est.guide_error_optical_mm())
        truth: float | None = None
        tm = self.truth_meter
        if state is State.COMPENSATE and tm.comp_errors_mm:
            truth = tm.comp_errors_mm.last
        elif state is State.LOCK and tm.lock_errors:
            truth = tm.lock_errors[-1][0]
        try:
            robot_now: RobotState | None = self._robot_view.state_now()
        except DriverError:
            robot_now = None
        preg, rreg = est.patient_reg, est.robot_reg
        fit = est.change_fit
        gm = est.gate_measures() if preg is not None else None
        deviations = None if gm is None or not gm.deviations_mm else np.array(gm.deviations_mm)
        return ControllerSnapshot(
            t_ns=self.clock.now_ns(), t_s=self.t_s(), state=state.value, sub_state=self.sub_state,
            pending=None if p is None else p.goto.name, pending_reason="" if p is None else p.reason,
            last_reason=self._last_reason, started=self._started,
            timeline=tuple(TimelineRow(float(r["t_s"]), str(r["state"]), str(r.get("reason") or ""))
                           for r in self.timeline),
            fre_mm=None if preg is None else preg.fre_rms_mm,
            tre_expected_mm=None if preg is None else preg.tre_expected_mm,
            robot_fre_mm=None if rreg is None else rreg.fre_rms_mm,
            T_optical_from_image=frozen_transform(None if preg is None else preg.T_optical_from_image),
            T_robot_from_optical=frozen_transform(None if rreg is None else rreg.T_robot_from_optical),
            T_bias=frozen_transform(est.T_bias) or RigidTransform.identity(),
            T_change_meas=frozen_transform(est.T_change_meas),
            T_image_from_guide=frozen_transform(guide_in_image(est)),
            reference_optical_mm=frozen_array(None if preg is None else preg.reference_optical_mm),
            live_mm=frozen_array(est.live_mm), flange_mm=frozen_array(est.flange_mm),
            gate_deviation_mm=_finite(est.gate_deviation_mm()), guide_error_mm=guide_err,
            robot=est.last_state, tracker=dict(est.tracker_samples), faults=tuple(self.faults),
            frames=self.metrics.frames, commands_sent=self.safety.commands_sent,
            commands_refused=self.safety.commands_refused,
            operator_commands_decided=self.operator_commands_decided, truth_error_mm=truth,
            located=self.pipeline.last_located, robot_now=robot_now,
            standoff_mm=None if est.guide_plan is None else est.guide_plan.standoff_mm,
            change_estimator=None if fit is None else fit.estimator,
            change_fre_mm=None if fit is None else fit.rigid_fre_mm,
            marker_residuals_mm=frozen_array(None if fit is None else fit.residuals_mm),
            marker_deviations_mm=frozen_array(deviations),
            gate_shape_mm=None if gm is None else _finite(gm.shape_mm),
            gate_ok=None if gm is None else gm.problem(self.cfg.gate) is None,
            **_target_fields(est), **_predictor_fields(est), **_path_fields(est), **_breathing_fields(preg))

    # ------------------------------------------------------------------ summary
    def summary(self) -> RunSummary:
        states = [str(s) for s, _ in itertools.groupby(row["state"] for row in self.timeline)]
        tm, m, est = self.truth_meter, self.metrics, self.est
        lock = tm.lock_errors[0] if tm.lock_errors else None  # at the moment of locking
        comp = tm.comp_errors_mm
        lat = list(self.ctx.latency_ms)
        return RunSummary(
            final_state=self.state.value, states=states, timeline=self.timeline,
            fre_mm=None if est.patient_reg is None else est.patient_reg.fre_rms_mm,
            tre_expected_mm=None if est.patient_reg is None else est.patient_reg.tre_expected_mm,
            robot_fre_mm=None if est.robot_reg is None else est.robot_reg.fre_rms_mm,
            lock_error_mm=None if lock is None else lock[0],
            lock_error_max_mm=max(e[0] for e in tm.lock_errors) if tm.lock_errors else None,
            lock_direction_error_deg=None if lock is None else lock[1],
            comp_error_rms_mm=comp.rms, comp_error_p95_mm=percentile(comp, 95), comp_error_max_mm=comp.max,
            latency_ms={"p50": percentile(lat, 50), "p95": percentile(lat, 95)},
            processing_ms={"p50": percentile(m.processing_ms, 50), "p95": percentile(m.processing_ms, 95)},
            gate_open_fraction=m.gate_open_fraction, time_to_lock_s=m.lock_time_s, duration_s=self.t_s(),
            target_model_fallback_fraction=m.target_model_fallback_fraction,
            target_model_held_fraction=m.target_model_held_fraction,
            target_sensor_fraction=m.target_sensor_fraction, frames=m.frames,
            commands_sent=self.safety.commands_sent, commands_refused=self.safety.commands_refused,
            faults=list(self.faults), session_log=str(self.session.path), comp_errors_mm=list(comp),
            comp_error_age_s=list(tm.comp_error_age_s), needle_direction_error_deg=self.needle.summary_deg(),
            tracked_needle=self.roles.tracked_needle, **_body_truth(tm),
        )



def _body_truth(tm: TruthMeter) -> dict[str, Any]:
    """The summary's deformable-body truth fields (docs/run.md) from the truth meter."""
    lock = tm.lock_samples
    targets = [x.target_mm for x in lock]
    res = tm.rigid_residuals_mm
    return {
        "target_error_mm": targets[0] if targets else None,
        "target_error_max_mm": max(targets) if targets else None,
        "entry_axis_error_mm": lock[0].entry_mm if lock else None,
        "body_rigid_residual_mm_p95": percentile(res, 95),
        "body_rigid_residual_mm_max": res.max,
        "comp_target_error_p95_mm": percentile(tm.comp_target_errors_mm, 95),
        "comp_entry_error_p95_mm": percentile(tm.comp_entry_errors_mm, 95),
        "comp_entry_errors_mm": list(tm.comp_entry_errors_mm),
        "comp_path_error_p95_mm": _finite_p95(tm.comp_path_errors_mm),
        "comp_path_now_error_p95_mm": _finite_p95(tm.comp_path_now_errors_mm),
        "comp_path_errors_mm": list(tm.comp_path_errors_mm),
        "comp_path_now_errors_mm": list(tm.comp_path_now_errors_mm),
        "comp_path_entry_errors_mm": list(tm.comp_path_entry_errors_mm),
        "comp_path_direction_errors_deg": list(tm.comp_path_direction_errors_deg),
        "change_fre_mm": {"p50": percentile(tm.change_fre_mm, 50), "p95": percentile(tm.change_fre_mm, 95)},
        "lock_target_errors_mm": targets,
        "lock_entry_errors_mm": [x.entry_mm for x in lock],
        "gate_false_open_rate": tm.gate_false_open_ticks / tm.gate_open_ticks if tm.gate_open_ticks else None,
        "gate_open_ticks": tm.gate_open_ticks,
    }


def _finite_p95(series: Sequence[float] | SampleSeries) -> float | None:
    """The p95 of a series' finite samples (None when it has none)."""
    xs = [x for x in series if math.isfinite(x)]
    return percentile(xs, 95)
