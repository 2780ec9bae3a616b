"""Procedure configuration: every tolerance, limit and policy the controller follows.

The devices engineer's ``SetupConfig`` embeds :class:`ProcedureConfig` as its ``[procedure]``
table. All models are pydantic v2, ``extra="forbid"``, frozen; field names carry units.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationInfo, model_validator

#: infinities and NaN are refused everywhere (``max_duration_s = inf`` would never end a run)
_STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _resolve_path(value: Path, info: ValidationInfo) -> Path:
    """As :data:`hil.config.types.ConfigPath` (not importable here: hil.config imports this module):
    relative paths are resolved against the validation context's ``config_dir``."""
    value = value.expanduser()
    ctx: Any = info.context
    if not value.is_absolute() and isinstance(ctx, dict) and ctx.get("config_dir") is not None:
        value = Path(ctx["config_dir"]) / value
    return value


_ConfigPath = Annotated[Path, AfterValidator(_resolve_path)]
#: x, y, z (mm), rx, ry, rz (rotation vector, rad): the robot pose form of `hil stereotaxy --robot-tcp-pose`
_Pose6 = tuple[float, float, float, float, float, float]


class StereotaxyRegistrationConfig(BaseModel):
    """``[procedure.registration.stereotaxy]``: image -> robot through a rod frame the robot held in
    the scanner (seed 004 §IV, the CT-Bot route; :func:`hil.geometry.stereotaxy.robot_from_image_via_frame`).

    Files as for ``hil stereotaxy`` (docs/pose004.md); relative paths are resolved against the setup
    file's directory. The image (plan) frame is the scanner frame of that slice.
    """

    model_config = _STRICT

    spots: _ConfigPath = Field(description="the slice's spots (hil.ct_slice_spots JSON or rod,u_px,v_px CSV)")
    frame: _ConfigPath = Field(description="the rod frame (hil.stereotactic_frame JSON)")
    pixel_mm: tuple[float, float] | None = Field(
        None, description="slice pixel size (mm); default: the spots file's, else estimated")
    refine: bool = Field(True, description="add the Levenberg-Marquardt refinement")
    robot_tcp_at_scan: _Pose6 = Field(
        description="T_robot_from_tcp while the slice was taken: x, y, z mm, rotation vector rad")
    tcp_from_frame: _Pose6 = Field(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0), description="the frame's mounting on the tool (T_tcp_from_frame)")
    max_residual_mm: float = Field(1.0, gt=0, description="refuse a slice fit with a larger RMS residual")


class RegistrationConfig(BaseModel):
    """REGISTER: image->optical from the skin markers, robot->optical from the flange markers (or,
    with ``robot_method = "stereotaxy"``, robot->image from a single CT slice of a rod frame the robot
    carries, and robot->optical composed with the skin-marker registration)."""

    model_config = _STRICT

    frames_averaged: int = Field(10, ge=1, le=1000, description="stereo frames averaged per marker set")
    fre_max_mm: float = Field(1.0, gt=0, description="refuse a registration with a larger FRE (RMS)")
    fle_rms_mm: float = Field(0.3, gt=0, description="fiducial localisation error used for expected TRE")
    tre_max_mm: float = Field(3.0, gt=0, description="refuse when the expected TRE at the target is larger")
    match_tolerance_mm: float = Field(3.0, gt=0, description="marker identification tolerance")
    min_markers: int = Field(4, ge=3, description="fewest identified skin markers accepted")
    hold_request_s: float = Field(3.0, gt=0, description="breath-hold asked for while registering")
    timeout_s: float = Field(30.0, gt=0, description="give up without a still, visible marker set")
    still_window_s: float = Field(0.3, gt=0, le=5.0, description="the marker centroid must stay still "
                                  "this long before frames are averaged")
    still_mm: float = Field(0.25, gt=0, description="largest centroid excursion (mm) over the window "
                            "that still counts as still")
    robot_method: Literal["flange_markers", "stereotaxy"] = Field(
        "flange_markers", description="how the robot is registered (stereotaxy: needs [..stereotaxy])")
    stereotaxy: StereotaxyRegistrationConfig | None = Field(
        None, description="single-slice stereotaxy route: spots, frame, TCP pose (docs/pose004.md §8)")

    @model_validator(mode="after")
    def _robot_route(self) -> RegistrationConfig:
        if self.robot_method == "stereotaxy" and self.stereotaxy is None:
            raise ValueError("robot_method = 'stereotaxy' needs a [procedure.registration.stereotaxy] table")
        return self


