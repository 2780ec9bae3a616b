"""LOCK: hold the guide at the corrected entry while the needle goes in; watch for drift (the guide
off the moving entry by more than the alarm distance) and, with the optical check, the needle
axis; finish after the hold time (or on the operator's word).

The arm is held by the servo loop (:class:`~hil.controller.commands.Hold`): it comes to rest
from the tracking command at the acceleration limit and is commanded at that pose every period,
through the loop's step check and following supervision, so a drift or a pushed arm is seen at
the robot's rate. With the loop in this process (a simulated run) the phase steps it between
pairs, as COMPENSATE does."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

from hil.controller import events as ev
from hil.controller.commands import Hold
from hil.controller.compensation import change_out_of_bounds
from hil.controller.fsm import Event, State
from hil.controller.needle import NeedleAlarmWindow
from hil.controller.phases.base import Phase, PhaseContext, PhaseResult
from hil.controller.phases.streaming import judge_then_stream
from hil.log import get_logger

if TYPE_CHECKING:
    from drivers.interfaces.camera import StereoFrame
    from hil.controller.inputs import TickInputs

_log = get_logger(__name__)


class LockSub(Enum):
    HOLDING = "holding"            # within the drift bound
    DRIFT_ALARM = "drift_alarm"    # the drift or needle alarm was raised in this LOCK


@dataclass
class _Scratch:
    alarmed: bool = False
    needle_alarmed: bool = False
    #: the needle alarm's window over this LOCK's readings (lock.needle_check.alarm_window_readings)
    needle_window: NeedleAlarmWindow = field(default_factory=lambda: NeedleAlarmWindow(1))


class LockPhase(Phase):
    state = State.LOCK

    def __init__(self, ctx: PhaseContext) -> None:
        super().__init__(ctx)
        self.s = _Scratch()

    @property
    def sub_state(self) -> LockSub:
        return LockSub.DRIFT_ALARM if (self.s.alarmed or self.s.needle_alarmed) else LockSub.HOLDING

    def on_enter(self, transition: str) -> PhaseResult:
        nc = self.ctx.cfg.lock.needle_check
        self.s = _Scratch(needle_window=NeedleAlarmWindow(1 if nc is None else nc.alarm_window_readings))
        return PhaseResult().command(Hold("lock"))

    def step(self, inputs: TickInputs) -> PhaseResult:
        return judge_then_stream(self.ctx, inputs, lambda: self._judge(inputs))

    def _judge(self, inputs: TickInputs) -> PhaseResult:
        ctx, lk, s, est = self.ctx, self.ctx.cfg.lock, self.s, self.ctx.est
        out = PhaseResult()
        if est.T_change_meas is not None:
            why = change_out_of_bounds(est.local(est.T_change_meas), est.change_fit, ctx.cfg.compensation)
            if why is not None:
                return out.fire(Event.CORRECTION_OUT_OF_BOUNDS, why + "; operator decision needed")
        err = est.guide_error_optical_mm()
        gm = est.gate_measures()
        ctx.session.write(ev.LOCK_MEASURED, guide_error_mm=err, gate_deviation_mm=est.gate_deviation_mm(),
                          shape_mm=gm.shape_mm, marker_deviations_mm=list(gm.deviations_mm))
        ctx.roles.track_needle(est)
        if err is not None and err > lk.drift_alarm_mm:
            if not s.alarmed:
                s.alarmed = True
                ctx.session.write(ev.DRIFT_ALARM, guide_error_mm=err, limit_mm=lk.drift_alarm_mm,
                                  policy=lk.on_drift)
                _log.warning(ev.DRIFT_ALARM, guide_error_mm=err, policy=lk.on_drift)
            if lk.on_drift == "retract":
                return out.fire(Event.DRIFT_DETECTED, f"guide {err:.2f} mm off the moving entry while locked")
            if lk.on_drift == "compensate":
                return out.fire(Event.LOCK_LOST, f"guide {err:.2f} mm off the moving entry while locked")
        if self._needle_alarm(inputs.frame, out):
            return out
        if lk.hold_s > 0 and self.elapsed_s() >= lk.hold_s and ctx.pending() is None:
            out.fire(Event.LOCK_COMPLETED, f"held {lk.hold_s} s")
        return out

    def _needle_alarm(self, frame: StereoFrame, out: PhaseResult) -> bool:
        """Measure the needle axis; when ``alarm_while_locked`` and the alarm window
        (:class:`~hil.controller.needle.NeedleAlarmWindow`: more than half of the last
        ``alarm_window_readings`` readings out of bounds) judges it out, log ``needle_axis_alarm``
        (once per LOCK) and apply ``lock.on_drift``. True when an event was added to ``out``."""
        ctx, lk, s = self.ctx, self.ctx.cfg.lock, self.s
        nc = lk.needle_check
        m = ctx.needle.measure(ctx.est, frame, self.state)
        if nc is None or m is None or not nc.alarm_while_locked:
            return False
        pe = m.path_error
        win = s.needle_window
        if not win.add(not pe.within(nc.max_direction_deg, nc.max_offset_mm)):
            return False
        why = (f"needle axis {pe.direction_error_deg:.2f} deg / entry {pe.entry_offset_mm:.2f} mm / "
               f"target {pe.target_offset_mm:.2f} mm off the plan while locked "
               f"({win.out_of_bounds} of the last {win.readings} readings out of bounds)")
        if not s.needle_alarmed:
            s.needle_alarmed = True
            ctx.session.write(ev.NEEDLE_AXIS_ALARM, reason=why, direction_error_deg=pe.direction_error_deg,
                              entry_offset_mm=pe.entry_offset_mm, target_offset_mm=pe.target_offset_mm,
                              limit_deg=nc.max_direction_deg, limit_mm=nc.max_offset_mm, policy=lk.on_drift,
                              out_of_bounds_readings=win.out_of_bounds, window_readings=win.readings)
            _log.warning(ev.NEEDLE_AXIS_ALARM, direction_error_deg=pe.direction_error_deg, policy=lk.on_drift,
                         out_of_bounds_readings=win.out_of_bounds, window_readings=win.readings)
        if lk.on_drift == "retract":
            out.fire(Event.DRIFT_DETECTED, why)
            return True
        if lk.on_drift == "compensate":
            out.fire(Event.LOCK_LOST, why)
            return True
        return False
