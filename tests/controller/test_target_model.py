"""The surrogate target model (hil/controller/target_model.py): its fit to a 4D CT, the live score
in any registration, the steered change (entry kept, path through the modelled target), each
fallback with its reason, and the refusals of a plan that cannot carry it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.controller.plan_file import PlanPhase, ProcedurePlan
from hil.controller.target_model import SurrogateTargetModel, fit_target_model
from hil.errors import InputFileError
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform
from tests.geometry.strategies import rigid_transforms

FIDUCIALS = np.array([[40.0, 0.0, 0.0], [-30.0, 25.0, 2.0], [0.0, -45.0, -3.0], [55.0, 50.0, -6.0],
                      [-50.0, -30.0, -10.0], [10.0, 70.0, -12.0]])
ENTRY = np.array([5.0, -10.0, 0.0])
TARGET = np.array([15.0, -2.0, -75.0])
#: the skin's breathing pattern per mm of score (mostly anterior, varying over the skin), not unit
PATTERN = np.array([[0.0, 0.1, 1.0], [0.1, 0.0, 0.6], [0.0, 0.2, 1.2], [0.0, 0.0, 0.4],
                    [0.2, 0.1, 0.9], [0.0, 0.3, 0.5]])
UNIT = PATTERN / np.linalg.norm(PATTERN)
#: the target's displacement per mm of score: superior-inferior, a little anterior
A_TRUE = np.array([0.0, -0.65, 0.1])
SCORES = np.array([2.0, 6.0, 12.0, 16.0, 12.0, 6.0, 2.0])


def _plan(scores: np.ndarray = SCORES, target_per_score: np.ndarray = A_TRUE) -> ProcedurePlan:
    phases = tuple(PlanPhase(FIDUCIALS + z * UNIT, TARGET + z * target_per_score) for z in scores)
    return ProcedurePlan(FIDUCIALS, ENTRY, TARGET, "plan.json", phases)


def _model(**kw: float) -> SurrogateTargetModel:
    return fit_target_model(_plan(), kw.get("residual", 2.0), kw.get("turn", 10.0))


def test_the_fit_recovers_an_exact_4d_ct() -> None:
    m = _model()
    np.testing.assert_allclose(m.pattern, UNIT, atol=1e-12)          # inhale positive
    np.testing.assert_allclose(m.target_per_score, A_TRUE, atol=1e-12)
    assert m.score_min_mm == 0.0
    assert m.score_max_mm == pytest.approx(16.0, abs=1e-9)
    assert m.fit_residual_mm == pytest.approx(0.0, abs=1e-9)
    assert m.explained == pytest.approx(1.0, abs=1e-12)


def test_the_fit_reports_what_a_lagging_target_leaves() -> None:
    lagged = ProcedurePlan(FIDUCIALS, ENTRY, TARGET, "plan.json", tuple(
        PlanPhase(FIDUCIALS + z * UNIT, TARGET + z * A_TRUE + np.array([0.0, 0.0, (-1.0) ** k]))
        for k, z in enumerate(SCORES)))
    m = fit_target_model(lagged, 2.0, 10.0)
    # the +-1 mm alternation is orthogonal to these scores (sum of z * (-1)^k is 0): the line
    # follows none of it, and the slope is unchanged
    assert m.fit_residual_mm == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(m.target_per_score, A_TRUE, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(T_oi=rigid_transforms(max_translation_mm=500.0), z=st.floats(0.0, 18.0), shift=st.booleans())
def test_the_score_is_the_same_in_any_registration(T_oi: RigidTransform, z: float, shift: bool) -> None:
    m = _model()
    ref = T_oi.apply(FIDUCIALS)
    live = T_oi.apply(FIDUCIALS + z * UNIT)
    if shift:                                      # a marker not seen: the others still tell
        live[2] = np.nan
    got, why = m.score(ref, live, T_oi.R.T)
    assert why == ""
    assert got == pytest.approx(z, abs=1e-9)


@settings(max_examples=60, deadline=None)
@given(T_oi=rigid_transforms(max_translation_mm=500.0), z=st.floats(0.0, 18.0),
       shift=st.tuples(*[st.floats(-1.5, 1.5)] * 3))
def test_the_steered_change_keeps_the_entry_and_aims_at_the_modelled_target(
        T_oi: RigidTransform, z: float, shift: tuple[float, float, float]) -> None:
    """The change is breathing's own rigid part (what a rigid fit of the markers gives) after a
    small shift of the patient: the entry stays where the change puts it; the path points from
    there at the plan's target moved by the model's ``z a`` and by the shift."""
    m = _model(turn=45.0)
    ref = T_oi.apply(FIDUCIALS)
    live = T_oi.apply(FIDUCIALS + z * UNIT)
    E = np.asarray(shift)
    change = RigidTransform.from_translation(E) @ register_horn(live, ref).T_fixed_from_moving
    steer = m.steer(change, ref, live, _plan(), T_oi)
    assert steer.fallback == ""
    entry_ref = T_oi.apply(ENTRY).reshape(3)
    entry_live = change.apply(entry_ref).reshape(3)
    np.testing.assert_allclose(steer.T_live_from_ref.apply(entry_ref).reshape(3), entry_live, atol=1e-9)
    want = T_oi.apply(TARGET + z * A_TRUE).reshape(3) + E - entry_live
    path = steer.T_live_from_ref.R @ (T_oi.apply(TARGET).reshape(3) - entry_ref)
    assert float(np.linalg.norm(np.cross(path / np.linalg.norm(path), want / np.linalg.norm(want)))) < 1e-9
    assert float(path @ want) > 0
    assert steer.target_shift_mm == pytest.approx(z * float(np.linalg.norm(A_TRUE)), abs=1e-9)


def test_at_the_registered_phase_nothing_turns() -> None:
    m = _model()
    T = RigidTransform.from_translation(np.array([0.3, 0.0, -0.2]))
    steer = m.steer(T, FIDUCIALS, FIDUCIALS.copy(), _plan(), RigidTransform.identity())
    assert steer.fallback == ""
    assert steer.turn_deg == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(steer.T_live_from_ref.as_matrix(), T.as_matrix(), atol=1e-9)


@pytest.mark.parametrize(("case", "reason"), [
    ("few", "the seen markers carry 4% of the 4D CT's breathing pattern (need 25%)"),
    ("shifted", "the markers do not move as in the 4D CT: residual 5.0 mm beyond 2.0 mm (patient moved, "
                "a cough, a marker swapped)"),
    ("deep", "breathing beyond the 4D CT's range: score 30.0 mm outside 0.0..16.0 mm"),
    ("turn", "the model would turn the path 5.8 deg (bound 5.0 deg)"),
])
def test_a_pair_the_model_cannot_vouch_for_keeps_the_rigid_direction(case: str, reason: str) -> None:
    m = _model(turn=5.0)
    live = FIDUCIALS + {"few": 8.0, "shifted": 0.0, "deep": 30.0, "turn": 16.0}[case] * UNIT
    if case == "few":
        live[[0, 1, 2, 4, 5]] = np.nan             # only the fourth, which barely moves
    if case == "shifted":
        live = live + np.array([0.0, 5.0, 0.0])    # the patient slid 5 mm on the table
    T = RigidTransform.from_translation(np.array([0.0, 0.0, 1.0]))
    steer = m.steer(T, FIDUCIALS, live, _plan(), RigidTransform.identity())
    assert steer.fallback == reason
    assert steer.T_live_from_ref is T
    assert (steer.turn_deg, steer.target_shift_mm) == (0.0, 0.0)
    assert math.isnan(steer.score_mm) == (case != "turn")


def test_a_plan_without_a_4d_ct_is_refused() -> None:
    bare = ProcedurePlan(FIDUCIALS, ENTRY, TARGET, "plans/p.json")
    with pytest.raises(InputFileError, match=r"plans/p.json: the surrogate target model needs a 4D CT: >= 2 "
                                             r"breathing phases in the plan's 'phases', it has 0"):
        fit_target_model(bare, 2.0, 10.0)


def test_a_4d_ct_whose_skin_does_not_move_is_refused() -> None:
    still = _plan(scores=np.array([0.2, 0.4, 0.3]))
    with pytest.raises(InputFileError,
                       match=r"phases: the fiducials move 0.40 mm over the 4D CT \(< 1.0 mm\)"):
        fit_target_model(still, 2.0, 10.0)
