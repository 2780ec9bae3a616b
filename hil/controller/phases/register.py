"""REGISTER: wait for a still breath-hold with the skin markers visible, average frames, register
the patient (image -> optical, seed 000) and the robot (optical -> robot, from the flange markers
at the poses the robot reports, or by single-slice stereotaxy, seed 004)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np

from hil.controller import events as ev
from hil.controller.entry_pattern import EntryPattern
from hil.controller.estimate import Estimate, FloatArray, count_seen
from hil.controller.fsm import Event, State
from hil.controller.phases.base import Phase, PhaseContext, PhaseResult
from hil.controller.registration import (
    RegistrationFailedError,
    register_patient,
    register_robot,
    register_robot_via_stereotaxy,
)
from hil.controller.registration_breathing import at_breathing_state
from hil.controller.target_model import SurrogateTargetModel
from hil.geometry.transform import RigidTransform

if TYPE_CHECKING:
    from hil.controller.inputs import TickInputs


#: Pairs whose marker centroid is kept for the stillness test.
CENTROIDS_KEPT = 64


class RegisterSub(Enum):
    WAIT_STILL = "wait_still"      # markers missing or moving
    AVERAGING = "averaging"        # still: frames are being averaged


@dataclass
class _Scratch:
    #: (exposure time, marker centroid) of the latest pairs
    centroids: deque[tuple[int, FloatArray]] = field(default_factory=lambda: deque(maxlen=CENTROIDS_KEPT))
    frames: list[FloatArray] = field(default_factory=list)
    flange: list[FloatArray] = field(default_factory=list)
    poses: list[RigidTransform] = field(default_factory=list)
    sub: RegisterSub = RegisterSub.WAIT_STILL


class RegisterPhase(Phase):
    state = State.REGISTER

    def __init__(self, ctx: PhaseContext) -> None:
        super().__init__(ctx)
        self.s = _Scratch()

    @property
    def sub_state(self) -> RegisterSub:
        return self.s.sub

    def on_enter(self, transition: str) -> PhaseResult:
        self.s = _Scratch()
        self.ctx.est.restart_registration()
        self.request_hold("registration", self.ctx.cfg.registration.hold_request_s)
        return PhaseResult()

    def step(self, inputs: TickInputs) -> PhaseResult:
        ctx, s, reg_cfg = self.ctx, self.s, self.ctx.cfg.registration
        est = ctx.est
        out = PhaseResult()
        if self.elapsed_s() > reg_cfg.timeout_s:
            return out.fire(Event.TIMED_OUT, f"no still breath-hold with visible markers within "
                                             f"{reg_cfg.timeout_s} s")
        live = est.live_mm
        t = inputs.frame.left.t_ns
        if live is None or count_seen(live) < reg_cfg.min_markers:
            s.centroids.clear()
            s.frames.clear()
            s.sub = RegisterSub.WAIT_STILL
            return out
        c = np.nanmean(live, axis=0)
        s.centroids.append((t, c))
        window = [p for (tt, p) in s.centroids if (t - tt) * 1e-9 <= reg_cfg.still_window_s]
        span = (t - s.centroids[0][0]) * 1e-9
        still = span >= reg_cfg.still_window_s and float(np.max(np.linalg.norm(
            np.array(window) - np.mean(window, axis=0), axis=1))) < reg_cfg.still_mm
        if not still:
            s.frames.clear()
            s.flange.clear()
            s.poses.clear()
            s.sub = RegisterSub.WAIT_STILL
            return out
        s.sub = RegisterSub.AVERAGING
        s.frames.append(live.copy())
        pose = est.robot_pose_at(t)
        if est.flange_mm is not None and pose is not None:
            s.flange.append(est.flange_mm.copy())
            s.poses.append(pose)
        if len(s.frames) < reg_cfg.frames_averaged:
            return out
        try:
            preg = register_patient(s.frames, est.plan, reg_cfg)
            st_cfg = reg_cfg.stereotaxy
            if reg_cfg.robot_method == "stereotaxy" and st_cfg is not None:
                rreg = register_robot_via_stereotaxy(st_cfg, preg.T_optical_from_image)
            else:
                rreg = register_robot(s.flange, s.poses, est.rig.flange_markers_tcp_mm)
        except RegistrationFailedError as exc:
            ctx.session.write(ev.REGISTRATION_FAILED, reason=exc.reason)
            return out.fire(Event.REGISTRATION_FAILED, exc.reason)
        residuals_mm = np.linalg.norm(preg.T_optical_from_image.apply(est.plan.fiducials_mm)
                                      - preg.reference_optical_mm, axis=1)     # Horn's fit's
        preg = at_breathing_state(preg, est.plan, est.entry_pattern, est.target_model,
                                  _breathing_residual_bound_mm(est))
        est.accept_registration(preg, rreg)
        ctx.roles.record_reference(est)
        ctx.session.write(ev.REGISTRATION_DONE, fre_mm=preg.fre_rms_mm, tre_expected_mm=preg.tre_expected_mm,
                          markers=preg.markers_used, frames=preg.frames,
                          T_optical_from_image=preg.T_optical_from_image,
                          robot_fre_mm=rreg.fre_rms_mm, T_robot_from_optical=rreg.T_robot_from_optical,
                          robot_method=rreg.method, robot_residual_mm=rreg.fre_rms_mm,
                          reference_optical_mm=preg.reference_optical_mm, residuals_mm=residuals_mm,
                          **_target_model_fields(est.target_model), **_entry_model_fields(est.entry_pattern),
                          **({} if preg.breathing is None else {"breathing": preg.breathing.record()}))
        return out.fire(Event.REGISTERED,
                        f"FRE {preg.fre_rms_mm:.3f} mm, expected TRE {preg.tre_expected_mm:.3f} mm")


def _breathing_residual_bound_mm(est: Estimate) -> float:
    """The bound of the breathing solve at registration: the breathing model's own (the ``pattern``
    estimator's, else the target model's)."""
    c = est.comp_cfg
    return c.pattern_residual_mm if est.entry_pattern is not None else c.target_model_residual_mm


def _entry_model_fields(model: EntryPattern | None) -> dict[str, object]:
    """``registration_done``'s account of the ``pattern`` estimator's model (none without one): its
    breathing patterns, the share of the fiducials' motion they hold, the entry's fit residual over
    the 4D CT's phases and the ridge chosen on the second pattern (hil/controller/entry_pattern.py)."""
    if model is None:
        return {}
    return {"entry_model": {"patterns": int(model.patterns.shape[2]), "explained": model.explained,
                            "fit_residual_mm": model.fit_residual_mm, "ridge_mm2": model.ridge_mm2}}


def _target_model_fields(model: SurrogateTargetModel | None) -> dict[str, object]:
    """``registration_done``'s account of the surrogate target model the controller will steer by
    (none without one): how well it fits the 4D CT, the share of the skin's motion its pattern
    explains, the score range it was fitted over and the target's mm per mm of score (image frame)."""
    if model is None:
        return {}
    return {"target_model": {"fit_residual_mm": model.fit_residual_mm, "explained": model.explained,
                             "score_range_mm": [model.score_min_mm, model.score_max_mm],
                             "target_per_score": model.target_per_score}}