class PlanningConfig(BaseModel):
    """PLAN: the guide pose on the path, stand-off above the entry, reachability."""

    model_config = _STRICT

    standoff_mm: float = Field(30.0, ge=0, le=200, description="guide tip distance above the entry")
    robot_model: Literal["ur3", "ur3e"] = "ur3"
    joint_margin_rad: float = Field(0.05, ge=0, description="keep this far from every joint limit")
    check_kinematics: bool = Field(True, description="require an inverse-kinematics solution")


class ApproachConfig(BaseModel):
    """APPROACH: move to the stand-off pose, then optical closed-loop correction (seed 001 2.3)."""

    model_config = _STRICT

    speed_mm_s: float = Field(50.0, gt=0)
    accel_mm_s2: float = Field(200.0, gt=0)
    tolerance_mm: float = Field(0.3, gt=0, description="optical guide error accepted after correction")
    max_corrections: int = Field(5, ge=0, description="closed-loop correction moves before giving up")
    correction_gain: float = Field(1.0, gt=0, le=1.0)
    timeout_s: float = Field(60.0, gt=0)
    arrived_mm: float = Field(0.5, gt=0, description="the robot-reported TCP within this of the move's "
                              "target counts as arrived (then the optical check starts)")
    arrived_speed_mm_s: float = Field(0.5, gt=0, description="and slower than this (mm/s)")
    measure_frames: int = Field(5, ge=1, le=100, description="pairs averaged for each optical check of "
                                "the stand-off pose")
    settle_s: float = Field(0.5, ge=0, le=5, description="the optical check uses only pairs exposed at "
                            "least this long after the arm came to rest (s): its vibration dies out, "
                            "and pairs already on their way, whose images still show it moving, are "
                            "left out")


class GateConfig(BaseModel):
    """GATE: hold-breath gate (seed 003 section 3, clinical step 4)."""

    model_config = _STRICT

    tolerance_mm: float = Field(1.5, gt=0, description="RMS deviation of live markers from the reference")
    marker_tolerance_mm: float | None = Field(
        None, gt=0, description="and no marker farther than this from its reference (None: 2 x tolerance_mm)")
    shape_tolerance_mm: float | None = Field(
        1.0, gt=0, description="and the shape back: the rigid-fit residual of the live markers against the "
                               "reference at most this (None: not checked)")
    dwell_s: float = Field(1.0, ge=0, description="the deviation must stay under tolerance this long "
                                                  "(longer than the natural end-exhale pause)")
    timeout_s: float = Field(30.0, gt=0, description="give up waiting (back to waiting, with a message)")
    hold_request_s: float = Field(8.0, gt=0, description="breath-hold asked for on entering the gate")
    min_hold_left_s: float | None = Field(
        4.0, ge=0, description="open only while the requested breath-hold has at least this long left "
                               "(compensate's alignment and lock.hold_s must fit in it; None: not checked)")
    moved_after_s: float | None = Field(
        15.0, gt=0, description="pause for re-registration when the markers have stayed farther than "
                                "tolerance_mm from the registered state this long with their shape back: "
                                "the patient moved on the table (None: not judged)")
    hold_rest_s: float = Field(
        5.0, ge=0, description="after a breath-hold that could not be used ends, let the patient breathe "
                               "this long, then ask for the next")

    @model_validator(mode="after")
    def _hold_budget_fits(self) -> GateConfig:
        if self.min_hold_left_s is not None and self.min_hold_left_s >= self.hold_request_s:
            raise ValueError(f"min_hold_left_s ({self.min_hold_left_s} s) must be shorter than "
                             f"hold_request_s ({self.hold_request_s} s): the gate could never open "
                             "(None turns the budget off)")
        return self


