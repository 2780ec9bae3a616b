"""The breathing state at registration (hil/controller/registration_breathing.py): a patient
registered a little off the 4D CT's registered phase gets the plan's entry and target where they
are at the reference state, for any registration and any score (hypothesis); without a model the
registration is Horn's; what the solve cannot vouch for keeps Horn's and says why."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.controller.entry_pattern import fit_entry_pattern
from hil.controller.plan_file import PlanPhase, ProcedurePlan
from hil.controller.registration import PatientRegistration
from hil.controller.registration_breathing import MAX_SHIFT_MM, at_breathing_state
from hil.controller.target_model import fit_target_model
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform
from tests.geometry.strategies import rigid_transforms

#: six skin markers, the entry and the target (image frame, mm) on a gently curved skin
MARKERS_MM = np.array([[-60.0, -50.0, 4.0], [0.0, -70.0, 2.0], [55.0, -40.0, 5.0],
                       [-50.0, 45.0, 3.0], [10.0, 60.0, 1.0], [65.0, 35.0, 6.0]])
ENTRY_MM = np.array([5.0, -10.0, 0.0])
TARGET_MM = np.array([15.0, -2.0, -75.0])
_RNG = np.random.default_rng(7)
#: one breathing pattern: displacement per unit score at the markers and the entry (mm), varying
#: over the skin (so that a rigid fit takes part of it), and the target's own per unit score
PATTERN_MM = np.array([0.0, 0.3, 1.0]) + 0.3 * _RNG.normal(size=(7, 3))
TARGET_PER_SCORE_MM = np.array([0.0, -1.1, 0.3])
#: where the patient was registered (optical frame)
T_REG = RigidTransform.from_rotvec([3.1, 0.1, 0.0], [60.0, 0.0, 1000.0])


def _body(score: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Markers (6, 3), entry and target at ``score`` (image frame)."""
    moved = np.vstack([MARKERS_MM, ENTRY_MM]) + score * PATTERN_MM
    return moved[:6], moved[6], TARGET_MM + score * TARGET_PER_SCORE_MM


def _plan(phases: int = 6) -> ProcedurePlan:
    out = []
    for k in range(1, phases + 1):
        markers, entry, target = _body(8.0 * (1 - np.cos(2.0 * np.pi * k / (phases + 1))))
        out.append(PlanPhase(markers, target, entry))
    return ProcedurePlan(MARKERS_MM, ENTRY_MM, TARGET_MM, "ct.json", tuple(out))


def _registered(reference_mm: np.ndarray) -> PatientRegistration:
    """Horn's registration of the plan's fiducials onto ``reference_mm`` (NaN rows unseen)."""
    ok = np.isfinite(reference_mm).all(axis=1)
    reg = register_horn(reference_mm[ok], MARKERS_MM[ok])
    return PatientRegistration(reg.T_fixed_from_moving, reg.fre_rms_mm, 0.5, reference_mm, int(ok.sum()), 10)


