"""The procedure's estimate: the single owner of the mutable state the phases share, and of the
frame-chain maths over it.

What it holds (frames in the names; mm, radians):
- the registrations (image -> optical, optical -> robot) and the planned guide pose;
- the closed-loop bias ``T_bias`` (robot frame, seed 001 §2.3) and the entry-centred frame
  ``T_center`` the motion filter works in;
- the live marker sets (skin: CT fiducial order, flange: layout order; NaN rows = not seen), the
  measured rigid change of the patient and its filter;
- the latest robot states (for interpolation at frame time), stereo pair and tracker samples.

Phases read and update it; observers never see it (they get a
:class:`~hil.controller.snapshot.ControllerSnapshot`). Nothing here blocks or touches a device.
"""

from __future__ import annotations

import itertools
import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.camera import StereoFrame
from drivers.interfaces.robot import RobotState
from drivers.interfaces.tracker import TrackerSample
from hil.controller.change_estimate import ChangeFit
from hil.controller.compensation import ChangePredictor, MotionFilter, interpolate_pose
from hil.controller.config import ProcedureConfig
from hil.controller.entry_pattern import EntryPattern, EntryRows, fit_entry_pattern
from hil.controller.gate import BreathHoldGate, GateMeasures, gate_measures, rms_deviation_mm
from hil.controller.plan_file import ProcedurePlan
from hil.controller.planning import GuidePlan, RigGeometry
from hil.controller.registration import PatientRegistration, RobotRegistration
from hil.controller.target_model import SurrogateTargetModel, TargetSteer, TargetTracker, fit_target_model
from hil.controller.target_sensor import TargetSensor
from hil.errors import ConfigError
from hil.geometry import native
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

FloatArray = NDArray[np.float64]
#: Robot states kept for interpolation at a frame's exposure time.
STATE_HISTORY = 8


def count_seen(markers: FloatArray | None) -> int:
    """Markers with a position (finite rows)."""
    return 0 if markers is None else int(np.isfinite(markers).all(axis=1).sum())


def mean_transform(ts: list[RigidTransform]) -> RigidTransform:
    """Mean of nearby rigid transforms (translation mean; rotation by rotation-vector mean about
    the first)."""
    base = ts[0]
    rv = np.mean([(base.inverse() @ T).as_rotvec() for T in ts], axis=0)
    R = base.R @ RigidTransform.from_rotvec(rv).R
    return RigidTransform(R, np.mean([T.t for T in ts], axis=0))


