"""The ``pattern`` change estimator (hil/controller/entry_pattern.py): on a body whose skin moves by
two breathing patterns, as its 4D CT shows, the entry lands exactly where the body puts it, for any
registration and any mix of the patterns (hypothesis), with a marker unseen and under a small rigid
motion; too few markers fall back and say why; a plan that cannot carry the model is named."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.controller.change_estimate import estimate_change
from hil.controller.entry_pattern import (
    RIDGE_GRID_MM2,
    EntryRows,
    entry_coefficients,
    entry_numpy,
    fit_entry_pattern,
)
from hil.controller.plan_file import PlanPhase, ProcedurePlan
from hil.errors import InputFileError
from hil.geometry import native
from hil.geometry.transform import RigidTransform
from tests.geometry.strategies import rigid_transforms

SIGMA_MM = 60.0
#: six skin markers and the entry (image frame, mm) on a gently curved skin
MARKERS_MM = np.array([[-60.0, -50.0, 4.0], [0.0, -70.0, 2.0], [55.0, -40.0, 5.0],
                       [-50.0, 45.0, 3.0], [10.0, 60.0, 1.0], [65.0, 35.0, 6.0]])
ENTRY_MM = np.array([5.0, -10.0, 0.0])
TARGET_MM = np.array([15.0, -2.0, -75.0])
#: the two patterns' displacement per unit score at the markers and at the entry (mm): the
#: thoracic one mostly anterior, the abdominal one anterior and inferior, varying over the skin
_RNG = np.random.default_rng(41)
PATTERN_MM = np.stack([np.array([0.0, 0.3, 1.0]) + 0.3 * _RNG.normal(size=(7, 3)),
                       np.array([0.0, -0.6, 0.8]) + 0.3 * _RNG.normal(size=(7, 3))], axis=2)   # (7, 3, 2)


def _body(scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The markers (6, 3) and the entry (3,) at these two scores (image frame)."""
    moved = np.vstack([MARKERS_MM, ENTRY_MM]) + PATTERN_MM @ scores
    return moved[:6], moved[6]


def _plan(with_entry: bool = True, phases: int = 6) -> ProcedurePlan:
    """A 4D CT over one breath: the two patterns out of phase (thoracic leads)."""
    out = []
    for k in range(1, phases + 1):
        a = 2.0 * np.pi * k / (phases + 1)
        markers, entry = _body(np.array([6.0 * (1 - np.cos(a)), 4.0 * (1 - np.cos(a - 0.8))]))
        out.append(PlanPhase(markers, TARGET_MM + 0.5 * k, entry if with_entry else None))
    return ProcedurePlan(MARKERS_MM, ENTRY_MM, TARGET_MM, "ct.json", tuple(out))


def _rows(T_reg: RigidTransform) -> EntryRows:
    return fit_entry_pattern(_plan()).registered(T_reg, T_reg.apply(MARKERS_MM), T_reg.apply(ENTRY_MM))


@settings(max_examples=100, deadline=None)
@given(T_reg=rigid_transforms(500.0), s1=st.floats(-3.0, 15.0), s2=st.floats(-3.0, 12.0),
       unseen=st.sampled_from([None, 0, 2, 5]))
def test_the_entry_lands_where_the_body_puts_it(T_reg: RigidTransform, s1: float, s2: float,
                                                unseen: int | None) -> None:
    markers, entry = _body(np.array([s1, s2]))
    live = T_reg.apply(markers)
    if unseen is not None:
        live[unseen] = np.nan
    fit = estimate_change(T_reg.apply(MARKERS_MM), live, T_reg.apply(ENTRY_MM), "pattern", SIGMA_MM,
                          _rows(T_reg))
    assert fit is not None
    assert (fit.estimator, fit.fallback) == ("pattern", "")
    np.testing.assert_allclose(fit.T_live_from_ref.apply(T_reg.apply(ENTRY_MM)), T_reg.apply(entry),
                               rtol=0, atol=1e-8)


def test_a_small_rigid_motion_on_top_is_followed() -> None:
    T_reg = RigidTransform.from_rotvec([3.1, 0.1, 0.0], [60.0, 0.0, 1000.0])
    markers, entry = _body(np.array([8.0, 5.0]))
    # the patient shifted 3 mm and turned 2 deg about a point 200 mm away since registration
    M = RigidTransform.from_rotvec([0.0, np.radians(2.0), 0.0], [3.0, -1.0, 0.5])
    pivot = T_reg.apply(np.array([0.0, 200.0, 0.0]))
    M = RigidTransform.from_translation(pivot) @ M @ RigidTransform.from_translation(-pivot)
    fit = estimate_change(T_reg.apply(MARKERS_MM), M.apply(T_reg.apply(markers)), T_reg.apply(ENTRY_MM),
                          "pattern", SIGMA_MM, _rows(T_reg))
    assert fit is not None
    assert fit.estimator == "pattern"
    err = np.linalg.norm(fit.T_live_from_ref.apply(T_reg.apply(ENTRY_MM)) - M.apply(T_reg.apply(entry)))
    assert err < 0.01      # the second solve takes the turn's cross term with the breathing


