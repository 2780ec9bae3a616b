"""COMPENSATE: follow the patient to the corrected entry. Each pair: the filtered rigid change of
the patient (about the entry point), bounded (beyond the bounds the operator decides), predicted
over the latency, rate-limited, streamed to the arm as servo set-points at the robot's rate until
the next pair is due; a slow optical bias correction (seed 001 §2.3); ALIGNED once the guide is
within the lock tolerance for the settle time with the gate open (and the needle check passed).

The sub-frame servo stream is the one place a phase commands the arm from inside its step (each
set-point must go out on its own deadline); it uses the context's command sink, so it still goes
through the safety layer like every other command.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

from hil.controller import events as ev
from hil.controller.commands import Track
from hil.controller.compensation import RateLimiter, correction_out_of_bounds, interpolate_pose
from hil.controller.deadline import DeadlineTimer
from hil.controller.fsm import Event, State
from hil.controller.phases.base import Phase, PhaseContext, PhaseResult
from hil.geometry.transform import RigidTransform

if TYPE_CHECKING:
    from drivers.interfaces.camera import StereoFrame
    from hil.controller.inputs import TickInputs


class CompensateSub(Enum):
    WAITING = "waiting"        # no measured change yet (markers not seen, filter not started)
    TRACKING = "tracking"      # streaming, guide not yet within tolerance
    SETTLING = "settling"      # within tolerance, waiting out the settle time


@dataclass
class _Scratch:
    last_cmd_ns: int | None = None
    settle_since_ns: int | None = None
    sub: CompensateSub = CompensateSub.WAITING


class CompensatePhase(Phase):
    state = State.COMPENSATE

    def __init__(self, ctx: PhaseContext) -> None:
        super().__init__(ctx)
        comp = ctx.cfg.compensation
        self.limiter = RateLimiter(comp.max_speed_mm_s, comp.max_accel_mm_s2, comp.max_angular_speed_rad_s)
        self.s = _Scratch()

    @property
    def sub_state(self) -> CompensateSub:
        return self.s.sub

    def on_enter(self, transition: str) -> PhaseResult:
        self.s = _Scratch()
        st = self.ctx.robot.state_now()
        self.limiter.reset(st.T_robot_from_tcp)
        self.ctx.safety.forget_stream()
        return PhaseResult()

    def step(self, inputs: TickInputs) -> PhaseResult:
        ctx, s, c, est = self.ctx, self.s, self.ctx.cfg.compensation, self.ctx.est
        frame = inputs.frame
        out = PhaseResult()
        now = ctx.clock.now_ns()
        if self.elapsed_s() > c.timeout_s:
            return out.fire(Event.TIMED_OUT, f"not aligned within {c.timeout_s} s")
        if est.T_change_meas is None or not est.filter.initialised:
            s.sub = CompensateSub.WAITING
            return out  # markers not seen this frame: hold the last command (watchdogs cover staleness)
        t_reg = ctx.clock.now_ns()
        change = est.filter.estimate()  # about the entry point
        why = correction_out_of_bounds(change, c)
        if why is not None:
            ctx.session.write(ev.CORRECTION_OUT_OF_BOUNDS, reason=why, T_change=change)
            return out.fire(Event.CORRECTION_OUT_OF_BOUNDS, why + "; operator decision needed")
        servo_dt = 1.0 / ctx.robot.control_rate_hz if c.servo_at_robot_rate else ctx.frame_period_s
        dt = servo_dt if s.last_cmd_ns is None else \
            min(max((now - s.last_cmd_ns) * 1e-9, servo_dt), 2.0 * ctx.frame_period_s)
        # slow closed-loop correction from the optical measurement of the flange (seed 001 2.3)
        st = est.last_state
        if (c.bias_gain > 0 and est.filter.speed_mm_s < c.bias_max_speed_mm_s and st is not None
                and st.tcp_speed_mm_s < c.bias_max_speed_mm_s):
            D = est.bias_measurement(frame)
            if D is not None:
                est.T_bias = interpolate_pose(est.T_bias, D, c.bias_gain)
        hold_s = servo_dt if c.servo_at_robot_rate else ctx.frame_period_s
        t_send = ctx.clock.now_ns()  # the stream's deadlines count from this command's slot
        horizon_s, cmd = self._servo_once(frame, dt, hold_s)
        t_cmd = ctx.clock.now_ns()
        ctx.latency_ms.append((t_cmd - frame.left.t_ns) * 1e-6)
        if c.servo_at_robot_rate:
            self._stream(frame, now, t_send, servo_dt)
        err = est.guide_error_optical_mm()
        dev = est.gate_deviation_mm()
        ctx.session.write(ev.COMPENSATION_STEP, exposure_t_ns=frame.left.t_ns,
                          latency_detect_ms=(t_reg - frame.left.t_ns) * 1e-6,
                          latency_command_ms=(t_cmd - frame.left.t_ns) * 1e-6,
                          change_mm=change.translation_norm(), predicted_s=horizon_s,
                          command_mm=cmd.t, guide_error_mm=err, gate_deviation_mm=dev)
        if err is not None and err <= ctx.cfg.lock.tolerance_mm and dev <= ctx.cfg.gate.tolerance_mm:
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

    def _stream(self, frame: StereoFrame, now: int, t_send: int, servo_dt: float) -> None:
        """Stream at the robot's rate until the next pair is due, on the predicted motion, on
        absolute deadlines one servo period apart from the pair's command (the work per command
        does not stretch the period; a slot missed by more than a period is skipped)."""
        ctx = self.ctx
        timer = DeadlineTimer(ctx.clock, servo_dt)
        timer.start(t_send)
        half_ns = timer.period_ns // 2
        timing = ctx.servo_timing()
        ready = timing.next_pair_ready
        if ready is None:  # the next grab blocks this thread: stop half a period before it is due
            next_ready_ns = now + round(ctx.frame_period_s * 1e9)

            def more() -> bool:
                return max(timer.next_ns(), ctx.clock.now_ns()) + half_ns <= next_ready_ns
        else:  # real time: stream until the prefetcher has the next pair (or an error) ready;
            # capped, and never on a pair the camera watchdog would call stale, so the tick
            # judges a missing or late pair as it would without the prefetcher
            cap_ns = min(now + round((2 * ctx.frame_period_s + timing.grab_timeout_s) * 1e9),
                         frame.left.t_ns + round(timing.camera_max_age_s * 1e9))

            def more() -> bool:
                return not ready() and max(timer.next_ns(), ctx.clock.now_ns()) <= cap_ns
        while more():
            skipped = timer.wait()
            if skipped:
                ctx.servo_deadlines_missed += 1
                ctx.session.write(ev.SERVO_DEADLINE_MISSED, slots_skipped=skipped, period_s=servo_dt)
            self._servo_once(frame, servo_dt, servo_dt)

    def _servo_once(self, frame: StereoFrame, dt: float, hold_s: float) -> tuple[float, RigidTransform]:
        """One rate-limited servo command on the motion predicted for when it takes effect:
        now + half the time it is held + the robot's actuation lag (capped). Returns (prediction
        horizon after the frame, s; the command)."""
        ctx, c, est = self.ctx, self.ctx.cfg.compensation, self.ctx.est
        now = ctx.clock.now_ns()
        horizon_ns = 0
        if c.predict_latency:
            lead_s = (now - frame.left.t_ns) * 1e-9 + 0.5 * hold_s + c.actuation_lag_s
            horizon_ns = round(min(lead_s, c.max_prediction_s) * 1e9)
        T_pred = est.global_(est.filter.estimate(frame.left.t_ns + horizon_ns, c.max_prediction_s))
        cmd = self.limiter.step(est.desired_tcp_robot(T_pred), dt, self._ramp_scale())
        ctx.execute(Track(cmd, dt))
        self.s.last_cmd_ns = ctx.clock.now_ns()
        return horizon_ns * 1e-9, cmd

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
