"""The surrogate target model: the path's direction follows the target the skin predicts.

Why (issue 41 point 2): the change estimators move the planned path about the entry with the
skin's rigid motion, so the direction after motion is "rigid about the entry". The target inside
moves on its own (liver and lung 5-25 mm superior-inferior, AAPM TG-76), and a breathing patient's
skin shows it only through a correlation. Clinical systems fit that correlation: CyberKnife
Synchrony from X-ray images during treatment; 4D-CT-based models from the planning CT's breathing
phases. This is the second kind.

**The model** (fitted once, from the plan's ``phases``: a 4D CT's fiducials and target at K
breathing phases, hil/controller/plan_file.py). With ``F_0``, ``t_0`` the registered phase
(end-exhale) and ``F_k``, ``t_k`` phase k (image frame):

- ``D_k = vec(F_k - F_0)`` (3N), the skin's displacement pattern at phase k;
- ``u`` = the first principal direction of the ``D_k`` (unit, 3N; sign: inhale positive): one
  breathing pattern of the skin;
- ``z_k = u . D_k`` (mm): the breathing score of phase k;
- ``a = argmin sum_k |t_k - t_0 - z_k a|^2`` (3,): the target's displacement per mm of score
  (least squares through the registered phase).

**Live**, each pair: the seen markers' displacements from their registered positions, turned into
the image frame (``R_image_from_optical (m_i - r_i)``), give the score by least squares on the
seen part of ``u``; the target is ``t_0 + z a`` (image), mapped into the optical frame by the
registration, then moved by the part of the estimator's change that breathing does not explain:
``T_change @ T_breath(z)^-1``, ``T_breath(z)`` the rigid fit (Horn, seed 000 eqs 17-21) of the
seen markers onto themselves displaced by ``z u`` (a slow drift or a small shift on the table moves
the target with the skin; breathing moves it by ``z a`` alone). The estimator's change is then
turned about the moved entry so that the path points from the moved entry at the modelled target
(the smallest rotation from the rigidly moved direction). Its translation at the entry, so the
entry's estimate, is unchanged.

**What it assumes, where it fails**: one breathing pattern (the first principal component) and a
target linear in it; no lag, no hysteresis (the target's loop between inhale and exhale is averaged
into ``a``); the patient breathes as in the 4D CT; the registration frame holds (no rigid shift of
the patient since registration). It cannot see breath-hold reproducibility (the target's offset
when a hold ends elsewhere than the CT's). Each pair it falls back to the rigid direction, and
says why, when:

- the seen markers carry less than a quarter of the pattern (``|u_seen|^2 < 0.25``): too few or
  the wrong markers seen;
- the markers do not move as the pattern says: the per-marker RMS residual of ``D - z u`` beyond
  ``target_model_residual_mm`` (the patient moved on the table, a cough, a marker swapped);
- the score is outside the 4D CT's range by more than a quarter of it (breathing deeper than at
  the CT: the linear model would extrapolate);
- the model would turn the path by more than ``target_model_max_turn_deg``.

Cost per pair: a few dot products and one Horn fit of the seen markers (docs/compensation.md
"Cost on the pair's path").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil.controller.plan_file import ProcedurePlan
from hil.errors import GeometryError, InputFileError
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

FloatArray = NDArray[np.float64]

__all__ = ["MIN_PATTERN_SHARE", "MIN_PHASES", "MIN_SCORE_RANGE_MM", "TARGET_MODELS", "SurrogateTargetModel",
           "TargetSteer", "fit_target_model"]

#: ``[procedure.compensation] target_model``'s values
TARGET_MODELS: tuple[str, ...] = ("rigid", "surrogate")

#: the model needs at least this many phases besides the registered one
MIN_PHASES = 2
#: a 4D CT whose fiducials move less than this (score range, mm) carries no pattern to correlate
MIN_SCORE_RANGE_MM = 1.0
#: the seen markers must carry at least this share of the pattern (``|u_seen|^2``)
MIN_PATTERN_SHARE = 0.25
#: the score may leave the 4D CT's range by this share of the range
_RANGE_MARGIN = 0.25


@dataclass(frozen=True)
class TargetSteer:
    """One pair's use of the model.

    Attributes:
        T_live_from_ref: the change with the direction steered (the estimator's when it fell back).
        score_mm: the breathing score (NaN when not computed).
        target_shift_mm: the modelled target's displacement from the plan's, mm (0 on fallback).
        turn_deg: the rotation added to the estimator's direction, deg (0 on fallback).
        fallback: why the rigid direction was kept ("" when the model steered).
    """

    T_live_from_ref: RigidTransform
    score_mm: float
    target_shift_mm: float
    turn_deg: float
    fallback: str = ""


def _turn(a: FloatArray, b: FloatArray) -> FloatArray:
    """The smallest rotation taking unit vector ``a`` onto unit vector ``b`` (3x3)."""
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    c = float(np.clip(a @ b, -1.0, 1.0))
    if s < 1e-12:
        return np.eye(3)
    return rotvec_to_matrix(axis / s * math.atan2(s, c))


@dataclass(frozen=True)
class SurrogateTargetModel:
    """The fitted model (module doc). Build it with :func:`fit_target_model`.

    Attributes:
        pattern: ``u``, (N, 3) per fiducial, unit as a whole, image frame.
        target_per_score: ``a``, (3,), mm of target displacement per mm of score, image frame.
        score_min_mm, score_max_mm: the 4D CT's score range (the registered phase's 0 included).
        fit_residual_mm: RMS of the target's fit over the phases, mm (what the CT says the model
            misses: lag, hysteresis).
        explained: share of the skin's displacement variance the pattern explains (0-1).
        residual_bound_mm: ``target_model_residual_mm``.
        max_turn_deg: ``target_model_max_turn_deg``.
    """

    pattern: FloatArray
    target_per_score: FloatArray
    score_min_mm: float
    score_max_mm: float
    fit_residual_mm: float
    explained: float
    residual_bound_mm: float
    max_turn_deg: float

    def target_image_mm(self, plan_target_mm: FloatArray, score_mm: float) -> FloatArray:
        """The modelled target at ``score_mm`` (image frame, mm)."""
        out: FloatArray = plan_target_mm + score_mm * self.target_per_score
        return out

    def score(self, reference_mm: FloatArray, live_mm: FloatArray,
              R_image_from_optical: FloatArray) -> tuple[float, str]:
        """(score mm, "") from corresponding marker rows (optical frame, NaN = not seen), or
        (NaN, why not) (module doc's first two fallbacks)."""
        ok = np.isfinite(reference_mm).all(axis=1) & np.isfinite(live_mm).all(axis=1)
        u = self.pattern[ok]
        share = float((u * u).sum())
        if share < MIN_PATTERN_SHARE:
            return math.nan, (f"the seen markers carry {share:.0%} of the 4D CT's breathing pattern "
                              f"(need {MIN_PATTERN_SHARE:.0%})")
        d = (live_mm[ok] - reference_mm[ok]) @ R_image_from_optical.T
        z = float((u * d).sum()) / share
        resid = math.sqrt(float(((d - z * u) ** 2).sum()) / int(ok.sum()))
        if resid > self.residual_bound_mm:
            return math.nan, (f"the markers do not move as in the 4D CT: residual {resid:.1f} mm beyond "
                              f"{self.residual_bound_mm} mm (patient moved, a cough, a marker swapped)")
        span = self.score_max_mm - self.score_min_mm
        lo, hi = self.score_min_mm - _RANGE_MARGIN * span, self.score_max_mm + _RANGE_MARGIN * span
        if not lo <= z <= hi:
            return math.nan, (f"breathing beyond the 4D CT's range: score {z:.1f} mm outside "
                              f"{self.score_min_mm:.1f}..{self.score_max_mm:.1f} mm")
        return z, ""

    def steer(self, T_live_from_ref: RigidTransform, reference_mm: FloatArray, live_mm: FloatArray,
              plan: ProcedurePlan, T_optical_from_image: RigidTransform) -> TargetSteer:
        """The estimator's change ``T_live_from_ref`` (optical frame) turned about the moved entry so
        the path points at the modelled target (module doc). Never raises: a pair the model cannot
        vouch for keeps the estimator's change and names why in :attr:`TargetSteer.fallback`."""
        R_oi = T_optical_from_image.R
        z, why = self.score(reference_mm, live_mm, R_oi.T)
        if why:
            return TargetSteer(T_live_from_ref, z, 0.0, 0.0, why)
        ok = np.isfinite(reference_mm).all(axis=1) & np.isfinite(live_mm).all(axis=1)
        ref = reference_mm[ok]
        try:      # the rigid motion the breathing pattern itself makes at this score
            T_breath = register_horn(ref + z * (self.pattern[ok] @ R_oi.T), ref).T_fixed_from_moving
        except GeometryError as exc:
            why = f"the seen markers cannot carry a rigid fit: {exc}"
            return TargetSteer(T_live_from_ref, z, 0.0, 0.0, why)
        entry_ref = T_optical_from_image.apply(plan.entry_mm).reshape(3)
        target_ref = T_optical_from_image.apply(plan.target_mm).reshape(3)
        shift_img = z * self.target_per_score
        # the change less breathing's own rigid part (a shift on the table, drift) moves the target too
        T_other = T_live_from_ref @ T_breath.inverse()
        target_live = T_other.apply(target_ref + R_oi @ shift_img).reshape(3)
        entry_live = T_live_from_ref.apply(entry_ref).reshape(3)
        d0 = T_live_from_ref.R @ (target_ref - entry_ref)
        d1 = target_live - entry_live
        d0 /= np.linalg.norm(d0)
        d1 /= np.linalg.norm(d1)
        turn = math.degrees(math.acos(float(np.clip(d0 @ d1, -1.0, 1.0))))
        if turn > self.max_turn_deg:
            why = f"the model would turn the path {turn:.1f} deg (bound {self.max_turn_deg} deg)"
            return TargetSteer(T_live_from_ref, z, 0.0, 0.0, why)
        R = _turn(d0, d1) @ T_live_from_ref.R
        T = RigidTransform(R, entry_live - R @ entry_ref)
        return TargetSteer(T, z, float(np.linalg.norm(shift_img)), turn)


def fit_target_model(plan: ProcedurePlan, residual_bound_mm: float,
                     max_turn_deg: float) -> SurrogateTargetModel:
    """Fit the model to ``plan.phases`` (module doc).

    Raises:
        InputFileError: naming the plan: fewer than :data:`MIN_PHASES` phases, or fiducials that move
            less than :data:`MIN_SCORE_RANGE_MM` over them.
    """
    if len(plan.phases) < MIN_PHASES:
        raise InputFileError(plan.source, f"the surrogate target model needs a 4D CT: >= {MIN_PHASES} "
                             f"breathing phases in the plan's 'phases', it has {len(plan.phases)}")
    D = np.stack([(ph.fiducials_mm - plan.fiducials_mm).reshape(-1) for ph in plan.phases])
    Y = np.stack([ph.target_mm - plan.target_mm for ph in plan.phases])
    _, sv, vt = np.linalg.svd(D, full_matrices=False)
    u = vt[0]
    z = D @ u
    if z.sum() < 0:                       # inhale positive: most phases are away from end-exhale
        u, z = -u, -z
    span = float(max(z.max(), 0.0) - min(z.min(), 0.0))
    if span < MIN_SCORE_RANGE_MM:
        raise InputFileError(plan.source, f"phases: the fiducials move {span:.2f} mm over the 4D CT (< "
                             f"{MIN_SCORE_RANGE_MM} mm): no breathing pattern to correlate the target with")
    a = (z @ Y) / float(z @ z)
    resid = math.sqrt(float(((Y - np.outer(z, a)) ** 2).sum(axis=1).mean()))
    explained = float(sv[0] ** 2 / (sv**2).sum())
    return SurrogateTargetModel(
        pattern=u.reshape(-1, 3), target_per_score=a, score_min_mm=float(min(z.min(), 0.0)),
        score_max_mm=float(max(z.max(), 0.0)), fit_residual_mm=resid, explained=explained,
        residual_bound_mm=residual_bound_mm, max_turn_deg=max_turn_deg)
