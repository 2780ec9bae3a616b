"""What observers see: a frozen :class:`ControllerSnapshot`, built by the controller thread after
each tick (bounded work: a few small array copies) and never changed afterwards.

Observers — the console, the OpenIGTLink stream, runtime plugins (``hil_on_tick``,
``hil_on_transition``) — read snapshots or the session log, never the controller: they cannot
see half-updated state and cannot command a device. Units: mm, seconds; frames in the names.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.robot import RobotState
from drivers.interfaces.tracker import TrackerSample
from hil.controller.estimate import Estimate
from hil.controller.located import LocatedMarkers
from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]


def frozen_array(a: FloatArray | None) -> FloatArray | None:
    if a is None:
        return None
    out = np.array(a, dtype=np.float64, copy=True)
    out.setflags(write=False)
    return out


def frozen_transform(T: RigidTransform | None) -> RigidTransform | None:
    if T is None:
        return None
    R, t = np.array(T.R, copy=True), np.array(T.t, copy=True)
    R.setflags(write=False)
    t.setflags(write=False)
    return RigidTransform(R, t)


@dataclass(frozen=True)
class TimelineRow:
    """One applied transition: when (s since start), the state entered, why."""

    t_s: float
    state: str
    reason: str


@dataclass(frozen=True)
class ControllerSnapshot:
    """The controller after one tick (module doc). Arrays are read-only copies."""

    t_ns: int
    t_s: float
    state: str
    sub_state: str | None
    pending: str | None
    pending_reason: str
    last_reason: str
    started: bool
    timeline: tuple[TimelineRow, ...]
    # registration
    fre_mm: float | None
    tre_expected_mm: float | None
    robot_fre_mm: float | None
    T_optical_from_image: RigidTransform | None
    T_robot_from_optical: RigidTransform | None
    T_bias: RigidTransform
    T_change_meas: RigidTransform | None
    #: the guide in the CT frame, where the controller believes it is (see :func:`guide_in_image`)
    T_image_from_guide: RigidTransform | None
    # markers, optical frame (NaN rows: not seen)
    reference_optical_mm: FloatArray | None
    live_mm: FloatArray | None
    flange_mm: FloatArray | None
    gate_deviation_mm: float | None
    guide_error_mm: float | None
    # devices
    robot: RobotState | None
    tracker: dict[str, TrackerSample] = field(default_factory=dict)
    # counts
    faults: tuple[str, ...] = ()
    frames: int = 0
    commands_sent: int = 0
    commands_refused: int = 0
    operator_commands_decided: int = 0
    #: the simulator's truth: the guide error the truth meter (an observer of these snapshots)
    #: measured on the previous snapshot in COMPENSATE or LOCK (None on a rig)
    truth_error_mm: float | None = None
    #: the arm as read when this snapshot was built (at ``t_ns``; ``robot`` is the tick's input)
    robot_now: RobotState | None = None
    #: the plan's stand-off of the guide from the entry, mm (None before a plan)
    standoff_mm: float | None = None
    #: the markers located in the latest pair, before identification: the ring centres per camera
    #: (``left_px``, ``right_px``; image px) and triangulated (``points_mm``; optical frame), with
    #: the pair's ``frame_seq``; None before the first pair or when locating it failed
    located: LocatedMarkers | None = None
    #: the deformation monitor: the estimator that produced the change (``[procedure.compensation]
    #: estimator``, or its fallback), the skin markers' rigid-fit residual (mm) and each marker's
    #: residual (mm, reference order, NaN: not seen); None before a change was measured
    change_estimator: str | None = None
    change_fre_mm: float | None = None
    marker_residuals_mm: FloatArray | None = None
    #: per-marker distance from the registered reference state (mm, NaN: not seen), the shape
    #: residual (the reference's rigid fit onto the live markers, mm) and whether every check of
    #: ``[procedure.gate]`` passes now (the gate without its dwell); None before registration
    marker_deviations_mm: FloatArray | None = None
    gate_shape_mm: float | None = None
    gate_ok: bool | None = None
    #: the loop's predictor (``[procedure.compensation] predictor``; docs/prediction.md "In the
    #: loop"), whether it answers now (False: warming up or holding after a fallback, alpha-beta
    #: sets the setpoint; None for alpha-beta itself), its fallbacks since the start and the last
    #: one's reason (None: none yet)
    predictor: str = "alpha-beta"
    predictor_active: bool | None = None
    predictor_fallbacks: int = 0
    predictor_fallback_reason: str | None = None
    #: the path's direction (``[procedure.compensation] target_model``; docs/compensation.md "The
    #: direction"): with the surrogate model, the last pair's modelled target shift (mm), the turn
    #: it added (deg), why that pair kept the rigid direction ("" when it steered) and which bound
    #: held its score or turn ("" when none did); None without the model or before a change was
    #: measured
    target_model: str = "rigid"
    target_shift_mm: float | None = None
    target_turn_deg: float | None = None
    target_fallback: str | None = None
    target_limited: str | None = None
    #: with a target sensor (``[procedure.tracking] target_sensor``): what the last pair's path
    #: pointed at ("sensor", "model" or "" for the rigid direction) and why the sensor gave no
    #: target for it ("" when it did); None without a target sensor or before a change was measured
    target_source: str | None = None
    target_sensor_why_not: str | None = None
    #: the path the controller follows for the last measured change: the planned entry and target
    #: (rows, optical frame, mm) moved by the change (the estimator's, steered by the target model
    #: when there is one), and when what it was measured on was taken (``Estimate.change_t_ns``,
    #: controller clock); None before a change was measured. What the arm is sent toward, before
    #: the filter, the prediction over the latency and the servo loop.
    path_optical_mm: FloatArray | None = None
    path_t_ns: int | None = None
    #: the breathing state at registration (docs/compensation.md "The breathing state at
    #: registration"): how far it moved the plan's entry and target from Horn's fit (mm), or why
    #: Horn's was kept ("" when it was not); None without a 4D CT's breathing model
    breathing_entry_shift_mm: float | None = None
    breathing_target_shift_mm: float | None = None
    breathing_kept_rigid_because: str | None = None


def guide_in_image(est: Estimate) -> RigidTransform | None:
    """``T_image_from_guide``: the needle guide in the CT frame from the registrations, the
    closed-loop bias, the live rigid change and the robot state (seed 000 eq 12 and §3):
    ``T_optical_from_image^-1 @ T_change^-1 @ T_robot_from_optical^-1 @ T_bias^-1 @
    T_robot_from_tcp @ T_tcp_from_guide``; None before both registrations and a robot state."""
    preg, rreg, st = est.patient_reg, est.robot_reg, est.last_state
    if preg is None or rreg is None or st is None:
        return None
    T_change = est.T_change_meas if est.T_change_meas is not None else RigidTransform.identity()
    T_optical_from_tcp = rreg.T_robot_from_optical.inverse() @ est.T_bias.inverse() @ st.T_robot_from_tcp
    return (preg.T_optical_from_image.inverse() @ T_change.inverse() @ T_optical_from_tcp
            @ est.rig.T_tcp_from_guide)