class CompensationConfig(BaseModel):
    """COMPENSATE: follow the rigid change reference->live applied to the plan (seed 000 section 3)."""

    model_config = _STRICT

    filter_alpha: float = Field(0.9, gt=0, le=1, description="alpha-beta filter: position gain")
    filter_beta: float = Field(0.7, ge=0, le=2, description="alpha-beta filter: velocity gain")
    predictor: Literal["alpha-beta", "none", "wlms", "ar-ls", "kalman-osc", "fast-lane"] = Field(
        "alpha-beta", description="what predicts the entry point's displacement over the latency "
                                  "(docs/prediction.md): alpha-beta (the filter's straight line, as before "
                                  "issue 42) or a learning predictor of hil/prediction (the rotation stays "
                                  "the alpha-beta filter's; warming up or after a fallback: alpha-beta)")
    predictor_innovation_bound_mm: float = Field(
        2.0, gt=0, le=50, description="a predictor's one-sample forecast error (3-D) beyond this is a "
                                      "fallback: the model restarts, alpha-beta sets the setpoint (mm)")
    predictor_hold_s: float = Field(1.0, ge=0, le=30, description="after an innovation fallback, alpha-beta "
                                                                  "sets the setpoint at least this long (s)")
    predictor_max_departure_mm: float = Field(
        5.0, gt=0, le=50, description="a prediction never departs further than this from the last measured "
                                      "displacement (mm)")
    predictor_max_speed_mm_s: float = Field(
        60.0, gt=0, description="nor further than this speed times the horizon (mm/s)")
    max_speed_mm_s: float = Field(60.0, gt=0, description="rate limit of the commanded correction")
    max_accel_mm_s2: float = Field(400.0, gt=0, description="acceleration limit of the correction")
    max_angular_speed_rad_s: float = Field(0.5, gt=0)
    max_angular_accel_rad_s2: float = Field(
        2.0, gt=0, description="angular acceleration limit of the correction (noise in the measured "
                               "attitude otherwise reaches the arm as bursts at the angular speed limit)")
    rate_limit_pivot: Literal["entry", "tcp"] = Field(
        "entry", description="the point whose translation the rate limits above hold, the rotation being "
                             "about it: entry (stand-off down the guide's axis: the axis stays through the "
                             "entry while a fast turn is clipped) or tcp (as before issue 41); the TCP's own "
                             "speed and acceleration are held to the same limits either way")
    max_correction_mm: float = Field(25.0, gt=0, description="beyond this change: pause, ask the operator")
    max_correction_deg: float = Field(10.0, gt=0)
    predict_latency: bool = Field(True, description="extrapolate the motion over the measured latency")
    max_prediction_s: float = Field(0.15, ge=0, description="never extrapolate further than this")
    actuation_lag_s: float = Field(0.03, ge=0, description="robot servo lag added to the prediction")
    bias_gain: float = Field(0.1, ge=0, le=1, description="closed-loop optical correction gain per frame")
    bias_max_speed_mm_s: float = Field(3.0, gt=0, description="update the optical bias only slower than this")
    settle_s: float = Field(0.3, ge=0, description="error must stay under lock tolerance this long")
    timeout_s: float = Field(60.0, gt=0)
    estimator: Literal["rigid", "weighted", "local-tps", "pattern"] = Field(
        "rigid", description="how the change is estimated from the skin markers (docs/compensation.md): "
                             "rigid (all markers), weighted (markers near the entry), local-tps (the "
                             "entry's own displacement by a thin-plate spline), pattern (the entry's "
                             "displacement by the 4D CT's breathing patterns; needs the entry in the "
                             "plan's phases)")
    weight_sigma_mm: float = Field(
        60.0, gt=0, le=1000, description="weighted / local-tps / pattern: a marker's weight is "
                                         "exp(-(d/sigma)^2), d its distance from the entry")
    pattern_residual_mm: float = Field(
        2.0, gt=0, description="pattern: per-marker RMS residual of the markers from the 4D CT's breathing "
                               "patterns beyond which a pair falls back to local-tps")
    deformation_bound_mm: float = Field(
        4.0, gt=0, description="rigid-fit residual of the skin markers beyond which the body no longer moves "
                               "as the model explains: pause, ask the operator")
    target_model: Literal["rigid", "surrogate"] = Field(
        "rigid", description="the path's direction after motion (docs/compensation.md): rigid (turned with "
                             "the skin about the entry) or surrogate (at the target a 4D CT's correlation "
                             "with the skin predicts; needs the plan's phases)")
    target_model_residual_mm: float = Field(
        2.0, gt=0, description="surrogate: per-marker RMS residual of the breathing pattern beyond which a "
                               "pair keeps the rigid direction")
    target_model_max_turn_deg: float = Field(
        10.0, gt=0, le=45, description="surrogate: the most the model may turn the path; a larger turn is "
                                       "held at it (towards the modelled target, as far as this)")


