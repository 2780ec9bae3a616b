"""Triangulation: DLT and seed 003's skew-line midpoint with its gap."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.transform import RigidTransform
from hil.geometry.triangulation import triangulate_dlt, triangulate_midpoint

K = np.array([[1394.0, 0.0, 960.0], [0.0, 1394.0, 540.0], [0.0, 0.0, 1.0]])
BASELINE_MM = 120.0
T_RIGHT_FROM_LEFT = RigidTransform.from_rotvec([0.0, -0.05, 0.0], [-BASELINE_MM, 0.0, 3.0])


def _projections() -> tuple[np.ndarray, np.ndarray]:
    P_left = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P_right = K @ T_RIGHT_FROM_LEFT.as_matrix()[:3]
    return P_left, P_right


def _project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    h = np.hstack([X, np.ones((len(X), 1))]) @ P.T
    return h[:, :2] / h[:, 2:]


@settings(max_examples=50)
@given(st.integers(0, 2**32 - 1), st.integers(1, 20))
def test_dlt_recovers_exact_points(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    X = rng.uniform([-200, -150, 600], [200, 150, 1400], size=(n, 3))
    PL, PR = _projections()
    out = triangulate_dlt(PL, PR, _project(PL, X), _project(PR, X))
    np.testing.assert_allclose(out, X, atol=1e-6)
    # OpenCV's (N, 1, 2) layout is accepted too
    out2 = triangulate_dlt(PL, PR, _project(PL, X)[:, None, :], _project(PR, X)[:, None, :])
    np.testing.assert_allclose(out2, X, atol=1e-6)


def test_midpoint_agrees_with_dlt_and_gap_is_zero_for_exact_rays() -> None:
    rng = np.random.default_rng(1)
    X = rng.uniform([-200, -150, 600], [200, 150, 1400], size=(10, 3))
    PL, PR = _projections()
    uvl, uvr = _project(PL, X), _project(PR, X)
    Kinv = np.linalg.inv(K)
    dirs_l = np.hstack([uvl, np.ones((10, 1))]) @ Kinv.T
    T_left_from_right = T_RIGHT_FROM_LEFT.inverse()
    dirs_r = T_left_from_right.apply_vector(np.hstack([uvr, np.ones((10, 1))]) @ Kinv.T)
    pts, gap = triangulate_midpoint(np.zeros(3), dirs_l, T_left_from_right.t, dirs_r)
    np.testing.assert_allclose(pts, X, atol=1e-8)
    assert np.all(gap < 1e-8)
    # a 2-pixel vertical error on the right image opens a gap
    uvr_bad = uvr + np.array([0.0, 2.0])
    dirs_bad = T_left_from_right.apply_vector(np.hstack([uvr_bad, np.ones((10, 1))]) @ Kinv.T)
    _, gap_bad = triangulate_midpoint(np.zeros(3), dirs_l, T_left_from_right.t, dirs_bad)
    assert np.all(gap_bad > 0.5)


def test_midpoint_of_known_skew_lines() -> None:
    pts, gap = triangulate_midpoint([0.0, 0.0, 0.0], [[1.0, 0.0, 0.0]], [3.0, 7.0, 5.0], [[0.0, 2.0, 0.0]])
    np.testing.assert_allclose(pts, [[3.0, 0.0, 2.5]], atol=1e-12)
    np.testing.assert_allclose(gap, [5.0], atol=1e-12)


def test_errors() -> None:
    PL, PR = _projections()
    with pytest.raises(GeometryError):
        triangulate_dlt(PL, PR, [[1.0, 2.0]], [[1.0, 2.0], [3.0, 4.0]])
    with pytest.raises(GeometryError):
        triangulate_dlt(PL[:2], PR, [[1.0, 2.0]], [[1.0, 2.0]])
    with pytest.raises(GeometryError):
        triangulate_dlt(PL, PR, [[np.nan, 2.0]], [[1.0, 2.0]])
    # parallel rays (same pixel in two translated, unrotated cameras): a point at infinity
    P_shifted = K @ np.hstack([np.eye(3), [[-BASELINE_MM], [0.0], [0.0]]])
    with pytest.raises(DegenerateConfigurationError):
        triangulate_dlt(PL, P_shifted, [[960.0, 540.0]], [[960.0, 540.0]])
    with pytest.raises(DegenerateConfigurationError):
        triangulate_midpoint([0, 0, 0], [[0, 0, 1.0]], [10, 0, 0], [[0, 0, 2.0]])
    with pytest.raises(GeometryError):
        triangulate_midpoint([0, 0, 0], [[0, 0, 0.0]], [10, 0, 0], [[0, 0, 1.0]])
    with pytest.raises(GeometryError):
        triangulate_midpoint([0, 0], [[0, 0, 1.0]], [10, 0, 0], [[0, 0, 1.0]])
    with pytest.raises(GeometryError):
        triangulate_midpoint([0, 0, 0], [[0, 0, 1.0]], [10, 0, 0], [[0, 0, 1.0], [0, 1, 1.0]])
    assert triangulate_dlt(PL, PR, np.zeros((0, 2)), np.zeros((0, 2))).shape == (0, 3)
