"""GATE: hold position and wait for the hold-breath gate to open (the live skin markers back
within tolerance of the reference for the dwell time, seed 002).

A patient who moved beyond the correction bounds (``[procedure.compensation] max_correction_mm`` /
``max_correction_deg``, the rigid change of the skin markers about the planned entry) will not
bring the markers back by holding the breath: GATE pauses for an operator decision (re-register,
or resume), as COMPENSATE and LOCK do, instead of asking for breath-holds until it times out.

The hold budget (``[procedure.gate] min_hold_left_s``): the needle goes in during the breath-hold
the gate asked for, so the gate opens only while that hold has at least ``min_hold_left_s`` left
on the controller's clock (counted from the request: the patient's reaction only makes the hold
end later, so this errs on the safe side). A hold that comes too late to use is logged once
(``gate_hold_too_short``); when it has ended and the patient has breathed for ``hold_rest_s``,
the gate asks for the next one (``breath_hold_requested``) and waits again.

A patient who shifted on the table (within the correction bounds) keeps the markers away from the
registered state at every point of the breathing cycle while their shape is back: no breath-hold
will ever open the gate. When the markers' deviation has not come within ``tolerance_mm`` for
``moved_after_s`` (several breaths: a breathing patient passes the reference at every end-exhale,
a held breath lasts ``hold_request_s``) and the shape is back within ``shape_tolerance_mm``, GATE
pauses for the operator (re-register) with that reason, instead of asking for breath-holds."""

from __future__ import annotations

from typing import TYPE_CHECKING

from hil.controller import events as ev
from hil.controller.commands import Stop
from hil.controller.compensation import change_out_of_bounds
from hil.controller.fsm import Event, State
from hil.controller.gate import BreathHoldGate, MovedPatientWatch
from hil.controller.phases.base import Phase, PhaseResult

if TYPE_CHECKING:
    from hil.controller.inputs import TickInputs


class GatePhase(Phase):
    """GATE (module doc). Scratch: the current hold request's end (controller clock, ns) and
    whether its being too short was logged."""

    _hold_end_ns: int = 0
    _too_short_logged: bool = False
    _moved: MovedPatientWatch

    state = State.GATE

    def on_enter(self, transition: str) -> PhaseResult:
        est, cfg = self.ctx.est, self.ctx.cfg
        assert est.patient_reg is not None
        if est.gate is None:
            est.gate = BreathHoldGate(cfg.gate, est.patient_reg.reference_optical_mm)
        est.gate.restart(self.entered_ns)
        self._moved = MovedPatientWatch(cfg.gate)
        self._moved.restart(self.entered_ns)
        # the arm holds before the patient is asked to (the log shows stop_sent first); a stop
        # that fails raises here, the entry faults, and no breath-hold is requested
        self.ctx.execute(Stop("gate: hold position while waiting for the breath-hold"))
        self._ask_for_hold()
        return PhaseResult()

    def _ask_for_hold(self) -> None:
        """Request a breath-hold of ``hold_request_s`` and note when it is due to end."""
        hold_s = self.ctx.cfg.gate.hold_request_s
        self.request_hold("gate", hold_s)
        self._hold_end_ns = self.ctx.clock.now_ns() + round(hold_s * 1e9)
        self._too_short_logged = False

    def _hold_problem(self, gate_open: bool) -> str | None:
        """Why the current hold cannot take the needle (None: it can, or the budget is off); asks
        for the next hold once this one has ended and the rest has passed. With ``gate_open`` (the
        body's checks hold) a hold too short to use is logged, once per hold."""
        g = self.ctx.cfg.gate
        if g.min_hold_left_s is None:
            return None
        now = self.ctx.clock.now_ns()
        left_s = (self._hold_end_ns - now) * 1e-9
        if left_s >= g.min_hold_left_s:
            return None
        if left_s <= -g.hold_rest_s:
            self._ask_for_hold()
            return "asking for the next breath-hold"
        why = (f"the breath-hold has {max(left_s, 0.0):.1f} s left, compensate and lock need "
               f"{g.min_hold_left_s} s: waiting for the next")
        if gate_open and not self._too_short_logged:
            self._too_short_logged = True
            self.ctx.session.write(ev.GATE_HOLD_TOO_SHORT, hold_left_s=left_s, need_s=g.min_hold_left_s,
                                   next_request_in_s=left_s + g.hold_rest_s)
        return why

    def step(self, inputs: TickInputs) -> PhaseResult:
        est, out = self.ctx.est, PhaseResult()
        assert est.gate is not None
        status = est.gate.update(est.live_mm, inputs.frame.left.t_ns)
        self.ctx.session.write(ev.GATE_MEASURED, deviation_rms_mm=status.deviation_rms_mm,
                               markers=status.markers, dwell_s=status.dwell_s, open=status.open,
                               max_marker_mm=status.max_marker_mm, shape_mm=status.shape_mm,
                               marker_deviations_mm=list(status.deviations_mm))
        if est.T_change_meas is not None:
            change = est.local(est.T_change_meas)
            why = change_out_of_bounds(change, est.change_fit, self.ctx.cfg.compensation)
            if why is not None:
                self.ctx.session.write(ev.CORRECTION_OUT_OF_BOUNDS, reason=why, T_change=change)
                return out.fire(Event.CORRECTION_OUT_OF_BOUNDS, why + "; operator decision needed")
        hold_problem = self._hold_problem(status.open)
        if status.open and hold_problem is None:
            return out.fire(Event.GATE_OPENED, status.justification)
        shifted = self._moved.update(status.deviation_rms_mm, status.markers, status.shape_mm,
                                     inputs.frame.left.t_ns)
        if shifted is not None:
            self.ctx.session.write(ev.CORRECTION_OUT_OF_BOUNDS, reason=shifted)
            return out.fire(Event.CORRECTION_OUT_OF_BOUNDS, shifted + "; operator decision needed")
        if status.timed_out:
            self.ctx.session.write(ev.GATE_TIMED_OUT, message=status.justification)
            return out.fire(Event.TIMED_OUT, status.justification)
        return out
