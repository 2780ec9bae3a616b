"""APPROACH: move to the stand-off pose above the entry, then check it optically and correct
(the closed-loop bias ``T_bias``, seed 001 §2.3) until the guide is within tolerance.

The move is a straight line the servo loop streams every period (:mod:`hil.servo.trajectory`),
then holds at its target while the optical check runs; with the loop in this process (a
simulated run) the phase steps it until the next pair is due. The optical check averages only
pairs exposed ``settle_s`` after the arm was seen at rest (config ``[procedure.approach]``): a
pair exposed earlier may show the arm still moving or ringing, and averaging it into ``T_bias``
would correct for motion that is over (on the GigE tier, whose images arrive 0.15-0.4 s after
they were rendered, that made the corrections wander by 1-3 mm).

Entering after a resume or recovery restarts from the pose the robot reports now, at a reduced
speed; after a fault recovery the robot is recovered first."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np

from drivers.interfaces.robot import RobotMode
from hil.controller import events as ev
from hil.controller.commands import MoveLinear
from hil.controller.compensation import interpolate_pose
from hil.controller.estimate import mean_transform
from hil.controller.fsm import Event, State
from hil.controller.phases.base import Phase, PhaseContext, PhaseResult
from hil.controller.phases.streaming import judge_then_stream
from hil.geometry.transform import RigidTransform

if TYPE_CHECKING:
    from hil.controller.inputs import TickInputs


class ApproachSub(Enum):
    MOVING = "moving"          # the linear move is under way
    MEASURING = "measuring"    # arrived: averaging the optical check


@dataclass
class _Scratch:
    target: RigidTransform | None = None
    sub: ApproachSub = ApproachSub.MOVING
    biases: list[RigidTransform] = field(default_factory=list)
    corrections: int = 0
    rest_ns: int = 0           # controller clock when the arm was seen at rest at the target
    first_exposure_ns: int = 0  # exposure of the first pair of the optical check


class ApproachPhase(Phase):
    state = State.APPROACH

    def __init__(self, ctx: PhaseContext) -> None:
        super().__init__(ctx)
        self.s = _Scratch()

    @property
    def sub_state(self) -> ApproachSub:
        return self.s.sub

    def on_enter(self, transition: str) -> PhaseResult:
        self.s = _Scratch()
        if transition == "recover":
            self.ctx.robot.recover()  # a DriverError here faults the entry
        return PhaseResult().command(self._move(self.resumed))

    def _move(self, resumed: bool) -> MoveLinear:
        est, a = self.ctx.est, self.ctx.cfg.approach
        assert est.guide_plan is not None
        target = est.T_bias @ est.guide_plan.T_robot_from_tcp
        self.s.target = target
        self.s.sub = ApproachSub.MOVING
        f = self.ctx.cfg.resume.initial_speed_fraction if resumed else 1.0
        return MoveLinear(target, a.speed_mm_s * f if resumed else a.speed_mm_s, a.accel_mm_s2 * f)

    def step(self, inputs: TickInputs) -> PhaseResult:
        return judge_then_stream(self.ctx, inputs, lambda: self._judge(inputs))

    def _judge(self, inputs: TickInputs) -> PhaseResult:
        ctx, s, a, est = self.ctx, self.s, self.ctx.cfg.approach, self.ctx.est
        out = PhaseResult()
        st = est.last_state
        assert st is not None
        assert s.target is not None
        assert est.guide_plan is not None
        if self.elapsed_s() > a.timeout_s:
            return out.fire(Event.TIMED_OUT, f"stand-off not reached within {a.timeout_s} s")
        if s.sub is ApproachSub.MOVING:
            arrived = (ctx.safety.move_profile_done() and st.mode is not RobotMode.MOVING
                       and st.tcp_speed_mm_s < a.arrived_speed_mm_s
                       and float(np.linalg.norm(st.T_robot_from_tcp.t - s.target.t)) < a.arrived_mm)
            if arrived:
                s.sub = ApproachSub.MEASURING
                s.rest_ns = inputs.t_ns
                s.biases.clear()
            return out
        if inputs.frame.left.t_ns < s.rest_ns + round(a.settle_s * 1e9):
            return out  # exposed before the arm settled (its images may still show it moving)
        D = est.bias_measurement(inputs.frame)
        if D is not None:
            if not s.biases:
                s.first_exposure_ns = inputs.frame.left.t_ns
            s.biases.append(D)
        if len(s.biases) < a.measure_frames:
            return out
        D_mean = mean_transform(s.biases)
        # error of the guide as the camera sees it, in the robot frame
        commanded = est.T_bias @ est.guide_plan.T_robot_from_tcp
        err = D_mean.inverse() @ commanded @ est.rig.T_tcp_from_guide
        want = est.guide_plan.T_robot_from_tcp @ est.rig.T_tcp_from_guide
        e_mm = float(np.linalg.norm(err.t - want.t))
        ctx.session.write(ev.APPROACH_MEASURED, guide_error_mm=e_mm, correction=s.corrections, T_bias=D_mean,
                          rest_ns=s.rest_ns, first_exposure_ns=s.first_exposure_ns, pairs=len(s.biases))
        if e_mm <= a.tolerance_mm:
            return out.fire(Event.STANDOFF_REACHED,
                            f"guide within {e_mm:.3f} mm of the stand-off pose (optical)")
        if s.corrections >= a.max_corrections:
            return out.fire(Event.APPROACH_FAILED,
                            f"guide still {e_mm:.3f} mm off after {s.corrections} optical corrections")
        s.corrections += 1
        est.T_bias = interpolate_pose(est.T_bias, D_mean, a.correction_gain)
        return out.command(self._move(False))
