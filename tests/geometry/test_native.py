"""The compiled per-pair geometry (hil/geometry/_native.c) against its numpy reference: Horn's
registration with unit or given weights and the greedy marker tracking agree to rounding (tracking:
exactly), every input the checks refuse goes the numpy way and raises its typed error, and a bad
buffer is a TypeError / ValueError naming the argument."""

from __future__ import annotations

import os
import re
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.compiled import CompiledKernel
from hil.controller.registration import track, track_numpy
from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry import native
from hil.geometry.registration import register_horn, register_horn_numpy
from hil.geometry.transform import RigidTransform

from .strategies import point_sets, rigid_transforms


@pytest.fixture
def compiled(compiled_geometry: Any) -> Any:
    """The compiled code selected for the test (tests/conftest.py)."""
    return compiled_geometry


def test_the_compiled_geometry_is_built_and_selected_by_default() -> None:
    assert native.is_built(), native.native_status()
    numpy_asked = os.environ.get("HIL_GEOMETRY_KERNEL", "").lower() == "numpy"
    assert native.native_status() == ("numpy (selected)" if numpy_asked else "compiled kernel")


def test_a_kernel_that_is_not_built_runs_numpy_and_says_why() -> None:
    k = CompiledKernel("hil.geometry._no_such_kernel", "HIL_NO_SUCH_KERNEL")
    assert k.active() is None
    assert k.use(True) is False
    assert k.active() is None
    assert k.status().startswith("numpy (the compiled kernel is not built: No module named")


@settings(max_examples=300, deadline=None)
@given(point_sets(min_points=3, max_points=20), rigid_transforms(), st.floats(0.0, 3.0),
       st.integers(0, 2**32 - 1))
def test_horn_agrees_with_numpy(moving: np.ndarray, T: RigidTransform, noise_mm: float, seed: int) -> None:
    assert native.is_built(), native.native_status()
    previous = native.use_native(True)
    try:
        fixed = T.apply(moving) + np.random.default_rng(seed).normal(scale=noise_mm, size=moving.shape)
        got = register_horn(fixed, moving)
    finally:
        native.use_native(previous)
    want = register_horn_numpy(fixed, moving)
    assert got.method == want.method == "horn"
    np.testing.assert_allclose(got.T_fixed_from_moving.R, want.T_fixed_from_moving.R, rtol=0, atol=1e-11)
    np.testing.assert_allclose(got.T_fixed_from_moving.t, want.T_fixed_from_moving.t, rtol=0, atol=1e-8)
    np.testing.assert_allclose(got.residuals_mm, want.residuals_mm, rtol=0, atol=1e-8)
    assert got.fre_rms_mm == pytest.approx(want.fre_rms_mm, abs=1e-9)
    assert not got.residuals_mm.flags.writeable
    assert not got.T_fixed_from_moving.R.flags.writeable


def test_refused_inputs_raise_the_numpy_codes_errors(compiled: object) -> None:
    """Everything the checks refuse is decided by the numpy code: same class, same message."""
    good = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    cases: list[tuple[Any, Any, type[Exception], str]] = [
        (good[:2], good[:2], GeometryError, "fixed: 2 point(s) given, at least 3 are needed"),
        (good, good[:3], GeometryError, "fixed has 4 points but moving has 3"),
        (np.where(good == 10, np.nan, good), good, GeometryError, "fixed contains NaN or infinite values"),
        (good, np.where(good == 10, np.inf, good), GeometryError, "moving contains NaN or infinite values"),
        (np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2], [5, 5, 5]]), good, DegenerateConfigurationError,
         "fixed: points are collinear"),
        (good, np.zeros((4, 3)), DegenerateConfigurationError, "moving: all points coincide"),
        (good, np.ones((4, 2)), GeometryError, "moving must have shape (N, 3), got (4, 2)"),
    ]
    for fixed, moving, err, message in cases:
        with pytest.raises(err) as exc_info:
            register_horn(fixed, moving)
        assert str(exc_info.value).startswith(message), str(exc_info.value)
    reg = register_horn(good.astype(np.float32), good)   # float32 and lists: the numpy code
    assert reg.fre_rms_mm == register_horn_numpy(good, good).fre_rms_mm
    assert register_horn(good.tolist(), good.tolist()).fre_rms_mm == pytest.approx(0.0, abs=1e-12)


@settings(max_examples=300, deadline=None)
@given(point_sets(min_points=3, max_points=20), rigid_transforms(), st.floats(0.0, 3.0),
       st.integers(0, 2**32 - 1), st.floats(0.0, 0.5))
