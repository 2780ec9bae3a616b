"""Where the patient breathed at registration: the plan's path at the reference state, not the CT's.

Why (issue 41): registration waits for a still breath-hold and registers the plan's fiducials (the
4D CT's registered phase, end-exhale) onto the averaged skin markers with Horn's method. A hold is
seldom exactly at that phase: the baseline wanders, and a hold ends a little above or below the
CT's exhale. The markers at registration then carry some breathing. Horn's fit takes part of it
for a rigid motion, and maps the plan's entry and target where the CT's phase would put them, not
where they are. Every change the controller measures afterwards is relative to that reference
state, so the offset stays with the path for the whole procedure. On the simulated patient with
every other error removed (``configs/sim_patient.toml`` without noise, drift or rig errors, an
exact 4D CT), the ``pattern`` entry at each pair was off by a constant 0.2 mm on seed 1 and 0.6 mm
on seed 2; the surrogate target model's score is zero at the reference too, so its target was off
by the target's motion per score times the reference's score.

**The solve** (when the plan's 4D CT carries a breathing model: the ``pattern`` estimator's
:class:`~hil.controller.entry_pattern.EntryPattern` or the surrogate target model): the reference
markers ``r_i`` against the plan's fiducials mapped by Horn's fit ``T`` (rotation ``R``) are, by
least squares over the seen markers,

    ``r_i - T f_i = R U_i z + t + w x (T f_i - T e)``

with ``U`` the 4D CT's breathing patterns (the entry model's, else the target model's one),
``z`` their scores at registration and ``t``, ``w`` the small rigid motion Horn's fit left. Then,
at the reference state (optical frame):

- the entry: ``T' e + R' C z`` (``C`` the entry model's displacement per score, ``T'`` Horn's fit
  moved by ``t``, ``w``, rotation ``R'``); without the entry model, ``T e`` (Horn's: its rigid fit
  already follows the skin around the entry);
- the target: ``T' g + R' a z_a`` with ``a`` the target model's displacement per score and
  ``z_a = u . (U z)`` its score of the breathing the solve found (the hold is still: no rate
  term); without the target model the planned direction is kept (the rigid direction).

The rigid motion is linearised about Horn's fit; the solve is repeated about ``T'``
(Gauss-Newton, :data:`_ITERATIONS` steps), so the linearisation costs no accuracy.

The registration the controller uses is the rigid transform that puts the plan's entry on the
entry at the reference state and turns the plan's direction onto the direction to the target
there (the smallest rotation after Horn's). Horn's transform, its FRE and the residuals stay in the
registration record. A set of markers that cannot tell breathing from a rigid motion (too few
seen, a basis not well conditioned), a reference the model leaves more than the pattern's
residual bound off, or an entry or target moved more than :data:`MAX_SHIFT_MM`, keeps Horn's
registration and says why (:attr:`RegistrationBreathing.kept_rigid_because`).

What it assumes: the model's (the patient breathes with the 4D CT's patterns, the entry and the
target move linearly with their scores). It cannot see the breath-hold reproducibility of the
target (a target that ends a hold elsewhere than the skin says).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from hil.controller.entry_pattern import MIN_CONDITION, MIN_MARKERS, EntryPattern, cross_matrices
from hil.controller.plan_file import ProcedurePlan
from hil.controller.registration import PatientRegistration
from hil.controller.target_model import SurrogateTargetModel
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

FloatArray = NDArray[np.float64]

__all__ = ["MAX_SHIFT_MM", "RegistrationBreathing", "at_breathing_state"]

#: an entry or target the solve would move further than this from Horn's keeps Horn's, mm (the
#: breathing a still breath-hold leaves is a few mm of skin at most)
MAX_SHIFT_MM = 5.0
#: Gauss-Newton steps of the solve (the first is Horn's fit's small leftover motion, linearised)
_ITERATIONS = 4


@dataclass(frozen=True)
class RegistrationBreathing:
    """The breathing state at registration (module doc).

    Attributes:
        T_optical_from_image_rigid: Horn's registration of the fiducials.
        scores_mm: the 4D CT patterns' scores at registration (empty when not solved).
        entry_shift_mm: how far the entry at the reference state is from Horn's mapping, mm.
        target_shift_mm: the same for the target, mm.
        turn_deg: the direction's turn from Horn's, deg.
        residual_mm: per-marker RMS the solve leaves, mm (NaN when not solved).
        kept_rigid_because: why Horn's registration was kept ("" when corrected).
    """

    T_optical_from_image_rigid: RigidTransform
    scores_mm: tuple[float, ...] = ()
    entry_shift_mm: float = 0.0
    target_shift_mm: float = 0.0
    turn_deg: float = 0.0
    residual_mm: float = math.nan
    kept_rigid_because: str = ""

    def record(self) -> dict[str, object]:
        """The ``registration_done`` record's ``breathing`` field."""
        return {"scores_mm": list(self.scores_mm), "entry_shift_mm": self.entry_shift_mm,
                "target_shift_mm": self.target_shift_mm, "turn_deg": self.turn_deg,
                "residual_mm": None if math.isnan(self.residual_mm) else self.residual_mm,
                "kept_rigid_because": self.kept_rigid_because,
                "T_optical_from_image_rigid": self.T_optical_from_image_rigid}


