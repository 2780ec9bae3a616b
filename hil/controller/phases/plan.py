"""PLAN: map the planned entry and target into the robot frame through both registrations and
plan the guide pose above the entry (reachability, joint limits, stand-off)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from hil.controller import events as ev
from hil.controller.fsm import Event, State
from hil.controller.phases.base import Phase, PhaseResult
from hil.controller.planning import PlanRefusedError, plan_guide

if TYPE_CHECKING:
    from hil.controller.inputs import TickInputs


class PlanPhase(Phase):
    state = State.PLAN

    def step(self, inputs: TickInputs) -> PhaseResult:
        ctx, est = self.ctx, self.ctx.est
        out = PhaseResult()
        if ctx.pending() is not None:
            return out  # planned already; waiting for the operator
        assert est.patient_reg is not None
        assert est.robot_reg is not None
        T_robot_from_image = est.robot_reg.T_robot_from_optical @ est.patient_reg.T_optical_from_image
        entry = T_robot_from_image.apply(est.plan.entry_mm).reshape(3)
        target = T_robot_from_image.apply(est.plan.target_mm).reshape(3)
        st = est.last_state
        x_hint = None if st is None else (st.T_robot_from_tcp @ est.rig.T_tcp_from_guide).R[:, 0]
        try:
            gp = plan_guide(entry, target, est.rig, ctx.cfg.planning, ctx.safety.limits,
                            q_near=None if st is None else st.q_rad, x_hint=x_hint)
        except PlanRefusedError as exc:
            ctx.session.write(ev.PLAN_REFUSED, reason=exc.reason, entry_robot_mm=entry,
                              target_robot_mm=target)
            return out.fire(Event.PLAN_REFUSED, exc.reason)
        est.guide_plan = gp
        ctx.session.write(ev.PLAN_ACCEPTED, entry_robot_mm=entry, target_robot_mm=target,
                          T_robot_from_tcp=gp.T_robot_from_tcp, q_rad=gp.q_rad, standoff_mm=gp.standoff_mm)
        return out.fire(Event.PLAN_ACCEPTED, "reachable")