def test_local_tps_misses_what_the_pattern_knows() -> None:
    """The same body, the spline's answer: the patterns vary over the skin, the spline cannot."""
    T_reg = RigidTransform.identity()
    markers, entry = _body(np.array([10.0, 8.0]))
    fit = estimate_change(MARKERS_MM, markers, ENTRY_MM, "local-tps", SIGMA_MM)
    assert fit is not None
    assert np.linalg.norm(fit.T_live_from_ref.apply(ENTRY_MM) - entry) > 0.5
    rows = _rows(T_reg)
    fit = estimate_change(MARKERS_MM, markers, ENTRY_MM, "pattern", SIGMA_MM, rows)
    assert fit is not None
    assert np.linalg.norm(fit.T_live_from_ref.apply(ENTRY_MM) - entry) < 1e-9


def test_three_markers_fall_back_and_say_why() -> None:
    markers, _ = _body(np.array([5.0, 2.0]))
    live = markers.copy()
    live[[0, 3, 5]] = np.nan
    fit = estimate_change(MARKERS_MM, live, ENTRY_MM, "pattern", SIGMA_MM, _rows(RigidTransform.identity()))
    assert fit is not None
    assert fit.estimator == "weighted"
    assert fit.fallback == ("breathing pattern: 3 markers seen: the breathing pattern needs 4; "
                            "3 markers seen: the local spline needs 4")


def test_without_rows_the_spline_stands_in() -> None:
    markers, _ = _body(np.array([5.0, 2.0]))
    fit = estimate_change(MARKERS_MM, markers, ENTRY_MM, "pattern", SIGMA_MM, None)
    assert fit is not None
    assert (fit.estimator, fit.fallback) == ("local-tps", "no breathing pattern for this registration")


def test_the_solver_is_kept_per_seen_set() -> None:
    rows = _rows(RigidTransform.identity())
    seen = np.ones(6, dtype=np.bool_)
    first = rows.solver(seen)
    assert rows.solver(seen.copy()) is first
    assert (first.P6.shape, first.E.shape, first.Q.shape) == ((6, 18), (3, 18), (18, 18))
    assert [a.flags.writeable for a in (first.P6, first.E, first.Q)] == [False, False, False]