class Estimate:
    """The procedure state (module doc). ``plan`` and ``rig`` are fixed for the procedure.
    ``camera_rate_hz``: the pair rate the ``[procedure.compensation] predictor`` is set up for
    (needed, Hz, unless the predictor is ``"alpha-beta"``).

    Raises:
        ConfigError: a predictor other than alpha-beta without a camera rate.
        PredictionError: a camera rate that is not a finite number > 0 for it.
        InputFileError: ``target_model = "surrogate"`` with a plan whose 4D CT cannot carry the
            model (hil/controller/target_model.py :func:`fit_target_model`); ``estimator =
            "pattern"`` with one that cannot carry that (hil/controller/entry_pattern.py).
    """

    def __init__(self, plan: ProcedurePlan, rig: RigGeometry, cfg: ProcedureConfig,
                 camera_rate_hz: float | None = None, target_sensor: TargetSensor | None = None) -> None:
        self.plan, self.rig = plan, rig
        self.patient_reg: PatientRegistration | None = None
        self.robot_reg: RobotRegistration | None = None
        self.guide_plan: GuidePlan | None = None
        self.T_bias = RigidTransform.identity()   # robot-frame closed-loop correction (seed 001 2.3)
        # the change is filtered and bounded about the planned entry point (optical frame): its
        # translation is then the entry's displacement, not a lever-arm artefact of the camera origin
        self.T_center = RigidTransform.identity()
        self.gate: BreathHoldGate | None = None
        self.filter = MotionFilter(cfg.compensation.filter_alpha, cfg.compensation.filter_beta)
        if cfg.compensation.predictor != "alpha-beta":
            if camera_rate_hz is None:
                raise ConfigError("[procedure.compensation]", [
                    f"predictor = {cfg.compensation.predictor!r} needs the camera's frame rate"])
            self.filter.predictor = ChangePredictor(cfg.compensation, camera_rate_hz)
        self.comp_cfg, self.gate_cfg = cfg.compensation, cfg.gate
        c = cfg.compensation
        #: the surrogate target model (``target_model = "surrogate"``), fitted to the plan's 4D CT
        self.target_model: SurrogateTargetModel | None = (
            fit_target_model(plan, c.target_model_residual_mm, c.target_model_max_turn_deg)
            if c.target_model == "surrogate" else None)
        #: the ``pattern`` estimator's model (hil/controller/entry_pattern.py), fitted to the plan's
        #: 4D CT, and its rows for the current registration (:meth:`accept_registration`)
        self.entry_pattern: EntryPattern | None = (fit_entry_pattern(plan) if c.estimator == "pattern"
                                                   else None)
        self.entry_rows: EntryRows | None = None
        #: the model in the loop (the score's rate from pair to pair)
        self.target_tracker = None if self.target_model is None else TargetTracker(
            self.target_model, cfg.tracking.target_sensor_max_turn_deg)
        #: the last pair's use of it (None: no model, or no change measured this pair)
        self.target_steer: TargetSteer | None = None
        #: the last pair's change estimate (estimator, rigid-fit residuals: the deformation monitor)
        self.change_fit: ChangeFit | None = None
        #: (the pair's exposure, controller clock ns; the change estimator's and the target
        #: model's time on it, ns: hil/controller/cost.py), for COMPENSATE's per-pair sum
        self.change_fit_cost: tuple[int, int] = (-1, 0)
        self.live_mm: FloatArray | None = None      # skin markers, reference order
        self.flange_mm: FloatArray | None = None    # flange markers, layout order
        self.T_change_meas: RigidTransform | None = None
        #: when what :attr:`T_change_meas` was measured on was taken: the pair's exposure, or the
        #: reference sensor's sample standing in (controller clock, ns; None before a change)
        self.change_t_ns: int | None = None
        self.last_frame: StereoFrame | None = None
        self.last_state: RobotState | None = None
        self.state_history: deque[RobotState] = deque(maxlen=STATE_HISTORY)
        self.tracker_samples: dict[str, TrackerSample] = {}
        #: the sensor at the target (``[procedure.tracking] target_sensor``; None: not used): its
        #: recent samples, fed by :meth:`record_tracker_samples`
        self.target_sensor = target_sensor
        #: when the last resume / recovery re-entered the forward path (the servo speed ramp)
        self.resumed_ns: int | None = None
        #: the flange set :meth:`T_optical_from_tcp_measured` last registered, and its result
        self._tcp_measured: tuple[FloatArray | None, RigidTransform | None] = (None, None)
        #: what :meth:`desired_tcp_robot_local` composed its chain of (T_bias, robot_reg,
        #: guide_plan, T_center), then the chain's L and R
        self._chain: tuple[RigidTransform, RobotRegistration, GuidePlan, RigidTransform,
                           RigidTransform, RigidTransform] | None = None

    # ------------------------------------------------------------------ updates
    def restart_registration(self) -> None:
        """Entering REGISTER: forget the patient registration, live markers, filter and bias."""
        self.patient_reg = None
        self.live_mm = None
        self.change_fit = None
        self.target_steer = None
        if self.target_tracker is not None:
            self.target_tracker.reset()
        self.filter.reset()
        self.T_bias = RigidTransform.identity()

    def accept_registration(self, preg: PatientRegistration, rreg: RobotRegistration) -> None:
        """A new registration: the live set starts at the reference, the gate is rebuilt."""
        self.patient_reg, self.robot_reg = preg, rreg
        self.T_center = RigidTransform.from_translation(preg.T_optical_from_image.apply(self.plan.entry_mm))
        if self.entry_pattern is not None:
            self.entry_rows = self.entry_pattern.registered(
                preg.T_optical_from_image, preg.reference_optical_mm, self.T_center.t,
                self.comp_cfg.pattern_residual_mm)
        self.gate = None
        self.live_mm = preg.reference_optical_mm.copy()
        if self.target_tracker is not None:
            self.target_tracker.reset()
        self.filter.reset()

    def record_tracker_samples(self, samples: dict[str, TrackerSample]) -> None:
        """A tracker read's samples: the tick's, and the target sensor's history."""
        self.tracker_samples = samples
        if self.target_sensor is not None:
            self.target_sensor.add(samples)

    def record_robot_state(self, st: RobotState) -> None:
        self.last_state = st
        self.state_history.append(st)

    # ------------------------------------------------------------------ frame chain
    def robot_pose_at(self, t_ns: int) -> RigidTransform | None:
        """The robot's reported TCP pose at ``t_ns`` (robot frame), interpolated in the recent
        state history (clamped to its ends); None before any state."""
        hist = list(self.state_history)
        if not hist:
            return None
        if t_ns <= hist[0].t_ns:
            return hist[0].T_robot_from_tcp
        for a, b in itertools.pairwise(hist):
            if a.t_ns <= t_ns <= b.t_ns:
                f = (t_ns - a.t_ns) / max(b.t_ns - a.t_ns, 1)
                return interpolate_pose(a.T_robot_from_tcp, b.T_robot_from_tcp, f)
        return hist[-1].T_robot_from_tcp

    def T_optical_from_tcp_measured(self) -> RigidTransform | None:
        """The TCP pose measured by the camera from the flange markers (optical frame), from at
        least three seen markers (Horn's method, seed 000); None otherwise.

        Registered once per flange set: the marker update replaces :attr:`flange_mm` with a new
        array for every pair (never writes into it), so the result is kept for that array and the
        pair's cross-check, bias and guide error share one registration."""
        fl = self.flange_mm
        if fl is None:
            return None
        seen, T = self._tcp_measured
        if seen is fl:
            return T
        ok = np.all(np.isfinite(fl), axis=1)
        T = (None if int(ok.sum()) < 3
             else register_horn(fl[ok], self.rig.flange_markers_tcp_mm[ok]).T_fixed_from_moving)
        self._tcp_measured = (fl, T)
        return T

    def local(self, T_change: RigidTransform) -> RigidTransform:
        """The change expressed about the planned entry point (translation = its displacement)."""
        return self.T_center.inverse() @ T_change @ self.T_center

    def global_(self, T_local: RigidTransform) -> RigidTransform:
        """Inverse of :meth:`local`: an entry-centred change back in the optical frame."""
        return self.T_center @ T_local @ self.T_center.inverse()

    def T_optical_from_tcp_planned(self) -> RigidTransform:
        """Where the plan puts the TCP, in the optical frame (needs both registrations' robot side
        and the guide plan)."""
        assert self.robot_reg is not None
        assert self.guide_plan is not None
        return self.robot_reg.T_robot_from_optical.inverse() @ self.guide_plan.T_robot_from_tcp

    def bias_measurement(self, frame: StereoFrame) -> RigidTransform | None:
        """``D = E @ O^-1`` (seed 001 §2.3): the robot-frame correction that maps where the camera
        sees the TCP (O, through the registration) onto where the robot says it is (E), at the
        frame's exposure time. None without flange markers, robot states or registration."""
        O_opt = self.T_optical_from_tcp_measured()
        E = self.robot_pose_at(frame.left.t_ns)
        if O_opt is None or E is None or self.robot_reg is None:
            return None
        return E @ (self.robot_reg.T_robot_from_optical @ O_opt).inverse()

    def guide_error_optical_mm(self) -> float | None:
        """Distance between the camera-measured guide and where the guide should be for the
        patient as seen in the same frame (optical frame, mm; no registration in the loop). None
        before registration/plan or without markers."""
        O_opt = self.T_optical_from_tcp_measured()
        if O_opt is None or self.T_change_meas is None or self.guide_plan is None or self.robot_reg is None:
            return None
        desired = self.T_change_meas @ self.T_optical_from_tcp_planned() @ self.rig.T_tcp_from_guide
        measured = O_opt @ self.rig.T_tcp_from_guide
        return float(np.linalg.norm(measured.t - desired.t))

    def desired_tcp_robot(self, T_change: RigidTransform) -> RigidTransform:
        """The TCP pose (robot frame) that keeps the guide on the plan for the optical-frame
        patient change ``T_change``, with the closed-loop bias."""
        assert self.robot_reg is not None
        T_robot_from_optical = self.robot_reg.T_robot_from_optical
        return self.T_bias @ T_robot_from_optical @ T_change @ self.T_optical_from_tcp_planned()

    def desired_tcp_robot_local(self, T_local: RigidTransform) -> RigidTransform:
        """:meth:`desired_tcp_robot` of the entry-centred change ``T_local`` (the motion
        filter's), i.e. ``desired_tcp_robot(global_(T_local))`` as ``L @ T_local @ R`` with
        ``L = T_bias @ T_robot_from_optical @ T_center`` and ``R = T_center^-1 @
        T_optical_from_tcp_planned``. Both are kept while what they are made of is the same
        object (every part is immutable and replaced, never changed), so a pair's setpoint and its
        velocity cost two compositions each instead of seven (the supervisor's latency)."""
        L, R = self._chain_ends()
        return L @ T_local @ R

    def _chain_ends(self) -> tuple[RigidTransform, RigidTransform]:
        """(L, R) of :meth:`desired_tcp_robot_local`, rebuilt when a part was replaced."""
        assert self.robot_reg is not None
        assert self.guide_plan is not None
        chain = self._chain
        if (chain is None or chain[0] is not self.T_bias or chain[1] is not self.robot_reg
                or chain[2] is not self.guide_plan or chain[3] is not self.T_center):
            L = self.T_bias @ self.robot_reg.T_robot_from_optical @ self.T_center
            R = self.T_center.inverse() @ self.T_optical_from_tcp_planned()
            chain = self._chain = (self.T_bias, self.robot_reg, self.guide_plan, self.T_center, L, R)
        return chain[4], chain[5]

    def tracking_setpoint(self, t_ns: int, max_horizon_s: float, velocity_step_s: float
                          ) -> tuple[RigidTransform, FloatArray, FloatArray]:
        """The tracking setpoint for the filtered patient change at ``t_ns`` (controller clock,
        ns): the TCP pose (robot frame, mm) :meth:`desired_tcp_robot_local` gives for
        ``filter.estimate(t_ns, max_horizon_s)``, and its linear (mm/s) and angular (rad/s, robot
        frame) velocity, the difference over ``velocity_step_s`` of the filter's extrapolation
        ``(D1.t - D0.t) / step`` and ``rotvec(D1 @ D0^-1) / step`` (both zero when
        ``velocity_step_s`` is 0). Runs compiled (``tcp_setpoint``, hil/geometry/_native.c) when
        selected, else (and for any value the compiled code declines) in numpy; the two agree to
        rounding (tests/controller/test_control_law.py). Never blocks.

        Raises:
            GeometryError: the motion filter has no sample yet.
        """
        f = self.filter
        x, v = f.vectors()
        t1_ns = t_ns + round(velocity_step_s * 1e9)
        k = native.active()
        if k is not None:
            L, R = self._chain_ends()
            D_R, D_t, vel, w = np.empty((3, 3)), np.empty(3), np.empty(3), np.empty(3)
            if k.tcp_setpoint(x, v, f.horizon_s(t_ns, max_horizon_s), f.horizon_s(t1_ns, max_horizon_s),
                              velocity_step_s, L.R, L.t, R.R, R.t, D_R, D_t, vel, w) == 0:
                return RigidTransform._composed(D_R, D_t), vel, w
        D0 = self.desired_tcp_robot_local(f.estimate(t_ns, max_horizon_s))
        if velocity_step_s <= 0:
            return D0, np.zeros(3), np.zeros(3)
        D1 = self.desired_tcp_robot_local(f.estimate(t1_ns, max_horizon_s))
        return D0, (D1.t - D0.t) / velocity_step_s, (D1 @ D0.inverse()).as_rotvec() / velocity_step_s

    def setpoint_of_line(self, x: FloatArray, v: FloatArray, h0_s: float, h1_s: float
                         ) -> tuple[RigidTransform, FloatArray, FloatArray]:
        """The TCP pose (robot frame, mm) :meth:`desired_tcp_robot_local` gives for the
        entry-centred change ``x + v * h0_s`` (a 6-vector: t mm, rotation vector rad, as the
        filter's state), and the linear (mm/s) and angular (rad/s, robot frame) velocity of the
        secant to the pose at ``h1_s`` (``h1_s > h0_s``). The loop's predictor's setpoint
        (hil/controller/phases/predicted.py). Compiled (``tcp_setpoint``) when selected, numpy
        otherwise; the two agree to rounding (tests/controller/test_predictor_in_loop.py). Never
        blocks."""
        dt_s = h1_s - h0_s
        k = native.active()
        if k is not None:
            L, R = self._chain_ends()
            D_R, D_t, vel, w = np.empty((3, 3)), np.empty(3), np.empty(3), np.empty(3)
            if k.tcp_setpoint(x, v, h0_s, h1_s, dt_s, L.R, L.t, R.R, R.t, D_R, D_t, vel, w) == 0:
                return RigidTransform._composed(D_R, D_t), vel, w
        x0, x1 = x + v * h0_s, x + v * h1_s
        D0 = self.desired_tcp_robot_local(RigidTransform(rotvec_to_matrix(x0[3:]), x0[:3]))
        D1 = self.desired_tcp_robot_local(RigidTransform(rotvec_to_matrix(x1[3:]), x1[:3]))
        return D0, (D1.t - D0.t) / dt_s, (D1 @ D0.inverse()).as_rotvec() / dt_s

    def gate_measures(self) -> GateMeasures:
        """How far the live skin markers are from the reference state (RMS, worst marker, shape);
        all inf before registration or without live markers."""
        if self.patient_reg is None:
            return gate_measures(np.zeros((0, 3)), None)
        return gate_measures(self.patient_reg.reference_optical_mm, self.live_mm)

    def gate_problem(self) -> str | None:
        """Why the body is not back in the registered state by ``[procedure.gate]`` (None: it is;
        the gate's checks without its dwell)."""
        return self.gate_measures().problem(self.gate_cfg)

    def gate_deviation_mm(self) -> float:
        """RMS deviation of the live skin markers from the reference (mm); inf before
        registration or without live markers."""
        if self.patient_reg is None or self.live_mm is None:
            return math.inf
        return rms_deviation_mm(self.patient_reg.reference_optical_mm, self.live_mm)[0]

    def path_optical_now(self) -> tuple[FloatArray, FloatArray] | None:
        """The planned entry and target where they are now (optical frame, mm): the registration
        moved by the patient's current rigid change. None before registration."""
        if self.patient_reg is None:
            return None
        T = self.patient_reg.T_optical_from_image
        if self.T_change_meas is not None:
            T = self.T_change_meas @ T
        return T.apply(self.plan.entry_mm).reshape(3), T.apply(self.plan.target_mm).reshape(3)