class NeedleCheckConfig(BaseModel):
    """``[procedure.lock.needle_check]``: the optical needle-axis check (seed 004 §III, two views).

    The needle resting in the guide is measured from its contour lines in both images and
    compared with the planned path moved by the measured patient motion (optical frame). The
    visible needle is searched between ``visible_from_mm`` and ``visible_to_mm`` before the entry
    point, along the path. Needs a camera that sees the needle (docs/pose004.md).
    """

    model_config = _STRICT

    radius_mm: float = Field(0.6, gt=0, description="needle radius (model check of the two-view fit)")
    visible_from_mm: float = Field(10.0, ge=0, description="visible needle starts this far before the entry")
    visible_to_mm: float = Field(110.0, gt=0, description="visible needle ends this far before the entry")
    max_direction_deg: float = Field(2.0, gt=0, description="largest accepted axis direction error")
    max_offset_mm: float = Field(2.0, gt=0, description="largest accepted axis offset at entry and target")
    required_before_lock: bool = Field(True, description="no LOCK without a passing check")
    alarm_while_locked: bool = Field(True, description="out-of-bounds while locked: alarm + lock.on_drift")
    alarm_window_readings: int = Field(
        3, ge=1, le=50, description="the alarm while locked judges the last this many needle-axis "
                                    "readings: it fires when more than half are out of bounds "
                                    "(1: on a single reading)")
    method: Literal["cylinder", "collinear"] = Field(
        "cylinder", description="cylinder: contour lines (§III); collinear: bead markers on the tube (§II-A)")
    bead_count: int = Field(3, ge=3, le=10, description="collinear: number of beads on the tube")
    bead_spacing_mm: float = Field(30.0, gt=0, description="collinear: distance between neighbouring beads")
    bead_offset_mm: float = Field(20.0, ge=0, description="collinear: first bead's distance from the tip")
    max_mono_stereo_deg: float = Field(
        10.0, gt=0, description="collinear: largest accepted angle between the monocular and stereo axes")

    @model_validator(mode="after")
    def _segment(self) -> NeedleCheckConfig:
        if self.visible_to_mm <= self.visible_from_mm:
            raise ValueError("visible_to_mm must be larger than visible_from_mm")
        return self

    def bead_positions_mm(self) -> tuple[float, ...]:
        """The beads' axis coordinates from the tip towards the hub (mm)."""
        return tuple(self.bead_offset_mm + i * self.bead_spacing_mm for i in range(self.bead_count))


