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
  (least squares through the registered phase);
- when the plan says the phases are one breath's equal bins at a period (``phases_period_s``),
  the score's rate ``z'_k`` (central differences around the cycle) joins as a second regressor:
  ``t_k - t_0 = z_k a + z'_k b`` (least squares). ``b`` (mm per mm/s) is the target's lag and
  hysteresis behind the skin, which a line in ``z`` alone averages away; a state-augmented
  correlation model of this kind is what the respiratory-tracking literature uses for the
  phase shift between surrogate and tumour (the inhale and exhale branches of Synchrony's models
  answer the same effect).

**Live**, each pair: the seen markers' displacements from their registered positions, turned into
the image frame (``R_image_from_optical (m_i - r_i)``), give the score by least squares on the
seen part of ``u``; the target is ``t_0 + z a`` (image), mapped into the optical frame by the
registration, then moved by what the markers moved beyond the pattern: the mean over the seen
markers of ``m_i - r_i - z R_image_from_optical^T u_i`` (a slow drift or a small shift on the
table moves the target with the skin; breathing moves it by ``z a`` alone). Only that translation:
the skin tilts as it breathes, and a rotation fitted to the markers (the estimator's change, which
turns with the skin about the entry, against the pattern's own rigid fit) would swing the target
75 mm below with the surface. Measured that way (the previous rule, ``T_change @ T_breath(z)^-1``),
the path's direction at its pair was 2.4 deg p95 off on the simulated patient; with the
translation, 1.0 deg (the markers' true positions, seeds 1-12: docs/compensation.md "The
direction"). The estimator's change is then turned about the moved entry so that the path points
from the moved entry at the modelled target (the smallest rotation from the rigidly moved
direction). Its translation at the entry, so the entry's estimate, is unchanged.

Live, the score's rate comes from pair to pair (:class:`TargetTracker`: an exponential average of
the differences, gain :data:`RATE_GAIN`, restarted after a gap over :data:`MAX_RATE_GAP_S` or a
pair the model could not judge, held within 1.5 times the 4D CT's fastest).

With a sensor at the target (``[procedure.tracking] target_sensor``,
:mod:`hil.controller.target_sensor`) the tracker turns the path at the target it measures instead
(:func:`turn_to_target`, bound ``target_sensor_max_turn_deg``) whenever the pair has a measurement,
and at the model's when it has none; :attr:`TargetSteer.source` says which.

**What it assumes, where it fails**: one breathing pattern (the first principal component) and a
target linear in it and its rate (without ``phases_period_s``, in it alone: the target's lag and
its loop between inhale and exhale are then averaged into ``a``); the patient breathes as in the
4D CT; the patient has not turned since registration (a shift is followed; a turn is not: on
the simulated patient a turn of 1 deg about the entry in the skin's plane leaves the markers
0.6-0.8 mm off the pattern, under the residual bound, and the direction 0.8-0.9 deg off; beyond
about 2.5 deg the residual bound refuses the pair, which keeps the estimator's direction, turning
with the patient). It cannot see breath-hold reproducibility (the target's offset when a hold
ends elsewhere than the CT's). A pair it cannot vouch for keeps the rigid direction (the last turn
it could vouch for fading out over :data:`TURN_RAMP_S`), and says why, when:

- the seen markers carry less than a quarter of the pattern (``|u_seen|^2 < 0.25``): too few or
  the wrong markers seen;
- the markers do not move as the pattern says: the per-marker RMS residual of ``D - z u`` beyond
  ``target_model_residual_mm`` (the patient moved on the table, a cough, a marker swapped);
- the modelled target comes within :data:`MIN_PATH_MM` of the entry (no direction to trust).

Two bounds hold the model's answer instead of discarding it, and say so
(:attr:`TargetSteer.limited`): a pair that breathes as the pattern says but deeper than the CT
tells the direction the target went, not how far beyond the CT's breaths. The rigid direction is
then the worse answer: on the two recorded 6-DoF liver traces (docs/benchmarks.md "Issue 41:
breathing deeper than the 4D CT"), breaths up to 1.9 times the 4D CT's average one put 11 % and
19 % of the pairs beyond the range or the turn bound, and keeping the rigid direction there left
the path 6.8 and 16 deg p95 off (the true markers, offline) where the held model leaves it 0.7 and
6 deg off.

- the score beyond the 4D CT's range by more than half of it (breathing much deeper than at the
  CT: the line would extrapolate far) is held at that edge for the target (the markers' own
  displacement beyond the pattern is still taken at the score they read);
- a turn beyond ``target_model_max_turn_deg`` is held at the bound, about the same axis (the
  path never turns further than the bound; it turns towards the modelled target as far as it may).

Cost per pair: a few dot products over the seen markers, compiled
(hil/geometry/_native.c ``target_score``, ``target_turn``, ``turn_about``; :func:`score_parts_numpy`,
:func:`turn_numpy` and the numpy branch of :func:`turned_about_entry` are the reference it is
tested against and what runs when the numpy code is selected, :mod:`hil.geometry.native`):
docs/compensation.md "Cost on the pair's path".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from hil.controller.plan_file import ProcedurePlan
from hil.controller.target_sensor import TargetReading
from hil.errors import GeometryError, InputFileError
from hil.geometry import native
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

FloatArray = NDArray[np.float64]

__all__ = ["MAX_RATE_GAP_S", "MIN_PATH_MM", "MIN_PATTERN_SHARE", "MIN_PHASES", "MIN_PHASES_FOR_RATE",
           "MIN_SCORE_RANGE_MM", "RATE_GAIN", "TARGET_MODELS", "TURN_RAMP_S", "PathTurn",
           "SurrogateTargetModel", "TargetSteer", "TargetTracker", "fit_target_model", "held_turn",
           "score_parts_numpy", "turn_numpy", "turn_to_target", "turned_about_entry"]

#: ``[procedure.compensation] target_model``'s values
TARGET_MODELS: tuple[str, ...] = ("rigid", "surrogate")

#: the model needs at least this many phases besides the registered one
MIN_PHASES = 2
#: the rate term needs a cycle of at least this many bins, the registered one included
MIN_PHASES_FOR_RATE = 4
#: a 4D CT whose fiducials move less than this (score range, mm) carries no pattern to correlate
MIN_SCORE_RANGE_MM = 1.0
#: the seen markers must carry at least this share of the pattern (``|u_seen|^2``)
MIN_PATTERN_SHARE = 0.25
#: the score may leave the 4D CT's range by this share of the range (breaths vary 10-30 % in depth
#: from one to the next; the CT's is an average one)
_RANGE_MARGIN = 0.5
#: the live score rate's exponential-average gain per pair
RATE_GAIN = 0.3
#: a gap between judged pairs longer than this restarts the rate, s
MAX_RATE_GAP_S = 0.5
#: the live rate is held within this multiple of the 4D CT's fastest
_RATE_MARGIN = 1.5
#: the model's turn fades in (and out, after a fallback) over this long, s
TURN_RAMP_S = 0.5
#: a path from the entry to the (modelled) target shorter than this has no direction to trust, mm
#: (hil/geometry/_native.c ``MIN_PATH_MM``)
MIN_PATH_MM = 1.0


@dataclass(frozen=True)
class TargetSteer:
    """One pair's use of the model.

    Attributes:
        T_live_from_ref: the change with the direction steered (the estimator's when it fell back).
        score_mm: the breathing score (NaN when not computed).
        target_shift_mm: the modelled target's displacement from the plan's, mm (0 on fallback).
        turn_deg: the rotation added to the estimator's direction, deg (0 on fallback).
        fallback: why the rigid direction was kept ("" when the model or the sensor steered).
        limited: which bound held the model's answer, and where ("" when none did; module doc).
        source: what the path pointed at: "model" (the modelled target), "sensor" (the target
            sensor's, :mod:`hil.controller.target_sensor`) or "" (the rigid direction kept).
        sensor_why_not: with a target sensor configured, why this pair had no measurement from it
            ("" when it had, or without one).
    """

    T_live_from_ref: RigidTransform
    score_mm: float
    target_shift_mm: float
    turn_deg: float
    fallback: str = ""
    limited: str = ""
    source: str = "model"
    sensor_why_not: str = ""


@dataclass(frozen=True)
class SurrogateTargetModel:
    """The fitted model (module doc). Build it with :func:`fit_target_model`.

    Attributes:
        pattern: ``u``, (N, 3) per fiducial, unit as a whole, image frame.
        target_per_score: ``a``, (3,), mm of target displacement per mm of score, image frame.
        target_per_rate: ``b``, (3,), mm of target displacement per mm/s of score rate (zeros when
            the plan gives no ``phases_period_s``).
        max_rate_mm_s: the 4D CT's fastest score rate, mm/s (inf without a period).
        score_min_mm, score_max_mm: the 4D CT's score range (the registered phase's 0 included).
        fit_residual_mm: RMS of the target's fit over the phases, mm (what the CT says the model
            misses: lag, hysteresis).
        explained: share of the skin's displacement variance the pattern explains (0-1).
        residual_bound_mm: ``target_model_residual_mm``.
        max_turn_deg: ``target_model_max_turn_deg``.
    """

    pattern: FloatArray
    target_per_score: FloatArray
    target_per_rate: FloatArray
    max_rate_mm_s: float
    score_min_mm: float
    score_max_mm: float
    fit_residual_mm: float
    explained: float
    residual_bound_mm: float
    max_turn_deg: float

    def __post_init__(self) -> None:
        for name in ("pattern", "target_per_score", "target_per_rate"):   # as the kernels take them
            object.__setattr__(self, name, _c64(getattr(self, name)))

    def target_image_mm(self, plan_target_mm: FloatArray, score_mm: float) -> FloatArray:
        """The modelled target at ``score_mm`` (image frame, mm)."""
        out: FloatArray = plan_target_mm + score_mm * self.target_per_score
        return out

    def score(self, reference_mm: FloatArray, live_mm: FloatArray,
              T_optical_from_image: RigidTransform) -> tuple[float, str]:
        """(score mm, "") from corresponding marker rows (optical frame, NaN = not seen), or
        (NaN, why not) (module doc's first three fallbacks). The compiled kernel computes it when
        selected (:mod:`hil.geometry.native`), else :func:`score_parts_numpy`."""
        k = native.active()
        if k is not None:
            out = np.empty(3)
            k.target_score(_c64(reference_mm), _c64(live_mm), self.pattern, T_optical_from_image.R, out)
            z, share, resid = out.tolist()
        else:
            z, share, resid, _ = score_parts_numpy(self.pattern, reference_mm, live_mm,
                                                      T_optical_from_image.R)
        return self._judge(z, share, resid)

    def _judge(self, z: float, share: float, resid: float) -> tuple[float, str]:
        if share < MIN_PATTERN_SHARE:
            return math.nan, (f"the seen markers carry {share:.0%} of the 4D CT's breathing pattern "
                              f"(need {MIN_PATTERN_SHARE:.0%})")
        if resid > self.residual_bound_mm:
            return math.nan, (f"the markers do not move as in the 4D CT: residual {resid:.1f} mm beyond "
                              f"{self.residual_bound_mm} mm (patient moved, a cough, a marker swapped)")
        return z, ""

    def held_score(self, z: float) -> tuple[float, str]:
        """(the score the target is modelled at, "" or the note saying it was held): ``z`` (mm)
        itself within the 4D CT's range widened by half of it on each side, else that edge (module
        doc)."""
        span = self.score_max_mm - self.score_min_mm
        lo, hi = self.score_min_mm - _RANGE_MARGIN * span, self.score_max_mm + _RANGE_MARGIN * span
        if lo <= z <= hi:
            return z, ""
        held = min(max(z, lo), hi)
        return held, (f"breathing beyond the 4D CT's range: score {z:.1f} mm (CT {self.score_min_mm:.1f}.."
                      f"{self.score_max_mm:.1f} mm), target held at {held:.1f} mm")

    def steer(self, T_live_from_ref: RigidTransform, reference_mm: FloatArray, live_mm: FloatArray,
              plan: ProcedurePlan, T_optical_from_image: RigidTransform) -> TargetSteer:
        """The estimator's change ``T_live_from_ref`` (optical frame) turned about the moved entry so
        the path points at the modelled target at this pair's score, its rate taken as 0 (module
        doc; :class:`TargetTracker` gives the rate). Never raises: a pair the model cannot vouch for
        keeps the estimator's change and names why in :attr:`TargetSteer.fallback`."""
        z, why = self.score(reference_mm, live_mm, T_optical_from_image)
        if why:
            return TargetSteer(T_live_from_ref, z, 0.0, 0.0, why, source="")
        return self.steer_at(T_live_from_ref, reference_mm, live_mm, plan, T_optical_from_image, z, 0.0)

    def steer_at(self, T_live_from_ref: RigidTransform, reference_mm: FloatArray, live_mm: FloatArray,
                 plan: ProcedurePlan, T_optical_from_image: RigidTransform, z: float,
                 rate_mm_s: float) -> TargetSteer:
        """:meth:`steer` at a score ``z`` (mm) the caller judged, and its rate (mm/s)."""
        turn = self.turn_at(T_live_from_ref, reference_mm, live_mm, plan, T_optical_from_image, z, rate_mm_s)
        if isinstance(turn, str):
            return TargetSteer(T_live_from_ref, z, 0.0, 0.0, turn, source="")
        T = turned_about_entry(T_live_from_ref, turn.rotvec, 1.0, T_optical_from_image, plan.entry_mm)
        return TargetSteer(T, z, turn.shift_mm, turn.deg, limited=turn.limited)

    def turn_at(self, T_live_from_ref: RigidTransform, reference_mm: FloatArray, live_mm: FloatArray,
                plan: ProcedurePlan, T_optical_from_image: RigidTransform, z: float,
                rate_mm_s: float) -> PathTurn | str:
        """The rotation that turns the changed path at the modelled target (module doc "Live"; the
        score and the turn held at their bounds, :attr:`PathTurn.limited` saying which), or why the
        model cannot vouch for it (the breathing pattern's rigid fit refused). The compiled kernel
        computes it when selected and able (it leaves a refused fit to the numpy code, which names
        why), else :func:`turn_numpy`."""
        z_held, limited = self.held_score(z)
        # the target at the held score: ``a`` scaled by z_held / z (z is not 0 when held: the range
        # holds 0), so the markers' displacement beyond the pattern is still taken at ``z``
        a = self.target_per_score if z_held == z else self.target_per_score * (z_held / z)
        k = native.active()
        turn: PathTurn | str | None = None
        if k is not None:
            out = np.empty(5)
            T_oi, T = T_optical_from_image, T_live_from_ref
            if k.target_turn(_c64(reference_mm), _c64(live_mm), self.pattern, T_oi.R, T_oi.t,
                             _c64(plan.entry_mm), _c64(plan.target_mm), a,
                             self.target_per_rate, T.R, T.t, z, rate_mm_s, out) == 0:
                turn = PathTurn(out[:3], float(out[3]), float(out[4]))
        if turn is None:
            turn = turn_numpy(self, T_live_from_ref, reference_mm, live_mm, plan, T_optical_from_image, z,
                              rate_mm_s, z_held)
        if isinstance(turn, str):
            return turn
        return self.bounded(turn, limited)

    def bounded(self, turn: PathTurn, limited: str = "") -> PathTurn:
        """``turn`` held at ``target_model_max_turn_deg`` (:func:`held_turn`)."""
        return held_turn(turn, self.max_turn_deg, limited, "model's")


def held_turn(turn: PathTurn, bound_deg: float, limited: str = "", whose: str = "model's") -> PathTurn:
    """``turn`` held at ``bound_deg`` (about the same axis) when beyond it, its
    :attr:`PathTurn.limited` saying so (the ``whose`` turn) after ``limited`` (what held it
    before)."""
    if turn.deg > bound_deg:
        note = f"the {whose} turn {turn.deg:.1f} deg held at the bound {bound_deg} deg"
        limited = f"{limited}; {note}" if limited else note
        turn = PathTurn(turn.rotvec * (bound_deg / turn.deg), bound_deg, turn.shift_mm)
    return turn._replace(limited=limited) if limited else turn


class PathTurn(NamedTuple):
    """The model's turn of the changed path at one pair.

    Attributes:
        rotvec: the smallest rotation taking the changed planned direction onto the direction from
            the changed entry to the modelled target (axis * angle, rad, optical frame).
        deg: its angle, deg.
        shift_mm: the modelled target's displacement from the plan's, mm.
        limited: which bound held the score or the turn ("" when none did).
    """

    rotvec: FloatArray
    deg: float
    shift_mm: float
    limited: str = ""


def _c64(a: FloatArray) -> FloatArray:
    """``a`` as the compiled kernels take it (float64, C-contiguous; no copy when it already is)."""
    out: FloatArray = np.ascontiguousarray(a, dtype=np.float64)
    return out


def score_parts_numpy(pattern: FloatArray, reference_mm: FloatArray, live_mm: FloatArray,
                      R_optical_from_image: FloatArray) -> tuple[float, float, float, int]:
    """The numpy reference of the compiled ``target_score``: (z mm, share ``|u_seen|^2``, per-marker
    RMS residual of ``d - z u`` mm, seen rows) with ``d_i = R_oi^T (m_i - r_i)`` (module doc);
    z and the residual NaN when no share is seen."""
    ok = np.isfinite(reference_mm).all(axis=1) & np.isfinite(live_mm).all(axis=1)
    u = pattern[ok]
    share = float((u * u).sum())
    seen = int(ok.sum())
    if not share > 0.0:
        return math.nan, share, math.nan, seen
    d = (live_mm[ok] - reference_mm[ok]) @ R_optical_from_image
    z = float((u * d).sum()) / share
    resid = math.sqrt(float(((d - z * u) ** 2).sum()) / seen)
    return z, share, resid, seen


def turn_numpy(model: SurrogateTargetModel, T_live_from_ref: RigidTransform, reference_mm: FloatArray,
               live_mm: FloatArray, plan: ProcedurePlan, T_optical_from_image: RigidTransform, z: float,
               rate_mm_s: float, z_target: float | None = None) -> PathTurn | str:
    """The numpy reference of the compiled ``target_turn`` (:meth:`SurrogateTargetModel.turn_at`
    without the bounds): the turn, or why there is none (no marker seen, a modelled target at the
    entry). ``z_target``: the score the target is modelled at (default ``z``; a held score,
    :meth:`SurrogateTargetModel.held_score`)."""
    R_oi = T_optical_from_image.R
    ok = np.isfinite(reference_mm).all(axis=1) & np.isfinite(live_mm).all(axis=1)
    if not ok.any():
        return "no marker seen: the target model has nothing to steer by"
    # what the markers moved beyond the breathing pattern at this score (a shift on the table,
    # drift) moves the target too: their mean displacement less the pattern's
    other = (live_mm[ok] - reference_mm[ok] - z * (model.pattern[ok] @ R_oi.T)).mean(axis=0)
    entry_ref = T_optical_from_image.apply(plan.entry_mm).reshape(3)
    target_ref = T_optical_from_image.apply(plan.target_mm).reshape(3)
    z_t = z if z_target is None else z_target
    shift_img = z_t * model.target_per_score + rate_mm_s * model.target_per_rate
    target_live = target_ref + R_oi @ shift_img + other
    return _turn_onto(T_live_from_ref, entry_ref, target_ref, target_live, float(np.linalg.norm(shift_img)),
                      "modelled")


def turn_to_target(T_live_from_ref: RigidTransform, plan: ProcedurePlan, T_optical_from_image: RigidTransform,
                   target_live_mm: FloatArray) -> PathTurn | str:
    """The smallest rotation turning the changed planned path so it points from the changed entry
    at ``target_live_mm`` (optical frame, mm: a measured target, :mod:`hil.controller.target_sensor`),
    without a bound (:func:`held_turn` gives one); or why there is none (the target within
    :data:`MIN_PATH_MM` of the entry). :attr:`PathTurn.shift_mm`: the target's displacement
    from the registered plan's, mm. numpy only (a few vector operations)."""
    entry_ref = T_optical_from_image.apply(plan.entry_mm).reshape(3)
    target_ref = T_optical_from_image.apply(plan.target_mm).reshape(3)
    target = np.asarray(target_live_mm, dtype=np.float64).reshape(3)
    shift_mm = math.hypot(*(target - target_ref).tolist())
    return _turn_onto(T_live_from_ref, entry_ref, target_ref, target, shift_mm, "measured")


def _turn_onto(T_live_from_ref: RigidTransform, entry_ref: FloatArray, target_ref: FloatArray,
               target_live: FloatArray, shift_mm: float, kind: str) -> PathTurn | str:
    """The smallest rotation taking the changed planned direction (``entry_ref`` -> ``target_ref``,
    optical at registration, turned by ``T_live_from_ref``) onto the direction from the changed
    entry to ``target_live``; or why there is none (``kind`` names the target in it)."""
    entry_live = T_live_from_ref.apply(entry_ref).reshape(3)
    # plain floats on 3-vectors: a tenth of numpy's per-call cost on the pair's path
    a0, a1, a2 = (T_live_from_ref.R @ (target_ref - entry_ref)).tolist()
    b0, b1, b2 = (target_live - entry_live).tolist()
    n0, n1 = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2), math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    if not (MIN_PATH_MM <= n0 < math.inf and MIN_PATH_MM <= n1 < math.inf):
        return (f"the {kind} target is {n1:.2g} mm from the entry (under {MIN_PATH_MM} mm): "
                "the path has no direction to trust")
    a0, a1, a2, b0, b1, b2 = a0 / n0, a1 / n0, a2 / n0, b0 / n1, b1 / n1, b2 / n1
    c = min(max(a0 * b0 + a1 * b1 + a2 * b2, -1.0), 1.0)
    x, y, z = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    s = math.sqrt(x * x + y * y + z * z)
    angle = math.atan2(s, c)      # exact near 0, where acos(c) loses half the digits
    rotvec = np.zeros(3) if s < 1e-12 else np.array([x, y, z]) * (angle / s)
    return PathTurn(rotvec, math.degrees(angle), shift_mm)


def turned_about_entry(T_live_from_ref: RigidTransform, rotvec: FloatArray, weight: float,
                       T_optical_from_image: RigidTransform, entry_image_mm: FloatArray) -> RigidTransform:
    """``T_live_from_ref`` turned by ``weight * rotvec`` (rad, optical frame) about where it puts
    the entry (``entry_image_mm``, image frame, through ``T_optical_from_image``): the entry's
    estimate is unchanged. Compiled (``turn_about``) when selected.

    Raises:
        GeometryError: a weighted rotation vector that is not finite."""
    k = native.active()
    if k is None:
        entry_ref = T_optical_from_image.apply(entry_image_mm).reshape(3)
        entry_live = T_live_from_ref.apply(entry_ref).reshape(3)
        R = rotvec_to_matrix(weight * rotvec) @ T_live_from_ref.R
        return RigidTransform(R, entry_live - R @ entry_ref)
    R, t = np.empty((3, 3)), np.empty(3)
    try:
        k.turn_about(_c64(rotvec), weight, T_live_from_ref.R, T_live_from_ref.t, T_optical_from_image.R,
                     T_optical_from_image.t, _c64(entry_image_mm), R, t)
    except ValueError as exc:
        raise GeometryError(f"the model's turn: {exc}") from None
    # a Rodrigues rotation times a proper one, every value finite: proper by construction
    return RigidTransform._composed(R, t)


class TargetTracker:
    """The model in the loop (module doc "Live"): each pair's score, its rate from the pairs
    before, and the steered change. The model's turn is faded in and out over
    :data:`TURN_RAMP_S` (a weight from 0 to 1 on the turn's angle) rather than switched: a step
    of a few degrees in the commanded direction would swing the guide 60 mm out faster than the
    correction's rate limits let it follow, and the axis would leave the entry meanwhile. While
    the model cannot vouch for the pairs, the last turn it could vouch for fades out on the
    estimator's change. One per procedure; :meth:`reset` at a new registration. Never raises; not
    thread-safe (the controller's thread)."""

    def __init__(self, model: SurrogateTargetModel, sensor_max_turn_deg: float = 20.0) -> None:
        self.model = model
        #: the bound on a measured target's turn (``target_sensor_max_turn_deg``), deg
        self.sensor_max_turn_deg = sensor_max_turn_deg
        self._last: tuple[int, float] | None = None
        self._t_ns: int | None = None
        #: the score's rate now, mm/s (0 until two judged pairs)
        self.rate_mm_s = 0.0
        #: the share of the model's turn applied now, 0-1
        self.weight = 0.0
        self._turn_rotvec = np.zeros(3)

    def reset(self) -> None:
        self._last, self._t_ns = None, None
        self.rate_mm_s, self.weight = 0.0, 0.0
        self._turn_rotvec = np.zeros(3)

    def steer(self, T_live_from_ref: RigidTransform, reference_mm: FloatArray, live_mm: FloatArray,
              plan: ProcedurePlan, T_optical_from_image: RigidTransform, exposure_t_ns: int,
              measured: TargetReading | None = None) -> TargetSteer:
        """:meth:`SurrogateTargetModel.steer` with the score's rate and the faded turn at this pair's
        exposure (controller clock, ns). ``measured``: the target sensor's reading for the pair
        (None: no sensor configured); when it has a target, the path points at it (its own bound,
        :attr:`sensor_max_turn_deg`; the same fade) and the model is judged only to keep its score's
        rate going."""
        m = self.model
        step = 0.0 if self._t_ns is None else max(0.0, (exposure_t_ns - self._t_ns) * 1e-9) / TURN_RAMP_S
        self._t_ns = exposure_t_ns
        z, why = m.score(reference_mm, live_mm, T_optical_from_image)
        if not why:
            self._update_rate(z, exposure_t_ns)
        turn: PathTurn | str = why
        source = ""
        if measured is not None and measured.target_optical_mm is not None:
            turn = turn_to_target(T_live_from_ref, plan, T_optical_from_image, measured.target_optical_mm)
            if not isinstance(turn, str):
                turn = held_turn(turn, self.sensor_max_turn_deg, "", "sensor's")
            source = "sensor"
        elif not why:
            turn = m.turn_at(T_live_from_ref, reference_mm, live_mm, plan, T_optical_from_image, z,
                             self.rate_mm_s)
            source = "model"
        if isinstance(turn, str):
            why = turn
            self._last, self.rate_mm_s = None, 0.0
            self.weight = max(0.0, self.weight - step)
        else:
            self.weight = min(1.0, self.weight + step)
            self._turn_rotvec = turn.rotvec
        T = turned_about_entry(T_live_from_ref, self._turn_rotvec, self.weight, T_optical_from_image,
                               plan.entry_mm)
        turn_deg = math.degrees(self.weight * math.hypot(*self._turn_rotvec.tolist()))
        sensor_why_not = "" if measured is None else measured.why_not
        if isinstance(turn, str):
            return TargetSteer(T, z, 0.0, turn_deg, why, source="", sensor_why_not=sensor_why_not)
        return TargetSteer(T, z, turn.shift_mm, turn_deg, limited=turn.limited, source=source,
                           sensor_why_not=sensor_why_not)

    def _update_rate(self, z: float, exposure_t_ns: int) -> None:
        last = self._last
        dt_s = None if last is None else (exposure_t_ns - last[0]) * 1e-9
        if last is None or dt_s is None or not 0.0 < dt_s <= MAX_RATE_GAP_S:
            self.rate_mm_s = 0.0
        else:
            self.rate_mm_s += RATE_GAIN * ((z - last[1]) / dt_s - self.rate_mm_s)
        bound = _RATE_MARGIN * self.model.max_rate_mm_s
        self.rate_mm_s = min(max(self.rate_mm_s, -bound), bound)
        self._last = (exposure_t_ns, z)


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
    if plan.phases_period_s is not None and len(plan.phases) >= MIN_PHASES_FOR_RATE - 1:
        # the registered phase (score 0, target 0) is bin 0 of the cycle; central differences
        zc = np.concatenate([[0.0], z])
        Yc = np.vstack([np.zeros(3), Y])
        dt = plan.phases_period_s / len(zc)
        rate = (np.roll(zc, -1) - np.roll(zc, 1)) / (2.0 * dt)
        coef, *_ = np.linalg.lstsq(np.column_stack([zc, rate]), Yc, rcond=None)
        a, b = coef[0], coef[1]
        resid = math.sqrt(float(((Yc - np.outer(zc, a) - np.outer(rate, b)) ** 2).sum(axis=1).mean()))
        max_rate = float(np.abs(rate).max())
    else:
        a = (z @ Y) / float(z @ z)
        b = np.zeros(3)
        resid = math.sqrt(float(((Y - np.outer(z, a)) ** 2).sum(axis=1).mean()))
        max_rate = math.inf
    explained = float(sv[0] ** 2 / (sv**2).sum())
    return SurrogateTargetModel(
        pattern=u.reshape(-1, 3), target_per_score=a, target_per_rate=b, max_rate_mm_s=max_rate,
        score_min_mm=float(min(z.min(), 0.0)),
        score_max_mm=float(max(z.max(), 0.0)), fit_residual_mm=resid, explained=explained,
        residual_bound_mm=residual_bound_mm, max_turn_deg=max_turn_deg)