def _both(rows: EntryRows, seen: np.ndarray, ref: np.ndarray, live: np.ndarray,
          entry: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The compiled ``pattern_entry``'s (4,) out and :func:`entry_numpy`'s for the same solve."""
    assert native.is_built(), native.native_status()
    previous = native.use_native(True)
    try:
        k = native.active()
        assert k is not None
        sol = rows.solver(seen)
        out = np.full(4, np.nan)
        assert k.pattern_entry(sol.P6, sol.E, sol.Q, ref, live, entry, out) == 0
    finally:
        native.use_native(previous)
    return out, entry_numpy(sol, ref, live, entry)


@settings(max_examples=150, deadline=None)
@given(T_reg=rigid_transforms(500.0), M=rigid_transforms(20.0), s1=st.floats(-3.0, 15.0),
       s2=st.floats(-3.0, 12.0), unseen=st.sampled_from([None, 1, 4]), seed=st.integers(0, 2**32 - 1))
def test_the_compiled_entry_agrees_with_numpy(T_reg: RigidTransform, M: RigidTransform, s1: float, s2: float,
                                              unseen: int | None, seed: int) -> None:
    markers, _ = _body(np.array([s1, s2]))
    ref, entry = T_reg.apply(MARKERS_MM), T_reg.apply(ENTRY_MM)
    live = M.apply(T_reg.apply(markers)) + np.random.default_rng(seed).normal(0.0, 0.3, size=(6, 3))
    seen = np.ones(6, dtype=np.bool_)
    if unseen is not None:
        seen[unseen] = False
    got, want = _both(_rows(T_reg), seen, np.ascontiguousarray(ref[seen]), np.ascontiguousarray(live[seen]),
                      entry)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


@pytest.mark.parametrize(("case", "error", "message"), [
    ("int", TypeError, "reference: expected float64 items"),
    ("rows", ValueError, "pattern_entry: live has 5 rows, the reference 6"),
    ("columns", ValueError, "pattern_entry: P6, E and Q must have 3N = 18 columns"),
])
def test_a_bad_buffer_is_named(case: str, error: type[Exception], message: str,
                               compiled_geometry: Any) -> None:
    k = compiled_geometry
    sol = _rows(RigidTransform.identity()).solver(np.ones(6, dtype=np.bool_))
    ref, live, out = MARKERS_MM.copy(), MARKERS_MM.copy(), np.empty(4)
    P6 = sol.P6
    if case == "int":
        ref = ref.astype(np.int64)
    elif case == "rows":
        live = live[:5].copy()
    else:
        P6 = np.ascontiguousarray(P6[:, :15])
    with pytest.raises(error, match=message):
        k.pattern_entry(P6, sol.E, sol.Q, ref, live, ENTRY_MM.copy(), out)


def test_the_fit_holds_both_patterns() -> None:
    model = fit_entry_pattern(_plan())
    assert model.patterns.shape == (6, 3, 2)
    assert model.fit_residual_mm < 1e-9
    assert model.explained == pytest.approx(1.0)


@pytest.mark.parametrize(("plan", "message"), [
    (_plan(with_entry=False), "ct.json: the pattern estimator needs the entry at every phase of the 4D CT "
                              "('entry_mm' in each of the plan's 'phases')"),
    (_plan(phases=1), "ct.json: the pattern estimator needs a 4D CT: >= 2 breathing phases in the plan's "
                      "'phases', it has 1"),
    (ProcedurePlan(MARKERS_MM, ENTRY_MM, TARGET_MM, "ct.json",
                   (PlanPhase(MARKERS_MM, TARGET_MM, ENTRY_MM),) * 3),
     "ct.json: phases: the fiducials do not move over the 4D CT: no breathing pattern to correlate the "
     "entry with"),
])
def test_a_plan_that_cannot_carry_the_model_is_named(plan: ProcedurePlan, message: str) -> None:
    with pytest.raises(InputFileError) as info:
        fit_entry_pattern(plan)
    assert str(info.value) == message


def test_markers_that_leave_the_patterns_fall_back_and_say_by_how_much() -> None:
    """A cough: two markers jump 8 mm in a way no pattern of the 4D CT moves them."""
    markers, _ = _body(np.array([5.0, 2.0]))
    live = markers.copy()
    live[0] += [0.0, 0.0, 8.0]
    live[1] += [8.0, 0.0, 0.0]
    fit = estimate_change(MARKERS_MM, live, ENTRY_MM, "pattern", SIGMA_MM, _rows(RigidTransform.identity()))
    assert fit is not None
    assert fit.estimator == "local-tps"
    assert fit.fallback.startswith("breathing pattern: the markers do not move as the 4D CT's breathing "
                                   "patterns (per-marker RMS residual ")
    assert fit.fallback.endswith(" mm beyond 2.0 mm)")


@pytest.mark.parametrize("compiled", [True, False])
def test_an_entry_that_is_not_finite_is_refused_not_composed(compiled: bool) -> None:
    """The estimator composes the pattern's entry without the checked constructor, so the model
    must never hand it a NaN: it says so instead, with either kernel."""
    rows = _rows(RigidTransform.identity())
    markers, _ = _body(np.array([5.0, 2.0]))
    was = native.use_native(compiled)
    try:
        with pytest.raises(ValueError, match=r"^the breathing patterns put the entry at a value that is "
                                             r"not finite$"):
            rows.entry_mm(np.ones(6, dtype=np.bool_), MARKERS_MM, markers, np.array([np.nan, 0.0, 0.0]))
    finally:
        native.use_native(was)


def _left_out_error(Z: np.ndarray, E: np.ndarray, ridge: float) -> float:
    """Leave-one-out by refitting without each phase (what PRESS computes in closed form)."""
    penalty = np.diag([0.0] + [1.0] * (Z.shape[1] - 1))
    total = 0.0
    for k in range(len(Z)):
        keep = np.arange(len(Z)) != k
        coef = np.linalg.solve(Z[keep].T @ Z[keep] + ridge * penalty, Z[keep].T @ E[keep])
        total += float(((E[k] - Z[k] @ coef) ** 2).sum())
    return total


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), noise_mm=st.floats(0.0, 1.0))
def test_the_ridge_is_the_one_leaving_out_a_phase_predicts_best(seed: int, noise_mm: float) -> None:
    """The closed-form choice is the brute-force leave-one-out's, on a CT of 9 phases whose second
    pattern's scores are small (the case the ridge is for)."""
    rng = np.random.default_rng(seed)
    Z = np.column_stack([rng.uniform(0.0, 20.0, 9), rng.normal(0.0, 1.0, 9)])
    E = Z @ rng.normal(0.0, 1.0, (2, 3)) + rng.normal(0.0, noise_mm, (9, 3))
    coef, ridge = entry_coefficients(Z, E)
    errors = {g: _left_out_error(Z, E, g) for g in RIDGE_GRID_MM2}
    assert errors[ridge] == pytest.approx(min(errors.values()), rel=1e-9, abs=1e-12)
    penalty = np.diag([0.0, ridge])
    np.testing.assert_allclose(coef, np.linalg.solve(Z.T @ Z + penalty, Z.T @ E), rtol=1e-9, atol=1e-12)


def test_an_exact_ct_keeps_no_ridge() -> None:
    assert fit_entry_pattern(_plan()).ridge_mm2 == 0.0