class LockConfig(BaseModel):
    """LOCK: hold at the corrected entry; watch for drift."""

    model_config = _STRICT

    tolerance_mm: float = Field(0.5, gt=0, description="guide error to enter LOCK")
    drift_alarm_mm: float = Field(2.0, gt=0, description="drift while locked that raises the alarm")
    on_drift: Literal["alarm", "retract", "compensate"] = "retract"
    retract_mm: float = Field(40.0, gt=0, description="back-off distance along the guide axis")
    retract_speed_mm_s: float = Field(30.0, gt=0)
    retract_timeout_s: float = Field(30.0, gt=0, description="RETRACT not finished within this: FAULT")
    retract_arrived_mm: float = Field(1.0, gt=0, description="the retract move counts as finished with "
                                      "the robot stopped within this of its target")
    hold_s: float = Field(2.0, ge=0, description="stay locked this long before DONE (0: until operator)")
    needle_check: NeedleCheckConfig | None = Field(
        None, description="optical needle-axis check before LOCK and while locked (None: off)")


class ResumeConfig(BaseModel):
    """Resumption after pause, protective stop, reconnect or fault: from the actual pose, ramped."""

    model_config = _STRICT

    ramp_s: float = Field(1.0, gt=0, description="speed ramps from 0 to full over this time")
    initial_speed_fraction: float = Field(0.1, gt=0, le=1.0)


class VisionConfig(BaseModel):
    """Marker location in the loop (issue 17; docs/benchmarks.md, docs/vision.md): region-of-interest
    tracking of the ring markers between full-frame searches (:mod:`hil.vision.tracking`), with the
    same centres as a full-frame search of the same image (within 0.012 px) at a fraction of its
    cost. On by default; false: a full-frame search on every pair."""

    model_config = _STRICT

    roi_tracking: bool = Field(True, description="search each marker only in a window around its predicted "
                                                 "position; false: a full-frame search on every pair")
    reacquire_every_frames: int = Field(
        30, ge=0, le=100000,
        description="scan the whole image for a new marker every this many pairs (the full-frame search "
        "follows when a candidate is no tracked marker); 0: only when a marker is lost")
    lost_retry_every_frames: int = Field(
        5, ge=1, le=100000, description="while a marker is missing (hidden), its last place is searched "
        "every this many pairs (a full-frame search when reacquire_every_frames is 0)")
    window_margin_px: float = Field(8.0, ge=0.0, le=200.0, description="how far a marker's window reaches "
                                    "beyond its outer ellipse, px")


class TrackingConfig(BaseModel):
    """The magnetic tracker in the procedure (seed 003 clinical step 5; docs/run.md).

    Needs a tracker in the setup and its registration to the camera (``T_optical_from_tracker``:
    ``calibration`` names a ``hil tracker-calibrate`` file; a simulated setup knows its own).
    While LOCKed the tracked needle tip is reported against the planned target (``needle_tracked``
    records); a patient reference sensor stands in for the skin markers when they cannot give
    the patient's rigid change, and is checked against them when both can.
    """

    model_config = _STRICT

    calibration: str | None = Field(None, description="tracker calibration JSON (hil.tracker_calibration), "
                                                       "relative to the setup file")
    needle_sensor: str | None = Field(None, description="the sensor on the needle (None: not tracked)")
    needle_tip_sensor_mm: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="the needle tip in the needle sensor's frame (pivot calibration)")
    needle_axis_sensor: tuple[float, float, float] | None = Field(
        None, description="needle direction towards the tip, sensor frame (None: along the tip offset)")
    reference_sensor: str | None = Field(None, description="the patient reference sensor (None: not used)")
    reference_backup: bool = Field(True, description="use the reference sensor's motion when the skin "
                                                     "markers cannot give the rigid change")
    reference_disagreement_mm: float = Field(
        2.0, gt=0, description="log reference_disagreement when sensor and markers move the entry "
                               "differently by more than this")
    target_sensor: str | None = Field(
        None, description="a sensor at the target (an EM-tracked marker placed at the tumour): while its "
                          "samples are fresh the path points at the target it measures; the surrogate "
                          "target model otherwise (needs [procedure.compensation] target_model = "
                          "\"surrogate\"; docs/compensation.md \"A sensor at the target\"). None: not used")
    target_sensor_offset_mm: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="where the target sensor sits against the target, image (CT) frame, "
                                     "mm: its position in the planning CT less the planned target")
    target_sensor_max_turn_deg: float = Field(
        20.0, gt=0, le=45, description="the most the target sensor's target may turn the path from the "
                                       "rigidly moved plan; a larger turn is held at it (a measured target "
                                       "swings further than the model may extrapolate: breaths twice the "
                                       "CT's turn a liver path by over 10 deg)")
    target_sensor_max_age_ms: float = Field(
        60.0, gt=0, le=1000, description="a pair's target is interpolated between the sensor's two samples "
                                         "around its exposure when they are at most this far apart, else "
                                         "taken from the nearest within this of it, ms; else the pair "
                                         "falls back to the model")


