"""The Controller: one tick per stereo pair, per supervisor period without one, or per operator
input that ends the wait for one, on an injected clock, through interfaces only. The arm is
commanded at its own rate by the servo loop (hil/servo; docs/architecture.md): the controller
publishes setpoints and stops to it.

A tick (docs/architecture.md draws it): the owed stop is retried and the operator's command is
decided -> the devices are read (:mod:`~hil.controller.pipeline`: the next pair, waited for at most
a supervisor period) -> the supervisor checks the watchdogs and the robot
(:mod:`~hil.controller.supervisor`) -> when a new pair arrived, perception identifies and tracks
the patient's markers into the estimate (:mod:`~hil.controller.markers`) -> the current phase
publishes the pair's setpoint (``Phase.command``: COMPENSATE's, so the frame -> command latency
carries nothing else) -> the flange markers (earlier when the setpoint needs them: a bias
correction) -> the tracker is read and its watchdog judged, when its samples take no part in the
markers (else it was read with the other devices) -> the camera cross-check and the frame's
record -> the current phase steps
(:mod:`~hil.controller.phases`) -> its commands are executed through the safety layer and its
events are processed by the state machine, in order. Entering a state runs its phase's entry
action the same way. Events are queued and processed one after the other, never fired from
inside another event's processing. Any device, safety or step error becomes FAULT_DETECTED with
the reason, and the robot is stopped.

Resumption (after pause, protective stop, reconnect or fault recovery) always starts from the
pose the robot reports *now*: APPROACH issues a fresh move from there; COMPENSATE restarts its
rate limiter from the actual pose at rest, with a speed ramp; no stored target is replayed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from drivers.interfaces.errors import DriverError
from hil.controller import events as ev
from hil.controller.commands import Command, Hold, MoveLinear, Stop, Track
from hil.controller.fsm import HALT_STATES, RECOVERY, Event, FireResult, State
from hil.controller.inputs import TickInputs
from hil.controller.markers import FlangeUpdate
from hil.controller.metrics import RunSummary
from hil.controller.operator_input import OperatorCommand, WakingOperator, as_command
from hil.controller.parts import ControllerParts
from hil.controller.phases.halt import HaltPhase
from hil.errors import HilError
from hil.log import get_logger
from hil.safety.layer import SafetyViolationError

if TYPE_CHECKING:
    from drivers.interfaces.camera import StereoFrame
    from drivers.interfaces.robot import RobotState

_log = get_logger(__name__)


class Controller(ControllerParts):
    """The procedure controller. Construction (devices, estimate, phases, supervisor) is
    :class:`~hil.controller.parts.ControllerParts`'s; this class runs the tick and the events."""

    # ------------------------------------------------------------------ events
    def fire(self, event: Event, reason: str = "") -> FireResult:
        """Queue an event and process the queue (module doc). Returns the result of ``event``."""
        self._queue.append((event, reason))
        first = self._drain()
        assert first is not None
        return first

    def fault(self, reason: str) -> None:
        """Record a fault, enter FAULT (or stay there) and stop the robot. A fault of a kind already
        recorded in this FAULT (the same reason but for its figures) is recorded once."""
        state = self.state
        if not self.supervisor.record_fault(reason, state):
            return
        self._queue.append((Event.FAULT_DETECTED, reason))
        self._drain()
        if state is State.FAULT:
            self.supervisor.stop_robot("fault: " + reason)

    def _drain(self) -> FireResult | None:
        """Process queued events in order (not re-entrantly: an event queued while processing
        is processed after the current one). Returns the first event's result."""
        if self._processing:
            return None
        self._processing = True
        first: FireResult | None = None
        try:
            while self._queue:
                event, reason = self._queue.popleft()
                # plan_current: a guide plan made on the patient registration in force (entering
                # REGISTER forgets the registration; resuming into APPROACH on the old plan would
                # guide on a registration that is gone)
                has_plan = self.est.guide_plan is not None
                guards = {"has_plan": has_plan, "plan_current": has_plan and self.est.patient_reg is not None}
                res = self.fsm.fire(event, reason=reason, guards=guards)
                first = first or res
                if res.changed:
                    self._last_reason = reason or res.transition_name
                    confirmed = event is Event.CONFIRM_REQUESTED
                    self.timeline.append({"t_s": round(self.t_s(), 4), "state": res.target.value,
                                          "event": res.event.value, "confirmed": confirmed,
                                          "reason": res.reason if confirmed else reason})
                    self._enter(res)
                    self._notify_transition(res)
        finally:
            self._processing = False
        return first

    def _enter(self, res: FireResult) -> None:
        now = self.clock.now_ns()
        resumed = res.transition_name in RECOVERY
        if resumed:
            self.est.resumed_ns = now
        self.supervisor.supersede_stop()  # the new state's entry action commands the robot itself
        s = res.target
        self.session.write(ev.STATE_ENTERED, state=s, reason=res.reason, transition=res.transition_name)
        phase = self.phases[s]
        self._phase = phase
        try:
            out = phase.enter_with_reason(now, res.transition_name, resumed, res.reason) \
                if isinstance(phase, HaltPhase) else phase.enter(now, res.transition_name, resumed)
            for cmd in out.commands:
                self.execute(cmd)
            self._queue.extend(out.events)
        except (DriverError, SafetyViolationError) as exc:
            if s is not State.FAULT:
                self.fault(f"entering {s.value}: {exc}")
        if s is State.LOCK and self.metrics.lock_time_s is None:
            self.metrics.lock_time_s = self.t_s()

    def execute(self, cmd: Command) -> None:
        """Run one command through the safety layer (a stop through the supervisor, which owes
        an undelivered one). Raises the safety layer's or the driver's error."""
        if isinstance(cmd, MoveLinear):
            self.safety.move_linear(cmd.target, cmd.speed_mm_s, cmd.accel_mm_s2)
        elif isinstance(cmd, Track):
            self.safety.track(cmd.setpoint, cmd.v_mm_s, cmd.w_rad_s, t_ref_ns=cmd.t_ref_ns,
                              valid_until_ns=cmd.valid_until_ns, exposure_t_ns=cmd.exposure_t_ns,
                              frame_seq=cmd.frame_seq, speed_scale=cmd.speed_scale,
                              max_horizon_s=cmd.max_horizon_s, lead_s=cmd.lead_s, state=cmd.robot_state)
        elif isinstance(cmd, Stop):
            self.supervisor.stop_robot(cmd.reason)
        else:
            assert isinstance(cmd, Hold)
            self.safety.hold(cmd.reason)

    # ------------------------------------------------------------------ the loop
    def run(self, max_duration_s: float | None = None) -> RunSummary:
        """Tick until the operator says the run is over or the time budget is spent. While it
        runs, the heap policy collects reference cycles and trims (hil/heap.py; started after the
        pipeline is primed, stopped on every path)."""
        limit = self.cfg.max_duration_s if max_duration_s is None else max_duration_s
        self.prime()
        self.watchdogs.arm(self.clock.now_ns())
        self.heap.start()
        try:
            with self.pipeline.prefetching(self.cfg.camera_prefetch):
                while not self.operator.finished(self.view()):
                    if self.t_s() > limit:
                        self.session.write(ev.RUN_TIME_EXCEEDED, limit_s=limit, state=self.state)
                        if self.state not in HALT_STATES:
                            self.fire(Event.ABORT_REQUESTED, f"procedure exceeded {limit} s")
                            self._notify_observers()  # the abort happened outside a tick: show it
                        break
                    self.tick()
        finally:
            self.heap.stop()
        return self.summary()

    def prime(self, timeout_s: float = 2.0) -> None:
        """Consume the camera pipeline's first (late) pair, once (see
        :meth:`~hil.controller.pipeline.DevicePipeline.prime`); the first time, record the
        following-error bounds the servo loop supervises with (``servo_following_bounds``)."""
        if not self.pipeline.primed:
            m = self.robot.following_model
            self.session.write(ev.SERVO_FOLLOWING_BOUNDS, lag_ms=round(m.time_constant_s * 1e3, 3),
                               bound_mm=m.max_error_mm, bound_deg=m.max_error_deg,
                               bound_ms=round(m.max_duration_s * 1e3, 3), bounds_from=m.source)
        self.pipeline.prime(timeout_s)

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
        self.metrics.processing_ms.append((time.perf_counter_ns() - t_start_wall) * 1e-6)
        self._notify_observers()
        self.heap.after_tick(self.clock.now_ns())   # after the setpoint and the observers

    def _tick(self) -> None:
        stats = self.servo_stats.due(self.clock.now_ns())
        if stats is not None:
            self.session.write(ev.SERVO_STATS, **stats)
        self.supervisor.retry_stop()
        self.log_refused_inputs()
        polled = self.operator.poll(self.view())
        command = None if polled is None else as_command(polled)
        if command is not None:
            self._handle_operator(command)
        try:
            # the tracker after the pair's setpoint, unless its samples take part in the markers
            st = self.pipeline.read(self.est, self._wake, defer_tracker=not self.roles.feeds_markers)
        except DriverError as exc:
            self.clock.sleep(self.frame_period_s)  # time moves on even when a device is gone
            self.fault(f"{exc.device}: {exc.message}")
            return
        if st is None:
            return  # an operator input waits: the next tick takes it before waiting for a pair
        if not self.pipeline.pair_arrived:   # with a pair: once its setpoint is out (_on_pair)
            self.fire(Event.ROBOT_STATE_RECEIVED)
        deferred = self.pipeline.tracker_deferred
        if self.est.tracker_samples and not deferred:
            self.fire(Event.TRACKER_SAMPLE_RECEIVED)
        reason = self.supervisor.check(self.clock.now_ns(), st, self.state,
                                       frozenset({"tracker"}) if deferred else frozenset())
        if reason is not None:
            self.fault(reason)
            return
        frame = self.est.last_frame
        if frame is None or not self.pipeline.pair_arrived:
            return  # a supervisor tick without a new pair (pipeline module doc): no perception, no step
        self._on_pair(frame, st, command)

    def _on_pair(self, frame: StereoFrame, st: RobotState, command: OperatorCommand | None) -> None:
        """A tick's new pair (module doc): markers, the setpoint, the deferred tracker, the
        cross-check and the record, then the phase's step and what it asks for."""
        points = self.pipeline.located(frame)
        self.markers.update_patient(self.est, points, frame.left.t_ns,
                                    lambda: self.roles.reference_sensor(self.est, self.state))
        detected_ns = self.clock.now_ns()
        flange = FlangeUpdate(self.markers, self.est, points)
        phase = self.phases[self.state] if self.state in self.STEPPED else None
        if phase is not None:   # the pair's setpoint first (latency); the judgement follows
            phase.command(TickInputs(detected_ns, command, frame, points, st, self.est.tracker_samples),
                          flange)
        flange()   # off the pair's path unless the setpoint needed it
        self.roles.target_sensor(self.est, self.state)
        self.fire(Event.ROBOT_STATE_RECEIVED)   # a data event every state stays in: off the pair's path
        if self.pipeline.tracker_deferred and not self._read_deferred_tracker():
            return
        inputs = TickInputs(detected_ns, command, frame, points, st, self.est.tracker_samples)
        reason = self.crosscheck.check(self.est, frame, self.state)
        if reason is not None:
            self.fault(reason)
            return
        self.metrics.on_frame(self.est, self.state)
        self.metrics.detect_ms.append((detected_ns - frame.left.t_ns) * 1e-6)
        self._log_frame(frame, st)
        self.fire(Event.FRAME_RECEIVED)
        out = phase.step(inputs) if phase is not None else None
        if out is not None:
            for cmd in out.commands:
                self.execute(cmd)
            self._queue.extend(out.events)
            self._drain()

    def _read_deferred_tracker(self) -> bool:
        """The tracker read :meth:`_on_pair` deferred, and its watchdog judged; False when either
        faulted (the tick ends)."""
        try:
            self.pipeline.read_tracker(self.est)
        except DriverError as exc:
            self.fault(f"{exc.device}: {exc.message}")
            return False
        if self.est.tracker_samples:
            self.fire(Event.TRACKER_SAMPLE_RECEIVED)
        reason = self.supervisor.check_watchdog("tracker", self.clock.now_ns())
        if reason is not None:
            self.fault(reason)
            return False
        return True

    @property
    def _wake(self) -> Callable[[], bool] | None:
        op = self.operator
        return op.input_waiting if isinstance(op, WakingOperator) else None

    #: States whose phase steps each pair (the halts only wait for the operator).
    STEPPED = frozenset({State.REGISTER, State.PLAN, State.APPROACH, State.GATE, State.COMPENSATE,
                         State.LOCK, State.RETRACT})

