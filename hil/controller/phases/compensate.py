"""COMPENSATE: follow the patient to the corrected entry. Each pair: the filtered rigid change of
the patient (about the entry point), bounded (beyond the bounds the operator decides), turned into
a tracking setpoint for the servo loop (the TCP pose at the pair's exposure and its velocity; the
loop extrapolates it over the measured latency, rate-limits and commands it at the robot's rate,
hil/servo); a slow optical bias correction (seed 001 §2.3); ALIGNED once the guide is within the
lock tolerance for the settle time with the gate open (and the needle check passed).

With ``[procedure.compensation] predictor`` other than alpha-beta, the setpoint is the secant of
that predictor's forecast (hil/controller/phases/predicted.py) whenever it answers, else the
filter's (warm-up, after a fallback); each fallback is written to the session log
(``predictor_fallback``) at the next pair, after its setpoint.

The setpoint goes through the safety layer (the context's command sink) like every other command.
It is published by :meth:`CompensatePhase.command`, which the tick calls as soon as the pair's
markers are in the estimate, before the camera cross-check, the frame's records and
:meth:`CompensatePhase.step`'s judgement (settling, ALIGNED): the pair's frame -> command latency
carries only what the setpoint needs.
With the servo loop in this process (a simulated run: ``PhaseContext.step_servo``), the phase
steps the loop at the robot's rate until the next pair is due; with the servo process it only
publishes.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

from hil.controller import events as ev
from hil.controller.commands import Track
from hil.controller.compensation import change_out_of_bounds, interpolate_pose
from hil.controller.fsm import Event, State
from hil.controller.gate import MovedPatientWatch
from hil.controller.phases.base import Phase, PhaseContext, PhaseResult
from hil.controller.phases.predicted import predicted_setpoint
from hil.controller.phases.streaming import stream_until_next_pair
from hil.controller.target_model import TargetSteer
from hil.geometry.transform import RigidTransform

if TYPE_CHECKING:
    from drivers.interfaces.camera import StereoFrame
    from drivers.interfaces.robot import RobotState
    from hil.controller.inputs import TickInputs


#: time step of the setpoint velocity's finite difference, s
_VELOCITY_STEP_S = 0.01


class CompensateSub(Enum):
    WAITING = "waiting"        # no measured change yet (markers not seen, filter not started)
    TRACKING = "tracking"      # streaming, guide not yet within tolerance
    SETTLING = "settling"      # within tolerance, waiting out the settle time


@dataclass(frozen=True)
class _Sent:
    """The setpoint :meth:`CompensatePhase.command` published for a pair (controller clock, ns)."""

    frame: StereoFrame
    change: RigidTransform     # the filtered patient change it follows (about the entry point)
    now_ns: int                # when the pair's handling began
    t_send_ns: int             # the in-process stream's deadlines count from this slot
    t_cmd_ns: int              # when the setpoint had been handed over
    horizon_s: float           # the prediction horizon at publication
    cmd: RigidTransform        # the pose at publication (robot frame)


@dataclass
class _Scratch:
    last_cmd_ns: int | None = None
    settle_since_ns: int | None = None
    sub: CompensateSub = CompensateSub.WAITING
    sent: _Sent | None = None
    #: whether the last setpoint came from the loop's predictor (False: the alpha-beta filter's)
    predicted: bool = False
    #: a patient who moved on the table (the markers never back while the shape is): GATE's watch
    moved: MovedPatientWatch | None = None


class CompensatePhase(Phase):
    state = State.COMPENSATE

    def __init__(self, ctx: PhaseContext) -> None:
        super().__init__(ctx)
        self.s = _Scratch()

    @property
    def sub_state(self) -> CompensateSub:
        return self.s.sub

    @property
    def setpoint_by(self) -> str:
        """What set the last setpoint: the configured predictor, or ``alpha-beta`` (configured,
        or the predictor's fallback)."""
        return self.ctx.cfg.compensation.predictor if self.s.predicted else "alpha-beta"

    def _say_fallbacks(self) -> None:
        """Write each predictor fallback since the last pair to the session log
        (:data:`~hil.controller.events.PREDICTOR_FALLBACK`)."""
        cp = self.ctx.est.filter.predictor
        if cp is None or not cp.unreported:
            return
        for f in cp.unreported:
            self.ctx.session.write(ev.PREDICTOR_FALLBACK, predictor=cp.name, reason=f.reason,
                                   fallbacks=f.fallbacks, exposure_t_ns=f.exposure_t_ns,
                                   fallback="alpha-beta", hold_s=self.ctx.cfg.compensation.predictor_hold_s)
        cp.unreported.clear()

    def on_enter(self, transition: str) -> PhaseResult:
        moved = MovedPatientWatch(self.ctx.cfg.gate)
        moved.restart(self.entered_ns)
        self.s = _Scratch(moved=moved)
        cp = self.ctx.est.filter.predictor
        if cp is not None:
            cp.unreported.clear()   # before COMPENSATE the predictor sets nothing (counted, not said)
        self.ctx.safety.start_tracking()   # the loop restarts from the actual pose, at rest
        return PhaseResult()

    def command(self, inputs: TickInputs, flange: Callable[[], None]) -> None:
        """Publish the pair's setpoint first, when nothing stands in the way (in time, the change
        measured, within the correction bounds); the tick's cross-check, records and
        :meth:`step`'s judgement follow. When something does, nothing is published here and
        :meth:`step` says why. ``flange`` brings the pair's flange markers in: called only when a
        bias correction is due (:meth:`_send`)."""
        self.s.sent = None
        c, est = self.ctx.cfg.compensation, self.ctx.est
        if self.elapsed_s() > c.timeout_s or est.T_change_meas is None or not est.filter.initialised:
            return
        change = est.filter.estimate()  # about the entry point
        if change_out_of_bounds(change, est.change_fit, c) is None:
            self.s.sent = self._send(inputs, change, flange)

    def step(self, inputs: TickInputs) -> PhaseResult:
        ctx, s, c, est = self.ctx, self.s, self.ctx.cfg.compensation, self.ctx.est
        frame = inputs.frame
        out = PhaseResult()
        self._say_fallbacks()
        sent, s.sent = (s.sent if s.sent is not None and s.sent.frame is frame else None), None
        if sent is None:   # command() published nothing for this pair: say why (or publish now)
            if self.elapsed_s() > c.timeout_s:
                return out.fire(Event.TIMED_OUT, f"not aligned within {c.timeout_s} s")
            if est.T_change_meas is None or not est.filter.initialised:
                s.sub = CompensateSub.WAITING
                return out  # markers not seen this frame: hold the last command (watchdogs cover staleness)
            change = est.filter.estimate()
            why = change_out_of_bounds(change, est.change_fit, c)
            if why is not None:
                ctx.session.write(ev.CORRECTION_OUT_OF_BOUNDS, reason=why, T_change=change)
                return out.fire(Event.CORRECTION_OUT_OF_BOUNDS, why + "; operator decision needed")
            sent = self._send(inputs, change)
        if ctx.step_servo is not None:
            stream_until_next_pair(ctx, frame, sent.now_ns, sent.t_send_ns, ctx.step_servo)
        err = est.guide_error_optical_mm()
        dev = est.gate_deviation_mm()
        fit, steer = est.change_fit, est.target_steer
        ctx.session.write(ev.COMPENSATION_STEP, exposure_t_ns=frame.left.t_ns,
                          latency_detect_ms=(sent.now_ns - frame.left.t_ns) * 1e-6,
                          latency_command_ms=(sent.t_cmd_ns - frame.left.t_ns) * 1e-6,
                          change_mm=sent.change.translation_norm(), predicted_s=sent.horizon_s,
                          command_mm=sent.cmd.t, guide_error_mm=err, gate_deviation_mm=dev,
                          estimator=None if fit is None else fit.estimator,
                          setpoint_by=self.setpoint_by,
                          change_fre_mm=None if fit is None else fit.rigid_fre_mm,
                          marker_residuals_mm=None if fit is None else fit.residuals_mm,
                          **_steer_fields(steer, est.target_sensor is not None))
        moved = self._patient_moved(frame.left.t_ns)
        if moved is not None:
            ctx.session.write(ev.CORRECTION_OUT_OF_BOUNDS, reason=moved)
            return out.fire(Event.CORRECTION_OUT_OF_BOUNDS, moved + "; operator decision needed")
        if err is not None and err <= ctx.cfg.lock.tolerance_mm and est.gate_problem() is None:
            if not ctx.needle.ok_for_lock(est, frame, self.state):
                s.settle_since_ns = None
                s.sub = CompensateSub.TRACKING
                return out
            if s.settle_since_ns is None:
                s.settle_since_ns = frame.left.t_ns
            s.sub = CompensateSub.SETTLING
            if (frame.left.t_ns - s.settle_since_ns) * 1e-9 >= c.settle_s:
                out.fire(Event.ALIGNED, f"guide within {err:.3f} mm for {c.settle_s} s, gate open")
        else:
            s.settle_since_ns = None
            s.sub = CompensateSub.TRACKING
        return out

    def _patient_moved(self, t_ns: int) -> str | None:
        """The gate's moved-patient watch (:class:`~hil.controller.gate.MovedPatientWatch`) on this
        pair's markers: ALIGNED needs the body back in the registered state, which a shifted
        patient never is, so COMPENSATE says so rather than track until its timeout."""
        if self.s.moved is None:
            return None
        m = self.ctx.est.gate_measures()
        return self.s.moved.update(m.rms_mm, m.markers, m.shape_mm, t_ns)

    def _send(self, inputs: TickInputs, change: RigidTransform,
              flange: Callable[[], None] | None = None) -> _Sent:
        """The slow optical bias correction (seed 001 §2.3), then the setpoint (:meth:`_publish`).
        ``flange``: brings the pair's flange markers in before the bias is measured (None: they
        are in)."""
        ctx, c, est, frame = self.ctx, self.ctx.cfg.compensation, self.ctx.est, inputs.frame
        now = ctx.clock.now_ns()
        st = est.last_state
        if (c.bias_gain > 0 and est.filter.speed_mm_s < c.bias_max_speed_mm_s and st is not None
                and st.tcp_speed_mm_s < c.bias_max_speed_mm_s):
            if flange is not None:
                flange()
            D = est.bias_measurement(frame)
            if D is not None:
                est.T_bias = interpolate_pose(est.T_bias, D, c.bias_gain)
        t_send = ctx.clock.now_ns()
        horizon_s, cmd = self._publish(frame, inputs.t_ns, inputs.robot)
        t_cmd = ctx.clock.now_ns()
        ctx.latency_ms.append((t_cmd - frame.left.t_ns) * 1e-6)
        return _Sent(frame, change, now, t_send, t_cmd, horizon_s, cmd)

    def _publish(self, frame: StereoFrame, now_ns: int, st: RobotState) -> tuple[float, RigidTransform]:
        """Publish the frame's tracking setpoint: the TCP pose that keeps the guide on the plan for
        the filtered patient change at the pair's exposure, and its velocity (the change's, through
        the same frame chain, by a 10 ms difference of the filter's linear extrapolation). The
        servo loop extrapolates it to each command time: horizon = time since the exposure (the
        measured latency) + half a period + the actuation lag, capped at ``max_prediction_s``.
        Returns (the horizon at publication, s; the pose at publication)."""
        ctx, c, est = self.ctx, self.ctx.cfg.compensation, self.ctx.est
        t_exp = frame.left.t_ns
        predict = c.predict_latency and c.max_prediction_s > 0
        if predict:
            lead_s, max_h = 0.5 / ctx.robot.control_rate_hz + c.actuation_lag_s, c.max_prediction_s
        else:
            lead_s, max_h = 0.0, 0.0
        t0 = time.perf_counter_ns()   # the setpoint's cost (hil/controller/cost.py), not control
        sp = predicted_setpoint(est, t_exp, now_ns, lead_s, max_h) if predict else None
        self.s.predicted = sp is not None
        if sp is None:   # alpha-beta: configured, or the predictor's fallback
            sp = est.tracking_setpoint(t_exp, c.max_prediction_s, _VELOCITY_STEP_S if predict else 0.0)
        cp = est.filter.predictor
        setpoint_ns = time.perf_counter_ns() - t0 + (0 if cp is None else cp.update_ns)
        ctx.setpoint_cost.add_ns(setpoint_ns)
        fit_t_ns, fit_ns = est.change_fit_cost
        if fit_t_ns == t_exp:   # this pair's change estimate (not an earlier pair's, held)
            ctx.pair_model_cost.add_ns(fit_ns + setpoint_ns)
        D0, v, w = sp
        timing = ctx.servo_timing()
        valid_until = t_exp + round(timing.camera_max_age_s * 1e9)
        ctx.execute(Track(D0, v, w, t_ref_ns=t_exp, valid_until_ns=valid_until, exposure_t_ns=t_exp,
                          frame_seq=frame.left.seq, speed_scale=self._ramp_scale(),
                          max_horizon_s=max_h, lead_s=lead_s, robot_state=st))
        self.s.last_cmd_ns = ctx.clock.now_ns()
        h = min(max((now_ns - t_exp) * 1e-9 + lead_s, 0.0), max_h)
        return h, RigidTransform(D0.R, D0.t + v * h)

    def _ramp_scale(self) -> float:
        """Speed scale of the servo stream: ramps from ``initial_speed_fraction`` to 1 over
        ``ramp_s`` after the last resume / recovery (1 when there was none)."""
        resumed_ns = self.ctx.est.resumed_ns
        if resumed_ns is None:
            return 1.0
        r = self.ctx.cfg.resume
        f0 = r.initial_speed_fraction
        since_s = (self.ctx.clock.now_ns() - resumed_ns) * 1e-9
        return min(1.0, f0 + (1.0 - f0) * since_s / r.ramp_s)


def _steer_fields(steer: TargetSteer | None, sensed: bool) -> dict[str, float | str]:
    """``compensation_step``'s surrogate target model fields (none without the model): the
    breathing score, the modelled target's shift, the turn added, why a pair kept the rigid
    direction ("" when the model steered) and which bound held the score or the turn ("" when none
    did); with a target sensor (``sensed``), what the path pointed at (``target_source``: "model",
    "sensor" or "") and why the sensor gave no target for the pair (``target_sensor_why_not``, ""
    when it did)."""
    if steer is None:
        return {}
    sensor = {"target_source": steer.source, "target_sensor_why_not": steer.sensor_why_not} if sensed else {}
    return {"target_score_mm": steer.score_mm, "target_shift_mm": steer.target_shift_mm,
            "target_turn_deg": steer.turn_deg, "target_fallback": steer.fallback,
            "target_limited": steer.limited, **sensor}