#: Names of the forward transitions that can be made to wait for an operator CONFIRM.
Confirmation = Literal[
    "register_to_plan", "plan_to_approach", "approach_to_gate", "gate_to_compensate",
    "compensate_to_lock", "lock_to_done",
]


class ProcedureConfig(BaseModel):
    """Everything the controller needs beyond the devices.

    ``confirm``: the transitions that wait for an operator CONFIRM (``--auto`` confirms them).
    Watchdog ages and hard motion limits live in the setup's ``[safety]`` table
    (:class:`hil.config.setup.SafetyConfig`), owned with the devices.
    """

    model_config = _STRICT

    registration: RegistrationConfig = RegistrationConfig()
    planning: PlanningConfig = PlanningConfig()
    approach: ApproachConfig = ApproachConfig()
    gate: GateConfig = GateConfig()
    compensation: CompensationConfig = CompensationConfig()
    lock: LockConfig = LockConfig()
    resume: ResumeConfig = ResumeConfig()
    tracking: TrackingConfig = TrackingConfig()
    vision: VisionConfig = VisionConfig()
    confirm: tuple[Confirmation, ...] = ("plan_to_approach", "lock_to_done")
    max_duration_s: float = Field(300.0, gt=0, description="abort the whole procedure after this")
    camera_prefetch: bool = Field(
        True, description="on the wall clock only (real time): grab and locate the next stereo pair in a "
        "background thread so the servo stream continues meanwhile; never with the simulated clock")
    heap_trim_every_s: float = Field(
        10.0, ge=0, le=3600, description="at most this often, s, after a tick or pair, the supervisor "
        "and the perception process collect reference cycles (walking only what the run created: the "
        "objects before it are frozen) and return their free C-heap pages to the system (glibc "
        "malloc_trim; hil/heap.py: a fault's cycles held stereo pairs for minutes, and freed "
        "image-sized buffers stayed resident); 0: never")
    supervisor_period_ms: float | None = Field(
        None, gt=0, le=1000, description="the longest a control tick waits for a stereo pair; when none "
        "arrived by then the tick still reads the robot and the tracker and checks the watchdogs and the "
        "operator (None: 1.25 camera frame periods, so it ticks with every pair while pairs arrive). The "
        "camera fault still comes only after the whole grab timeout. Applies with the prefetcher, the "
        "perception process and the simulated clock")

    @model_validator(mode="after")
    def _consistent(self) -> ProcedureConfig:
        if self.lock.drift_alarm_mm <= self.lock.tolerance_mm:
            raise ValueError("lock.drift_alarm_mm must be larger than lock.tolerance_mm")
        if len(set(self.confirm)) != len(self.confirm):
            raise ValueError("confirm lists a transition twice")
        if self.tracking.target_sensor is not None and self.compensation.target_model != "surrogate":
            raise ValueError("tracking.target_sensor needs compensation.target_model = \"surrogate\" (the "
                             "model the path falls back to when the sensor's samples are missing or late)")
        return self
