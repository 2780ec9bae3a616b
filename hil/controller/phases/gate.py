"""GATE: hold position and wait for the hold-breath gate to open (the live skin markers back
within tolerance of the reference for the dwell time, seed 002).

A patient who moved beyond the correction bounds (``[procedure.compensation] max_correction_mm`` /
``max_correction_deg``, the rigid change of the skin markers about the planned entry) will not
bring the markers back by holding the breath: GATE pauses for an operator decision (re-register,
or resume), as COMPENSATE and LOCK do, instead of asking for breath-holds until it times out."""

from __future__ import annotations

from typing import TYPE_CHECKING

from hil.controller import events as ev
from hil.controller.commands import Stop
from hil.controller.compensation import change_out_of_bounds
from hil.controller.fsm import Event, State
from hil.controller.gate import BreathHoldGate
from hil.controller.phases.base import Phase, PhaseResult

if TYPE_CHECKING:
    from hil.controller.inputs import TickInputs


class GatePhase(Phase):
    state = State.GATE

    def on_enter(self, transition: str) -> PhaseResult:
        est, cfg = self.ctx.est, self.ctx.cfg
        assert est.patient_reg is not None
        if est.gate is None:
            est.gate = BreathHoldGate(cfg.gate, est.patient_reg.reference_optical_mm)
        est.gate.restart(self.entered_ns)
        # the arm holds before the patient is asked to (the log shows stop_sent first); a stop
        # that fails raises here, the entry faults, and no breath-hold is requested
        self.ctx.execute(Stop("gate: hold position while waiting for the breath-hold"))
        self.request_hold("gate", cfg.gate.hold_request_s)
        return PhaseResult()

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
        if status.open:
            return out.fire(Event.GATE_OPENED, status.justification)
        if status.timed_out:
            self.ctx.session.write(ev.GATE_TIMED_OUT, message=status.justification)
            return out.fire(Event.TIMED_OUT, status.justification)
        return out