def test_weighted_horn_agrees_with_numpy(moving: np.ndarray, T: RigidTransform, noise_mm: float, seed: int,
                                         zero_share: float) -> None:
    """The change estimators' weighted fit (hil.controller.change_estimate): weights over the
    three decades it keeps (a weight below 1e-3 of the largest is dropped there: a wider span
    makes the rotation about the heavy pairs rest on pairs that hardly count, an ill-conditioned
    eigenproblem where two solvers may part well beyond rounding), some zero (those pairs take no
    part, not even in the configuration check)."""
    rng = np.random.default_rng(seed)
    fixed = T.apply(moving) + rng.normal(scale=noise_mm, size=moving.shape)
    w = 10.0 ** rng.uniform(-3, 0, size=len(moving))
    w[rng.random(len(moving)) < zero_share] = 0.0
    try:
        want = register_horn_numpy(fixed, moving, w)
    except GeometryError as exc:   # too few positive weights, or a degenerate weighted set
        previous = native.use_native(True)
        try:
            with pytest.raises(type(exc), match="^" + re.escape(str(exc)) + "$"):
                register_horn(fixed, moving, w)
        finally:
            native.use_native(previous)
        return
    previous = native.use_native(True)
    try:
        got = register_horn(fixed, moving, w)
        k = native.active()
        assert k is not None
        R, t, res = np.empty((3, 3)), np.empty(3), np.empty(len(moving))
        assert k.horn(fixed, moving, R, t, res, w) >= 0.0   # the compiled code did it
    finally:
        native.use_native(previous)
    # looser than unit weights' 1e-11: three pairs nearly on a line with weights 1e3 apart leave
    # a small eigenvalue gap (20,000 random cases: worst 1.5e-9 in R, 2.6e-8 mm in t)
    np.testing.assert_allclose(got.T_fixed_from_moving.R, want.T_fixed_from_moving.R, rtol=0, atol=1e-8)
    np.testing.assert_allclose(got.T_fixed_from_moving.t, want.T_fixed_from_moving.t, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.residuals_mm, want.residuals_mm, rtol=0, atol=1e-6)
    assert got.fre_rms_mm == pytest.approx(want.fre_rms_mm, abs=1e-8)


def test_refused_weights_raise_the_numpy_codes_errors(compiled: object) -> None:
    good = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [20, 0, 0]])
    cases: list[tuple[Any, type[Exception], str]] = [
        (np.array([1.0, 1.0, -1.0, 1.0, 1.0]), GeometryError, "weights must be finite and non-negative"),
        (np.array([1.0, np.nan, 1.0, 1.0, 1.0]), GeometryError, "weights must be finite and non-negative"),
        (np.array([1.0, 1.0, 0.0, 0.0, 0.0]), GeometryError, "at least 3 point pairs need a positive weight"),
        (np.ones(4), GeometryError, "4 weights given for 5 point pairs"),
        (np.array([1.0, 1.0, 0.0, 0.0, 1.0]), DegenerateConfigurationError, "fixed: points are collinear"),
    ]
    for w, err, message in cases:
        with pytest.raises(err) as exc_info:
            register_horn(good, good, w)
        assert str(exc_info.value).startswith(message), str(exc_info.value)
    # a zero weight's pair takes no part: its point may sit anywhere, even on another's
    on_top = good.copy()
    on_top[4] = on_top[0]
    reg = register_horn(on_top, good, np.array([1.0, 1.0, 1.0, 1.0, 0.0]))
    assert reg.fre_rms_mm == pytest.approx(0.0, abs=1e-9)
    assert reg.residuals_mm[4] == pytest.approx(np.linalg.norm(good[4] - good[0]), abs=1e-9)
    # weights that are not an (N,) float64 array: the numpy code
    assert register_horn(good, good, [1, 1, 1, 1, 1]).fre_rms_mm == pytest.approx(0.0, abs=1e-12)


