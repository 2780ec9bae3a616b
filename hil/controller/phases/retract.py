"""RETRACT: back off along the guide axis from where the robot is now, then finish (a straight
line the servo loop streams; in-process, the phase steps the loop until the next pair)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from drivers.interfaces.robot import RobotMode
from hil.controller.commands import MoveLinear
from hil.controller.fsm import Event, State
from hil.controller.phases.base import Phase, PhaseResult
from hil.controller.phases.streaming import judge_then_stream
from hil.geometry.transform import RigidTransform

if TYPE_CHECKING:
    from hil.controller.inputs import TickInputs


class RetractPhase(Phase):
    state = State.RETRACT
    target: RigidTransform | None = None

    def on_enter(self, transition: str) -> PhaseResult:
        ctx, lk = self.ctx, self.ctx.cfg.lock
        st = ctx.robot.state_now()
        axis = (st.T_robot_from_tcp @ ctx.est.rig.T_tcp_from_guide).R[:, 2]
        self.target = RigidTransform(st.T_robot_from_tcp.R, st.T_robot_from_tcp.t - lk.retract_mm * axis)
        move = MoveLinear(self.target, lk.retract_speed_mm_s, ctx.cfg.approach.accel_mm_s2)
        return PhaseResult().command(move)

    def step(self, inputs: TickInputs) -> PhaseResult:
        return judge_then_stream(self.ctx, inputs, self._judge)

    def _judge(self) -> PhaseResult:
        lk, out = self.ctx.cfg.lock, PhaseResult()
        st = self.ctx.est.last_state
        assert st is not None
        assert self.target is not None
        if self.elapsed_s() > lk.retract_timeout_s:
            return out.fire(Event.TIMED_OUT, f"retract not finished within {lk.retract_timeout_s:g} s")
        left_mm = float(np.linalg.norm(st.T_robot_from_tcp.t - self.target.t))
        if self.ctx.safety.move_profile_done() and st.mode is not RobotMode.MOVING \
                and left_mm < lk.retract_arrived_mm:
            return out.fire(Event.RETRACTED, f"backed off {lk.retract_mm} mm along the guide axis")
        return out
