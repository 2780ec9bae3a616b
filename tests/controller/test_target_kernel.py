"""The surrogate target model's compiled per-pair steering (hil/geometry/_native.c ``target_score``,
``target_turn``, ``turn_about``) against its numpy reference (hil/controller/target_model.py
``score_parts_numpy``, ``turn_numpy`` and the numpy branch of ``turned_about_entry``): the same
score, turn and steered change to rounding in any registration, with markers unseen, collinear or
many; what the kernel declines (no marker seen) goes the numpy way with the numpy code's words; a
bad buffer is a TypeError / ValueError naming the argument."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.controller.plan_file import ProcedurePlan
from hil.controller.target_model import (
    SurrogateTargetModel,
    TargetSteer,
    TargetTracker,
    score_parts_numpy,
    turn_numpy,
    turned_about_entry,
)
from hil.errors import GeometryError
from hil.geometry import native
from hil.geometry.transform import RigidTransform
from tests.geometry.strategies import rigid_transforms

ENTRY = np.array([5.0, -10.0, 0.0])
TARGET = np.array([15.0, -2.0, -75.0])


@pytest.fixture
def numpy_only() -> Iterator[None]:
    """The numpy code selected for the test, the previous selection restored after."""
    previous = native.use_native(False)
    yield
    native.use_native(previous)


def _kernel() -> Any:
    """The compiled module (built: tools/test builds it), whatever is selected."""
    previous = native.use_native(True)
    k = native.active()
    native.use_native(previous)
    assert k is not None, native.native_status()
    return k


def _both(call: Any) -> tuple[Any, Any]:
    """``call()`` with the compiled code selected, then with the numpy code."""
    assert native.is_built(), native.native_status()
    previous = native.use_native(True)
    try:
        got = call()
        native.use_native(False)
        want = call()
    finally:
        native.use_native(previous)
    return got, want


def _case(n: int, seed: int) -> tuple[SurrogateTargetModel, ProcedurePlan, np.ndarray, np.ndarray]:
    """A model of n fiducials on a curved patch (image frame), its plan, the fiducials and a
    breathing displacement pattern per mm of score with 0.3 mm of non-model noise."""
    rng = np.random.default_rng(seed)
    fid = rng.uniform(-80.0, 80.0, size=(n, 3))
    fid[:, 2] = 0.2 * fid[:, 0] + 0.002 * fid[:, 1] ** 2
    pattern = np.column_stack([0.1 * rng.normal(size=n), 0.2 * rng.normal(size=n),
                               1.0 + 0.3 * rng.normal(size=n)])
    pattern /= np.linalg.norm(pattern)
    model = SurrogateTargetModel(
        pattern=pattern, target_per_score=rng.normal(0.0, 0.5, 3), target_per_rate=rng.normal(0.0, 0.1, 3),
        max_rate_mm_s=20.0, score_min_mm=0.0, score_max_mm=16.0, fit_residual_mm=0.5, explained=0.9,
        residual_bound_mm=2.0, max_turn_deg=45.0)
    plan = ProcedurePlan(fid, ENTRY, TARGET, "plan.json", ())
    return model, plan, fid, rng.normal(0.0, 0.3, size=(n, 3))


@settings(max_examples=200, deadline=None)
@given(n=st.integers(4, 12), seed=st.integers(0, 2**32 - 1), T_oi=rigid_transforms(500.0),
       change=rigid_transforms(20.0), z=st.floats(-20.0, 40.0), rate=st.floats(-30.0, 30.0),
       unseen=st.sets(st.integers(0, 11), max_size=4))
def test_score_turn_and_steered_change_agree_with_numpy(
        n: int, seed: int, T_oi: RigidTransform, change: RigidTransform, z: float, rate: float,
        unseen: set[int]) -> None:
    model, plan, fid, noise = _case(n, seed)
    ref = T_oi.apply(fid)
    live = T_oi.apply(fid + z * model.pattern + noise)
    drop = sorted(i for i in unseen if i < n)[: n - 3]
    live[drop] = np.nan
    if drop:
        ref[drop[0]] = np.nan                      # a reference row unknown too: also not seen

    got, want = _both(lambda: model.score(ref, live, T_oi))
    assert got[1] == want[1]
    assert got[0] == pytest.approx(want[0], rel=1e-12, abs=1e-12) or math.isnan(got[0]) == math.isnan(want[0])
    parts = score_parts_numpy(model.pattern, ref, live, T_oi.R)
    out = np.empty(3)
    assert _kernel().target_score(ref, live, model.pattern, T_oi.R, out) == parts[3]
    np.testing.assert_allclose(out, parts[:3], rtol=1e-12, atol=1e-12)

    t_got, t_want = _both(lambda: model.turn_at(change, ref, live, plan, T_oi, z, rate))
    assert isinstance(t_got, type(t_want))
    if isinstance(t_got, str):
        assert t_got == t_want
    else:
        np.testing.assert_allclose(t_got.rotvec, t_want.rotvec, rtol=0, atol=1e-10)
        assert t_got.deg == pytest.approx(t_want.deg, abs=1e-6)
        assert t_got.shift_mm == pytest.approx(t_want.shift_mm, rel=1e-12, abs=1e-12)
        # the held score by a scaled slope in the kernel, by the held score in numpy (0..16 widened: -8..24)
        assert t_got.limited.startswith("breathing beyond") == (not -8.0 <= z <= 24.0)

    s_got, s_want = _both(lambda: model.steer_at(change, ref, live, plan, T_oi, z, rate))
    _same_steer(s_got, s_want)


@settings(max_examples=100, deadline=None)
@given(change=rigid_transforms(50.0), T_oi=rigid_transforms(500.0), weight=st.floats(0.0, 1.0),
       rotvec=st.tuples(*[st.floats(-0.3, 0.3)] * 3))
def test_the_turn_about_the_entry_agrees_with_numpy(change: RigidTransform, T_oi: RigidTransform,
                                                   weight: float, rotvec: tuple[float, float, float]) -> None:
    rv = np.array(rotvec)
    got, want = _both(lambda: turned_about_entry(change, rv, weight, T_oi, ENTRY))
    np.testing.assert_allclose(got.R, want.R, rtol=0, atol=1e-14)
    np.testing.assert_allclose(got.t, want.t, rtol=0, atol=1e-9)
    entry_ref = T_oi.apply(ENTRY)
    np.testing.assert_allclose(got.apply(entry_ref), change.apply(entry_ref), rtol=0, atol=1e-9)


def test_a_breathing_sequence_steers_the_same_either_way() -> None:
    """The tracker over 60 pairs of breathing with a cough and an occlusion in it: every pair's
    steered change, score, rate and turn agree (the rate and the fade carry state from pair to
    pair, so a difference would grow)."""
    model, plan, fid, noise = _case(6, 3)
    T_oi = RigidTransform.from_rotvec([0.1, -0.2, 0.3], [100.0, -50.0, 800.0])
    ref = T_oi.apply(fid)

    def run() -> list[TargetSteer]:
        tracker, out = TargetTracker(model), []
        for k in range(60):
            z = 8.0 + 7.0 * math.sin(2 * math.pi * k / 30.0)
            live = T_oi.apply(fid + z * model.pattern + 0.3 * noise)
            if 20 <= k < 24:
                live = live + np.array([0.0, 9.0, 0.0])   # a cough: the markers leave the pattern
            if k in (40, 41):
                live[[0, 1, 2, 3]] = np.nan                 # most markers hidden
            change = RigidTransform.from_translation([0.01 * k, 0.0, 0.02 * z])
            out.append(tracker.steer(change, ref, live, plan, T_oi, k * 33_333_333))
        return out

    got, want = _both(run)
    assert sum(bool(s.fallback) for s in want) >= 4
    for g, w in zip(got, want, strict=True):
        _same_steer(g, w)


def test_collinear_seen_markers_still_steer_the_same_either_way() -> None:
    """Three seen markers on a line carry the score, and the model needs no rigid fit of them
    (what they moved beyond the pattern is their mean): the kernel and the numpy code steer alike."""
    model, plan, fid, _ = _case(6, 5)
    fid[:3] = np.array([[0.0, 0.0, 0.0], [20.0, 10.0, 5.0], [40.0, 20.0, 10.0]])
    seen_part = model.pattern[:3] / float(np.linalg.norm(model.pattern[:3]))
    model = _with_pattern(model, np.vstack([seen_part, np.zeros((3, 3))]))   # all of it on the line
    live = fid + 4.0 * model.pattern
    live[3:] = np.nan
    z, why = model.score(fid, live, RigidTransform.identity())
    assert (why, z) == ("", pytest.approx(4.0, abs=1e-12))
    got, want = _both(lambda: model.turn_at(RigidTransform.identity(), fid, live, plan,
                                            RigidTransform.identity(), 4.0, 0.0))
    assert not isinstance(want, str)
    assert not isinstance(got, str)
    np.testing.assert_allclose(got.rotvec, want.rotvec, atol=1e-12)
    assert got.deg == pytest.approx(want.deg, abs=1e-9)
    assert want.deg > 0.1


def test_no_seen_marker_gets_the_numpy_codes_words_either_way() -> None:
    model, plan, fid, _ = _case(6, 5)
    live = np.full_like(fid, np.nan)
    got, want = _both(lambda: model.turn_at(RigidTransform.identity(), fid, live, plan,
                                            RigidTransform.identity(), 4.0, 0.0))
    assert want == "no marker seen: the target model has nothing to steer by"
    assert got == want


def test_a_modelled_target_at_the_entry_is_a_fallback_not_an_error() -> None:
    """A model that puts the target where the change puts the entry leaves the path no direction
    (without the check, rounding's direction would be steered at): the kernel declines, the numpy
    code names why, and the tracker keeps the estimator's change."""
    _, plan, fid, _ = _case(6, 4)
    up = np.tile([0.0, 0.0, 1.0 / math.sqrt(6.0)], (6, 1))      # breathing = a pure translation
    change = RigidTransform.from_translation(5.0 * up[0])          # = breathing's own rigid part
    model = SurrogateTargetModel(up, (ENTRY + change.t - TARGET) / 5.0, np.zeros(3), 20.0, 0.0, 16.0, 0.5,
                                 0.9, 2.0, 45.0)
    live = fid + 5.0 * up
    steers = _both(lambda: TargetTracker(model).steer(change, fid, live, plan, RigidTransform.identity(), 0))
    for steer in steers:
        assert steer.fallback.startswith("the modelled target is ")
        assert steer.fallback.endswith(" mm from the entry (under 1.0 mm): the path has no direction "
                                       "to trust")
        assert steer.T_live_from_ref.is_close(change, atol_mm=1e-12, atol_rad=1e-15)


def test_many_rows_steer_the_same_either_way() -> None:
    """The turn holds no per-row buffer: 70 seen markers are the kernel's too."""
    model, plan, fid, noise = _case(70, 7)
    live = fid + 6.0 * model.pattern + noise
    change = RigidTransform.from_translation([0.5, 0.0, 1.0])
    out = np.empty(5)
    assert _kernel().target_turn(fid, live, model.pattern, np.eye(3), np.zeros(3), ENTRY, TARGET,
                                 model.target_per_score, model.target_per_rate, change.R, change.t, 6.0, 0.0,
                                 out) == 0
    got, want = _both(lambda: model.steer_at(change, fid, live, plan, RigidTransform.identity(), 6.0, 0.0))
    assert want.fallback == ""
    _same_steer(got, want)


def test_bad_buffers_name_the_argument(compiled_geometry: Any) -> None:
    k = compiled_geometry
    model, _, fid, _ = _case(6, 1)
    with pytest.raises(ValueError, match="target_score: argument 2 has 5 rows, the reference 6"):
        k.target_score(fid, fid[:5].copy(), model.pattern, np.eye(3), np.empty(3))
    with pytest.raises(TypeError, match="R_oi: expected a readable C-contiguous float64 array"):
        k.target_score(fid, fid, model.pattern, [[1, 0, 0], [0, 1, 0], [0, 0, 1]], np.empty(3))
    with pytest.raises(ValueError, match="out: dimension 0 has length 4, expected 5"):
        k.target_turn(fid, fid, model.pattern, np.eye(3), np.zeros(3), ENTRY, TARGET, np.zeros(3),
                      np.zeros(3), np.eye(3), np.zeros(3), 1.0, 0.0, np.empty(4))
    with pytest.raises(TypeError, match="R_out: expected a writable C-contiguous float64 array"):
        k.turn_about(np.zeros(3), 1.0, np.eye(3), np.zeros(3), np.eye(3), np.zeros(3), ENTRY,
                     np.eye(3).T.copy().T, np.empty(3))


def test_a_rotation_that_is_not_finite_is_a_geometry_error_either_way(compiled_geometry: Any) -> None:
    rv = np.array([0.1, math.nan, 0.0])
    for on in (True, False):
        previous = native.use_native(on)
        try:
            with pytest.raises(GeometryError):
                turned_about_entry(RigidTransform.identity(), rv, 1.0, RigidTransform.identity(), ENTRY)
        finally:
            native.use_native(previous)


def test_the_numpy_reference_runs_without_the_kernel(numpy_only: None) -> None:
    """With the numpy code selected the model still steers (the reference the compiled code is
    held to): the exact pattern's score, and no turn at the registered phase."""
    model, plan, fid, _ = _case(6, 2)
    assert native.active() is None
    steer = model.steer(RigidTransform.identity(), fid, fid + 5.0 * model.pattern, plan,
                        RigidTransform.identity())
    assert steer.fallback == ""
    assert steer.score_mm == pytest.approx(5.0, abs=1e-12)
    still = turn_numpy(model, RigidTransform.identity(), fid, fid.copy(), plan, RigidTransform.identity(),
                       0.0, 0.0)
    assert not isinstance(still, str)
    assert (still.rotvec.tolist(), still.deg, still.shift_mm) == ([0.0, 0.0, 0.0], 0.0, 0.0)


def _with_pattern(model: SurrogateTargetModel, pattern: np.ndarray) -> SurrogateTargetModel:
    m = model
    return SurrogateTargetModel(pattern, m.target_per_score, m.target_per_rate, m.max_rate_mm_s,
                                m.score_min_mm, m.score_max_mm, m.fit_residual_mm, m.explained,
                                m.residual_bound_mm, m.max_turn_deg)


def _same_steer(got: TargetSteer, want: TargetSteer) -> None:
    assert got.fallback == want.fallback
    # the same bounds held (the turn's figure in the note may round apart)
    assert [x[:20] for x in got.limited.split("; ")] == [x[:20] for x in want.limited.split("; ")]
    np.testing.assert_allclose(got.T_live_from_ref.R, want.T_live_from_ref.R, rtol=0, atol=1e-10)
    np.testing.assert_allclose(got.T_live_from_ref.t, want.T_live_from_ref.t, rtol=0, atol=1e-7)
    assert (math.isnan(got.score_mm) and math.isnan(want.score_mm)) or \
        got.score_mm == pytest.approx(want.score_mm, rel=1e-12, abs=1e-12)
    assert got.turn_deg == pytest.approx(want.turn_deg, abs=1e-6)
    assert got.target_shift_mm == pytest.approx(want.target_shift_mm, rel=1e-12, abs=1e-12)
