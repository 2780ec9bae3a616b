"""COMPENSATE: follow the rigid change of the patient markers (seed 000 section 3).

The change reference -> live, ``T_live_from_ref`` (optical frame), is solved from the matched
marker sets with Horn's quaternion method (seed 000 eqs 17-21) and applied to the planned path:
the desired guide pose is ``T_live_from_ref @ T_optical_from_guide_planned``. The estimate is
smoothed by an alpha-beta filter (position and velocity of the 6 pose parameters), predicted
forward over the measured latency plus the robot's actuation lag (capped), bounded (beyond the
bound the controller pauses and asks the operator), and the command is rate-limited in speed and
acceleration (a stopping-distance limit keeps it from overshooting).

With ``[procedure.compensation] predictor`` other than ``"alpha-beta"`` a :class:`ChangePredictor`
rides on the filter: it is fed the measured displacement of the entry point (the translation of
the entry-centred change) at each pair and predicts it over the latency; the setpoint's
translation follows it, the rotation stays the filter's (docs/prediction.md "In the loop").
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil.controller.change_estimate import ChangeFit
from hil.controller.config import CompensationConfig, ProcedureConfig
from hil.errors import GeometryError
from hil.geometry import native
from hil.geometry.registration import Registration, register_horn
from hil.geometry.transform import RigidTransform, rotvec_to_matrix
from hil.prediction import GuardedPredictor, PredictionError, SafetyLimits, make_predictor
from hil.servo.limiter import LimiterArgs, RateLimiter

__all__ = ["ChangePredictor", "MotionFilter", "PredictorFallback", "RateLimiter", "change_out_of_bounds",
           "correction_out_of_bounds", "deformation_out_of_bounds", "interpolate_pose", "limiter_args",
           "rigid_change"]

FloatArray = NDArray[np.float64]


def rigid_change(reference_mm: FloatArray, live_mm: FloatArray) -> Registration | None:
    """``T_live_from_ref`` from corresponding marker rows (NaN rows = not seen), seed 000 eqs
    17-21 (Horn). Returns None with fewer than 3 usable, non-degenerate pairs."""
    ok = np.isfinite(reference_mm).all(axis=1) & np.isfinite(live_mm).all(axis=1)
    if int(ok.sum()) < 3:
        return None
    try:
        return register_horn(live_mm[ok], reference_mm[ok])
    except GeometryError:
        return None


def limiter_args(procedure: ProcedureConfig, T_tcp_from_guide: RigidTransform) -> LimiterArgs:
    """The servo's :class:`RateLimiter` for ``procedure``: the correction's limits
    (``[procedure.compensation]``) about the pivot ``rate_limit_pivot`` names: the entry, the
    stand-off (``[procedure.planning] standoff_mm``) down the guide's z axis, in the TCP frame
    (``T_tcp_from_guide``: the rig's guide), or the TCP."""
    c = procedure.compensation
    pivot = (0.0, 0.0, 0.0)
    if c.rate_limit_pivot == "entry":
        entry_tcp_mm = T_tcp_from_guide.apply(np.array([0.0, 0.0, procedure.planning.standoff_mm]))
        x, y, z = (float(v) for v in entry_tcp_mm)
        pivot = (x, y, z)
    return (c.max_speed_mm_s, c.max_accel_mm_s2, c.max_angular_speed_rad_s, c.max_angular_accel_rad_s2, pivot)


def _to_vec(T: RigidTransform) -> FloatArray:
    return np.concatenate([T.t, T.as_rotvec()])


def _from_vec(x: FloatArray) -> RigidTransform:
    return RigidTransform(rotvec_to_matrix(x[3:]), x[:3])


def deformation_out_of_bounds(fit: ChangeFit | None, cfg: CompensationConfig) -> str | None:
    """The deformation monitor: None while the skin markers' rigid-fit residual (the last pair's
    :attr:`ChangeFit.rigid_fre_mm`) is within ``deformation_bound_mm``, else the reason (the body no
    longer moves as the model explains: a cough, the patient moving on the table, a marker come
    off or swapped)."""
    if fit is None or fit.rigid_fre_mm <= cfg.deformation_bound_mm:
        return None
    return (f"the skin markers no longer move as one body: rigid-fit residual {fit.rigid_fre_mm:.1f} mm "
            f"beyond {cfg.deformation_bound_mm} mm (the change estimate cannot be vouched for)")


def change_out_of_bounds(T_change: RigidTransform, fit: ChangeFit | None,
                         cfg: CompensationConfig) -> str | None:
    """:func:`correction_out_of_bounds`, then :func:`deformation_out_of_bounds`.

    With ``target_model = "surrogate"`` the change also carries the model's turn of the path (at
    most ``target_model_max_turn_deg``, hil/controller/target_model.py), which is not the
    patient turning: the commanded change's rotation may then reach ``max_correction_deg`` plus
    that turn, and the patient's own rotation (the estimator's change in ``fit``, before the
    model; a rotation's angle does not depend on the point it is taken about) is held to
    ``max_correction_deg``."""
    if cfg.target_model == "surrogate":
        why = correction_out_of_bounds(T_change, cfg, cfg.target_model_max_turn_deg)
        if why is None and fit is not None:
            a = math.degrees(fit.T_live_from_ref.rotation_angle_rad())
            if a > cfg.max_correction_deg:
                why = (f"patient turned {a:.1f} deg from the registered state "
                       f"(bound {cfg.max_correction_deg} deg)")
    else:
        why = correction_out_of_bounds(T_change, cfg)
    return why or deformation_out_of_bounds(fit, cfg)


def correction_out_of_bounds(T_change: RigidTransform, cfg: CompensationConfig,
                             turn_allowance_deg: float = 0.0) -> str | None:
    """None when the change is within the correction bounds, else the reason.

    ``T_change`` must be expressed about the point that matters (the controller uses the planned
    entry), so that its translation is that point's displacement. ``turn_allowance_deg``: a turn
    of the path the change carries besides the patient's (:func:`change_out_of_bounds`).
    """
    t = T_change.translation_norm()
    a = math.degrees(T_change.rotation_angle_rad())
    if t > cfg.max_correction_mm:
        return f"patient moved {t:.1f} mm from the registered state (bound {cfg.max_correction_mm} mm)"
    if a > cfg.max_correction_deg + turn_allowance_deg:
        if turn_allowance_deg:
            return (f"the path turned {a:.1f} deg from the plan (bound {cfg.max_correction_deg} deg for the "
                    f"patient + {turn_allowance_deg} deg for the target model)")
        return f"patient turned {a:.1f} deg from the registered state (bound {cfg.max_correction_deg} deg)"
    return None


@dataclass(frozen=True)
class PredictorFallback:
    """One fallback of the loop's predictor: the pair's exposure time (controller clock, ns), the
    reason (:attr:`GuardedPredictor.last_fallback_reason`) and the count so far."""

    exposure_t_ns: int
    reason: str
    fallbacks: int


class ChangePredictor:
    """The configured predictor (hil/prediction) on the entry point's displacement, mm, in the
    entry-centred optical frame: the translation of ``T_center^-1 @ T_live_from_ref @ T_center``.

    Fed by :meth:`MotionFilter.update_about` at each pair with a measured change (a dropout, no
    change, feeds nothing; the next pair's interval is then a gap: the guard restarts the model).
    Times are the pairs' exposures (controller clock, ns), taken relative to the first sample
    after a reset. The guard's limits come from ``[procedure.compensation] predictor_*`` and
    ``max_prediction_s``. Never blocks; CPU per pair: docs/prediction.md "Cost".

    Args:
        cfg: the compensation section (``predictor`` must not be ``"alpha-beta"``: that is the
            filter alone).
        rate_hz: the camera's pair rate the model is set up for, Hz.

    Raises:
        PredictionError: an unknown predictor or a rate that is not a finite number > 0.
    """

    def __init__(self, cfg: CompensationConfig, rate_hz: float) -> None:
        limits = SafetyLimits(max_horizon_s=cfg.max_prediction_s,
                              max_departure_mm=cfg.predictor_max_departure_mm,
                              max_speed_mm_s=cfg.predictor_max_speed_mm_s,
                              innovation_bound_mm=cfg.predictor_innovation_bound_mm,
                              hold_s=cfg.predictor_hold_s)
        self.predictor: GuardedPredictor = make_predictor(cfg.predictor, rate_hz, limits,
                                                          alpha=cfg.filter_alpha, beta=cfg.filter_beta)
        self.name = cfg.predictor
        #: the last sample's exposure (ns; None before one) and the time origin of the model's seconds
        self.last_t_ns: int | None = None
        self._t0_ns: int | None = None
        #: fallbacks not yet said in the session log (COMPENSATE drains them)
        self.unreported: list[PredictorFallback] = []
        #: samples the guard refused (not finite, time not forward): skipped like a dropout
        self.refused = 0
        #: the last :meth:`update`'s duration, ns (process clock: a cost figure, not control)
        self.update_ns = 0

    def reset(self) -> None:
        """Forget every sample (a new registration); the fallback count stays."""
        self.predictor.reset()
        self.last_t_ns = self._t0_ns = None
        self.unreported.clear()

    @property
    def predicting(self) -> bool:
        """Whether the model answers (warm, not holding after a fallback)."""
        return self.predictor.predicting

    @property
    def fallbacks(self) -> int:
        """Fallbacks since the procedure started (gap, rate, innovation, output not finite)."""
        return self.predictor.fallbacks

    @property
    def last_fallback_reason(self) -> str | None:
        """Why the last fallback was taken (None: none yet)."""
        return self.predictor.last_fallback_reason

    def update(self, displacement_mm: FloatArray, t_ns: int) -> None:
        """Feed the entry's measured displacement (the translation of the entry-centred change,
        (3,) mm) at exposure ``t_ns`` (ns). A refused sample (not finite, not after the previous
        one) is skipped and counted in :attr:`refused`."""
        if self._t0_ns is None:
            self._t0_ns = t_ns
        before = self.predictor.fallbacks
        t0 = time.perf_counter_ns()
        try:
            self.predictor.update((t_ns - self._t0_ns) * 1e-9, displacement_mm)
        except PredictionError:
            self.refused += 1
            return
        finally:
            self.update_ns = time.perf_counter_ns() - t0
        self.last_t_ns = t_ns
        if self.predictor.fallbacks != before:
            self.unreported.append(PredictorFallback(t_ns, self.predictor.last_fallback_reason or "",
                                                     self.predictor.fallbacks))

    def predict_mm(self, horizon_s: float) -> FloatArray:
        """The entry's displacement ``horizon_s`` after the last sample (mm; bounded by the guard).

        Raises:
            PredictionError: no sample yet, or a negative or non-finite horizon.
        """
        return self.predictor.predict(horizon_s)


class MotionFilter:
    """Alpha-beta filter on ``T_live_from_ref`` as a 6-vector (t mm, rotation vector rad).

    The rotation vector is additive for the small rotations compensated here (bounded by
    ``max_correction_deg``).
    """

    def __init__(self, alpha: float, beta: float) -> None:
        self.alpha = alpha
        self.beta = beta
        self._x: FloatArray | None = None
        self._v = np.zeros(6)
        self._t_ns = 0
        #: the loop's predictor of the entry's displacement, fed beside the filter (None: alpha-beta)
        self.predictor: ChangePredictor | None = None

    @property
    def initialised(self) -> bool:
        return self._x is not None

    def reset(self) -> None:
        self._x = None
        self._v = np.zeros(6)
        if self.predictor is not None:
            self.predictor.reset()

    def update(self, T_meas: RigidTransform, t_ns: int) -> None:
        """Feed the measured change at frame time ``t_ns`` (must not go back in time)."""
        z = _to_vec(T_meas)
        if self._x is None:
            self._x, self._v, self._t_ns = z, np.zeros(6), t_ns
            return
        dt = (t_ns - self._t_ns) * 1e-9
        if dt <= 0:
            return
        x_pred = self._x + self._v * dt
        r = z - x_pred
        self._x = x_pred + self.alpha * r
        self._v = self._v + (self.beta / dt) * r
        self._t_ns = t_ns

    def update_about(self, T_meas: RigidTransform, T_center: RigidTransform, t_ns: int) -> None:
        """:meth:`update` with the measured change ``T_meas`` expressed about ``T_center``:
        feeds ``T_center^-1 @ T_meas @ T_center``. Runs compiled (``filter_feed``,
        hil/geometry/_native.c) when selected and the filter has a sample; the numpy code
        otherwise and for any value the compiled code declines. The two agree to rounding
        (tests/controller/test_control_law.py). The :attr:`predictor`, if any, is fed the same
        change about the centre after the filter."""
        self._update_about(T_meas, T_center, t_ns)
        if self.predictor is not None:   # the translation of T_center^-1 @ T_meas @ T_center
            Rc, tc = T_center.R, T_center.t
            self.predictor.update(Rc.T @ (T_meas.R @ tc + T_meas.t - tc), t_ns)

    def _update_about(self, T_meas: RigidTransform, T_center: RigidTransform, t_ns: int) -> None:
        k = native.active()
        if k is not None and self._x is not None:
            dt = (t_ns - self._t_ns) * 1e-9
            if dt <= 0:
                return
            if k.filter_feed(T_meas.R, T_meas.t, T_center.R, T_center.t, self._x, self._v, dt,
                             self.alpha, self.beta) == 0:
                self._t_ns = t_ns
                return
        self.update(T_center.inverse() @ T_meas @ T_center, t_ns)

    def horizon_s(self, t_ns: int | None, max_horizon_s: float) -> float:
        """How far :meth:`estimate` extrapolates for ``t_ns``: the time since the last sample,
        s, within [0, ``max_horizon_s``] (0 for None)."""
        return 0.0 if t_ns is None else min(max((t_ns - self._t_ns) * 1e-9, 0.0), max_horizon_s)

    def vectors(self) -> tuple[FloatArray, FloatArray]:
        """The state (x, v): the change's 6-vector (t mm, rotation vector rad) at the last
        sample and its rate (per s). The arrays are the filter's own: read, never write.

        Raises:
            GeometryError: nothing fed yet.
        """
        if self._x is None:
            raise GeometryError("motion filter has no sample yet")
        return self._x, self._v

    def estimate(self, t_ns: int | None = None, max_horizon_s: float = 0.0) -> RigidTransform:
        """The filtered change, extrapolated to ``t_ns`` (at most ``max_horizon_s`` ahead of the
        last sample; never backwards). Compiled (``filter_pose``) when selected, as
        :meth:`update_about`.

        Raises:
            GeometryError: nothing fed yet.
        """
        x, v = self.vectors()
        h = self.horizon_s(t_ns, max_horizon_s)
        k = native.active()
        if k is not None:
            R, t = np.empty((3, 3)), np.empty(3)
            if k.filter_pose(x, v, h, R, t) == 0:
                return RigidTransform._composed(R, t)
        return _from_vec(x + v * h)

    @property
    def speed_mm_s(self) -> float:
        """|translational rate|, mm/s (np.linalg.norm's own dot product, without its layers)."""
        v = self._v[:3]
        return math.sqrt(float(v.dot(v)))


def interpolate_pose(a: RigidTransform, b: RigidTransform, f: float) -> RigidTransform:
    """Pose ``f`` of the way from ``a`` to ``b`` (linear in translation, geodesic in rotation)."""
    rel = a.inverse() @ b
    R = a.R @ rotvec_to_matrix(rel.as_rotvec() * f)
    return RigidTransform(R, a.t + f * (b.t - a.t))
