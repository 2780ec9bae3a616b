"""The projective correction of triangulated points (hil.geometry.projective)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hil.errors import GeometryError
from hil.geometry.projective import ProjectiveCorrection, apply_homography, warp_matrix

CENTER = np.array([60.0, 120.0, 860.0])

small_s = st.floats(-0.01, 0.01, allow_nan=False)
small_q = st.floats(-2e-5, 2e-5, allow_nan=False)
params = st.tuples(small_s, small_s, small_s, small_s, small_s, small_s, small_q, small_q, small_q)
points = arrays(np.float64, (7, 3), elements=st.floats(-300.0, 300.0, allow_nan=False))


def test_zero_parameters_are_the_identity() -> None:
    np.testing.assert_array_equal(warp_matrix(CENTER, np.zeros(9)), np.eye(4))


def test_the_warp_is_the_documented_formula() -> None:
    p = np.array([0.01, -0.02, 0.005, 0.001, -0.002, 0.003, 1e-5, -2e-5, 3e-5])
    x = np.array([[100.0, 50.0, 900.0], [-20.0, 200.0, 780.0]])
    S = np.array([[p[0], p[3], p[4]], [p[3], p[1], p[5]], [p[4], p[5], p[2]]])
    r = x - CENTER
    expected = CENTER + (r + r @ S.T) / (1.0 + r @ p[6:])[:, None]
    np.testing.assert_allclose(apply_homography(warp_matrix(CENTER, p), x), expected, rtol=0, atol=1e-12)


def test_the_center_is_a_fixed_point() -> None:
    p = np.array([0.01, -0.02, 0.005, 0.001, -0.002, 0.003, 1e-5, -2e-5, 3e-5])
    at_center = apply_homography(warp_matrix(CENTER, p), CENTER[None])
    np.testing.assert_allclose(at_center, CENTER[None], atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(params, points)
def test_undoing_a_warp_gives_the_points_back(p: tuple[float, ...], offsets: np.ndarray) -> None:
    x = CENTER + offsets
    W = warp_matrix(CENTER, p)
    corr = ProjectiveCorrection.undoing(W)
    np.testing.assert_allclose(corr.apply(apply_homography(W, x)), x, rtol=0, atol=1e-8)


@settings(max_examples=30, deadline=None)
@given(params, points)
def test_displacement_is_the_largest_move(p: tuple[float, ...], offsets: np.ndarray) -> None:
    x = CENTER + offsets
    corr = ProjectiveCorrection.undoing(warp_matrix(CENTER, p))
    moved = np.linalg.norm(corr.apply(x) - x, axis=1)
    assert corr.displacement_mm(x) == pytest.approx(float(moved.max()), abs=1e-12)


def test_a_translation_matrix_moves_points_by_it() -> None:
    H = np.eye(4)
    H[:3, 3] = (1.0, -2.0, 3.0)
    corr = ProjectiveCorrection.from_matrix(2.0 * H)   # any scale: normalised by H[3][3]
    np.testing.assert_allclose(corr.apply([[0.0, 0.0, 0.0], [10.0, 10.0, 10.0]]),
                               [[1.0, -2.0, 3.0], [11.0, 8.0, 13.0]], atol=1e-12)
    assert corr.displacement_mm(np.zeros((0, 3))) == 0.0
    assert not corr.H_metric_from_measured.flags.writeable


@pytest.mark.parametrize(("bad", "says"), [
    (np.eye(3), "4x4"),
    (np.full((4, 4), np.nan), "finite"),
    (np.diag([1.0, 1.0, 1.0, 0.0]), "H[3][3]"),
])
def test_bad_matrices_are_refused(bad: np.ndarray, says: str) -> None:
    with pytest.raises(GeometryError, match=says.replace("[", r"\[").replace("]", r"\]")):
        ProjectiveCorrection.from_matrix(bad)


def test_a_singular_warp_is_refused() -> None:
    with pytest.raises(GeometryError, match="singular"):
        ProjectiveCorrection.undoing(np.zeros((4, 4)))


@settings(max_examples=40, deadline=None)
@given(params, points)
def test_to_measured_is_the_inverse_of_apply(p: tuple[float, ...], offsets: np.ndarray) -> None:
    x = CENTER + offsets
    corr = ProjectiveCorrection.undoing(warp_matrix(CENTER, p))
    np.testing.assert_allclose(corr.to_measured(corr.apply(x)), x, rtol=0, atol=1e-8)
    np.testing.assert_allclose(corr.to_measured(x), apply_homography(warp_matrix(CENTER, p), x), rtol=0,
                               atol=1e-8)