def _direction(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    out: np.ndarray = d / np.linalg.norm(d)
    return out


@settings(max_examples=60, deadline=None)
@given(T_reg=rigid_transforms(500.0), score=st.floats(-2.5, 3.0), unseen=st.sampled_from([None, 1, 4]))
def test_the_path_lands_where_the_body_was_at_registration(T_reg: RigidTransform, score: float,
                                                            unseen: int | None) -> None:
    markers, entry, target = _body(score)
    reference = T_reg.apply(markers)
    if unseen is not None:
        reference[unseen] = np.nan
    plan = _plan()
    preg = at_breathing_state(_registered(reference), plan, fit_entry_pattern(plan),
                              fit_target_model(plan, 2.0, 10.0), 2.0)
    T = preg.T_optical_from_image
    np.testing.assert_allclose(T.apply(ENTRY_MM), T_reg.apply(entry), rtol=0, atol=1e-7)
    np.testing.assert_allclose(_direction(T.apply(ENTRY_MM), T.apply(TARGET_MM)),
                               _direction(T_reg.apply(entry), T_reg.apply(target)), rtol=0, atol=1e-9)
    assert preg.breathing is not None
    assert preg.breathing.kept_rigid_because == ""
    assert preg.breathing.residual_mm < 1e-7


def test_horns_fit_alone_misses_and_the_record_says_by_how_much() -> None:
    markers, entry, _target = _body(-2.0)
    plan = _plan()
    horn = _registered(T_REG.apply(markers))
    preg = at_breathing_state(horn, plan, fit_entry_pattern(plan), fit_target_model(plan, 2.0, 10.0), 2.0)
    assert preg.breathing is not None
    miss_entry = float(np.linalg.norm(horn.T_optical_from_image.apply(ENTRY_MM) - T_REG.apply(entry)))
    assert miss_entry > 0.5                                   # what the correction is for
    assert preg.breathing.entry_shift_mm == pytest.approx(miss_entry, abs=1e-7)
    assert preg.breathing.T_optical_from_image_rigid is horn.T_optical_from_image
    assert preg.breathing.turn_deg > 0.5
    assert (preg.fre_rms_mm, preg.reference_optical_mm) == (horn.fre_rms_mm, horn.reference_optical_mm)
    record = preg.breathing.record()
    assert record["kept_rigid_because"] == ""
    assert record["T_optical_from_image_rigid"] is horn.T_optical_from_image


def test_the_entry_model_alone_keeps_the_planned_direction() -> None:
    markers, entry, _target = _body(2.5)
    plan = _plan()
    horn = _registered(T_REG.apply(markers))
    preg = at_breathing_state(horn, plan, fit_entry_pattern(plan), None, 2.0)
    T, H = preg.T_optical_from_image, horn.T_optical_from_image
    np.testing.assert_allclose(T.apply(ENTRY_MM), T_REG.apply(entry), rtol=0, atol=1e-7)
    np.testing.assert_allclose(T.R, H.R, rtol=0, atol=1e-12)
    assert preg.breathing is not None
    assert preg.breathing.turn_deg == 0.0


def test_the_target_model_alone_keeps_horns_entry() -> None:
    markers, _entry, target = _body(2.5)
    plan = _plan()
    horn = _registered(T_REG.apply(markers))
    preg = at_breathing_state(horn, plan, None, fit_target_model(plan, 2.0, 10.0), 2.0)
    T, H = preg.T_optical_from_image, horn.T_optical_from_image
    np.testing.assert_allclose(T.apply(ENTRY_MM), H.apply(ENTRY_MM), rtol=0, atol=1e-9)
    # Horn's entry is not the true one, so the direction is to the true target from Horn's entry
    np.testing.assert_allclose(_direction(T.apply(ENTRY_MM), T.apply(TARGET_MM)),
                               _direction(H.apply(ENTRY_MM), T_REG.apply(target)), rtol=0, atol=2e-3)


def test_without_a_breathing_model_the_registration_is_horns() -> None:
    horn = _registered(T_REG.apply(MARKERS_MM))
    assert at_breathing_state(horn, _plan(), None, None, 2.0) is horn


def _kept(preg: PatientRegistration, horn: PatientRegistration) -> str:
    assert preg.T_optical_from_image is horn.T_optical_from_image
    assert preg.breathing is not None
    return preg.breathing.kept_rigid_because


def test_too_few_markers_keep_horns_and_say_why() -> None:
    markers, _entry, _target = _body(2.0)
    reference = T_REG.apply(markers)
    reference[[0, 3, 5]] = np.nan
    horn = _registered(reference)
    plan = _plan()
    why = _kept(at_breathing_state(horn, plan, fit_entry_pattern(plan), None, 2.0), horn)
    assert why == "3 markers at registration: telling breathing from a rigid motion needs 4"


def test_markers_off_the_patterns_keep_horns_and_say_why() -> None:
    markers, _entry, _target = _body(1.0)
    off = markers + np.array([[4.0, 0.0, 0.0], [0.0, -4.0, 0.0], [0.0, 0.0, 4.0],
                              [-4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, -4.0]])
    horn = _registered(T_REG.apply(off))
    plan = _plan()
    why = _kept(at_breathing_state(horn, plan, fit_entry_pattern(plan), None, 2.0), horn)
    assert why.startswith("the reference markers do not sit on the 4D CT's breathing patterns: residual ")
    assert why.endswith(" mm beyond 2.0 mm")


def test_a_shift_beyond_the_bound_keeps_horns_and_says_why() -> None:
    markers, entry, _target = _body(40.0)
    horn = _registered(T_REG.apply(markers))
    plan = _plan()
    horn_miss_mm = float(np.linalg.norm(horn.T_optical_from_image.apply(ENTRY_MM) - T_REG.apply(entry)))
    assert horn_miss_mm > MAX_SHIFT_MM
    why = _kept(at_breathing_state(horn, plan, fit_entry_pattern(plan), None, 2.0), horn)
    assert why.startswith("the breathing found at registration would move the entry ")
    assert why.endswith(f"(bound {MAX_SHIFT_MM} mm)")