def at_breathing_state(preg: PatientRegistration, plan: ProcedurePlan, entry_pattern: EntryPattern | None,
                       target_model: SurrogateTargetModel | None,
                       residual_bound_mm: float) -> PatientRegistration:
    """``preg`` with its registration moved to the breathing state at registration (module doc) and
    :attr:`PatientRegistration.breathing` saying how; ``preg`` itself without a breathing model.
    Never raises: what the solve cannot vouch for keeps Horn's registration and says why."""
    if entry_pattern is not None:
        patterns = entry_pattern.patterns
    elif target_model is not None:
        patterns = np.asarray(target_model.pattern, dtype=np.float64)[:, :, None]
    else:
        return preg
    T = preg.T_optical_from_image
    solved = _solve(T, preg.reference_optical_mm, plan, patterns)
    if isinstance(solved, str):
        return replace(preg, breathing=RegistrationBreathing(T, kept_rigid_because=solved))
    T_rig, z, resid = solved
    if not resid <= residual_bound_mm:
        why = (f"the reference markers do not sit on the 4D CT's breathing patterns: residual "
               f"{resid:.2f} mm beyond {residual_bound_mm} mm")
        return replace(preg, breathing=RegistrationBreathing(T, tuple(z.tolist()), residual_mm=resid,
                                                             kept_rigid_because=why))
    entry_h, target_h = T.apply(np.vstack([plan.entry_mm, plan.target_mm]))
    entry_r, target_r = T_rig.apply(np.vstack([plan.entry_mm, plan.target_mm]))
    entry = entry_h.copy()
    if entry_pattern is not None:
        entry = entry_r + T_rig.R @ (entry_pattern.entry_per_score @ z)
    if target_model is not None:
        z_a = float(np.einsum("nk,nkr,r->", target_model.pattern, patterns, z))
        target = target_r + T_rig.R @ (z_a * target_model.target_per_score)
    else:
        target = target_h + (entry - entry_h)
    d_entry, d_target = float(np.linalg.norm(entry - entry_h)), float(np.linalg.norm(target - target_h))
    if not max(d_entry, d_target) <= MAX_SHIFT_MM:
        why = (f"the breathing found at registration would move the entry {d_entry:.1f} mm and the target "
               f"{d_target:.1f} mm (bound {MAX_SHIFT_MM} mm)")
        return replace(preg, breathing=RegistrationBreathing(T, tuple(z.tolist()), d_entry, d_target,
                                                             residual_mm=resid, kept_rigid_because=why))
    rotvec = _turn(target_h - entry_h, target - entry)
    R = rotvec_to_matrix(rotvec) @ T.R
    T_new = RigidTransform(R, entry - R @ plan.entry_mm)
    turn_deg = math.degrees(float(np.linalg.norm(rotvec)))
    how = RegistrationBreathing(T, tuple(z.tolist()), d_entry, d_target, turn_deg, resid)
    return replace(preg, T_optical_from_image=T_new, breathing=how)


def _solve(T: RigidTransform, reference_mm: FloatArray, plan: ProcedurePlan,
           patterns: FloatArray) -> tuple[RigidTransform, FloatArray, float] | str:
    """(the rigid registration without the breathing, the scores ``z`` (r,), the per-marker RMS
    residual mm) of the module doc's least squares, or why it cannot be trusted. The small rigid
    motion is linearised; :data:`_ITERATIONS` Gauss-Newton steps apply it (on the test body 3 mm
    of score off: the entry 0.02 mm off after one, 2e-4 after two, 5e-9 after four)."""
    ok = np.isfinite(reference_mm).all(axis=1)
    n = int(ok.sum())
    if n < MIN_MARKERS:
        return f"{n} markers at registration: telling breathing from a rigid motion needs {MIN_MARKERS}"
    r = patterns.shape[2]
    z, resid = np.zeros(r), math.nan
    for _ in range(_ITERATIONS):
        mapped = T.apply(plan.fiducials_mm)[ok]
        entry = T.apply(plan.entry_mm).reshape(3)
        basis = np.zeros((n, 3, r + 6))
        basis[:, :, :r] = np.einsum("ij,njr->nir", T.R, patterns[ok])
        basis[:, :, r:r + 3] = np.eye(3)
        basis[:, :, r + 3:] = cross_matrices(mapped - entry)         # w x d
        B = basis.reshape(3 * n, r + 6)
        scale = np.linalg.norm(B, axis=0)
        if not (scale > 0.0).all():
            return "the markers at registration do not show every breathing pattern"
        sv = np.linalg.svd(B / scale, compute_uv=False)
        if not sv[-1] >= MIN_CONDITION * sv[0]:
            return "the markers at registration cannot tell the breathing patterns from a rigid motion"
        y = (reference_mm[ok] - mapped).reshape(-1)
        p = np.asarray(np.linalg.lstsq(B, y, rcond=None)[0], dtype=np.float64)
        left = y - B @ p
        z, resid = p[:r], math.sqrt(float(left @ left) / n)
        R = rotvec_to_matrix(p[r + 3:])
        T = RigidTransform(R, entry + p[r:r + 3] - R @ entry) @ T   # turned about the entry, shifted
    return T, z, resid


def _turn(d0: FloatArray, d1: FloatArray) -> FloatArray:
    """The smallest rotation (rotation vector, rad) taking the direction of ``d0`` onto ``d1``."""
    a, b = d0 / np.linalg.norm(d0), d1 / np.linalg.norm(d1)
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        return np.zeros(3)
    out: FloatArray = axis / s * math.atan2(s, float(a @ b))
    return out