@st.composite
def tracking_cases(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, float]:
    """Points and predictions (some NaN rows), predictions near, off or between the points."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    m = draw(st.integers(0, 30))
    k = draw(st.integers(1, 12))
    points = rng.uniform(-100, 100, size=(m, 3))
    predicted = rng.uniform(-100, 100, size=(k, 3))
    for i in range(min(k, m)):
        if rng.random() < 0.7:   # near a point, sometimes two predictions near the same one
            predicted[i] = points[rng.integers(0, m)] + rng.normal(scale=2.0, size=3)
    predicted[rng.random(k) < 0.2] = np.nan
    return points, predicted, draw(st.floats(0.5, 20.0))


@settings(max_examples=300, deadline=None)
@given(tracking_cases())
def test_track_agrees_exactly_with_numpy(case: tuple[np.ndarray, np.ndarray, float]) -> None:
    points, predicted, tol = case
    assert native.is_built(), native.native_status()
    previous = native.use_native(True)
    try:
        got = track(points, predicted, tol)
    finally:
        native.use_native(previous)
    assert np.array_equal(got, track_numpy(points, predicted, tol), equal_nan=True)


def test_track_exact_assignment(compiled: object) -> None:
    """The closest pair first, each point once, nothing beyond the tolerance."""
    points = np.array([[0.0, 0, 0], [10, 0, 0], [30, 0, 0]])
    predicted = np.array([[1.0, 0, 0], [0.5, 0, 0], [np.nan, 0, 0], [24.0, 0, 0], [9, 0, 0]])
    got = track(points, predicted, 5.0)
    want = np.array([[np.nan] * 3, [0.0, 0, 0], [np.nan] * 3, [np.nan] * 3, [10.0, 0, 0]])
    assert np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(track(np.zeros((0, 3)), predicted, 5.0), np.full((5, 3), np.nan), equal_nan=True)


def test_track_beyond_the_compiled_size_runs_numpy(compiled: object) -> None:
    rng = np.random.default_rng(3)
    points = rng.uniform(-100, 100, size=(700, 3))
    predicted = points[:8] + 0.1
    assert np.array_equal(track(points, predicted, 1.0), points[:8])


def test_bad_buffers_name_the_argument(compiled: Any) -> None:
    k = compiled
    f = np.zeros((4, 3))
    R, t, res = np.empty((3, 3)), np.empty(3), np.empty(4)
    with pytest.raises(TypeError, match="fixed: expected float64 items"):
        k.horn(f.astype(np.float32), f, R, t, res)
    with pytest.raises(ValueError, match="moving: dimension 0 has length 3, expected 4"):
        k.horn(f, f[:3].copy(), R, t, res)
    with pytest.raises(TypeError, match="R: expected a writable"):
        k.horn(f, f, b"x" * 72, t, res)
    with pytest.raises(ValueError, match="residuals: dimension 0 has length 3, expected 4"):
        k.horn(f, f, R, t, np.empty(3))
    with pytest.raises(TypeError, match="points: expected a readable C-contiguous float64 array"):
        k.track(np.zeros((6, 3))[::2], f, 1.0, np.empty((4, 3)))
    with pytest.raises(ValueError, match="out: dimension 0 has length 3, expected 4"):
        k.track(f, f, 1.0, np.empty((3, 3)))


def test_more_rows_than_the_compiled_arrays_hold_go_the_numpy_way(compiled: object) -> None:
    """Thousands of predicted rows and no point (K * M = 0): not the compiled code's arrays."""
    predicted = np.zeros((5000, 3))
    assert np.array_equal(track(np.zeros((0, 3)), predicted, 1.0), np.full((5000, 3), np.nan), equal_nan=True)
    points = np.arange(15000.0).reshape(5000, 3)
    assert np.array_equal(track(points, points[:1] + 0.1, 1.0), points[:1])


@pytest.mark.parametrize("scale", [1e200, 1.5e9])
def test_coordinates_beyond_any_rig_are_a_typed_error_either_way(compiled: object, scale: float) -> None:
    """Coordinates beyond MAX_COORDINATE_MM (1e9 mm; at 1e200 the squares overflow): the compiled
    code declines, and both paths raise the same GeometryError naming the set."""
    moving = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * scale
    fixed = np.column_stack([-moving[:, 1], moving[:, 0], moving[:, 2]]) / scale
    for fn in (register_horn, register_horn_numpy):
        with pytest.raises(GeometryError, match=r"moving has a coordinate of .* beyond the 1e\+09 mm"):
            fn(fixed, moving)


def test_coordinates_at_the_bound_register(compiled: object) -> None:
    moving = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * 1e9
    fixed = np.column_stack([-moving[:, 1], moving[:, 0], moving[:, 2]])   # 90 degrees about z
    got, ref = register_horn(fixed, moving), register_horn_numpy(fixed, moving)
    assert got.fre_rms_mm < 1e-3
    np.testing.assert_allclose(got.T_fixed_from_moving.R, ref.T_fixed_from_moving.R, rtol=0, atol=1e-12)
