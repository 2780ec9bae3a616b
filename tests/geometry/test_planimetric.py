"""Seed 002 planimetric method: plane fit, three-plane intersection, frame from normal + line."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.planimetric import (
    Plane,
    fit_plane,
    intersect_planes,
    line_plane_intersection,
    planimetric_frame,
)
from hil.geometry.transform import RigidTransform

from .strategies import rigid_transforms


def _plane_points(normal: np.ndarray, point: np.ndarray, rng: np.random.Generator, n: int = 12) -> np.ndarray:
    normal = normal / np.linalg.norm(normal)
    a = np.cross(normal, [1.0, 0.0, 0.0])
    if np.linalg.norm(a) < 0.1:
        a = np.cross(normal, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    uv = rng.uniform(-40, 40, size=(n, 2))
    return point + uv[:, :1] * a + uv[:, 1:] * b


def test_fit_plane_exact_and_noisy() -> None:
    rng = np.random.default_rng(3)
    n = np.array([0.2, -0.4, 0.9])
    p0 = np.array([10.0, 20.0, 30.0])
    pts = _plane_points(n, p0, rng)
    plane = fit_plane(pts, orient_towards=n)
    np.testing.assert_allclose(plane.normal, n / np.linalg.norm(n), atol=1e-12)
    assert abs(plane.distance_mm(p0)) < 1e-9
    assert plane.rms_mm < 1e-9
    assert fit_plane(pts, orient_towards=-n).normal @ n < 0
    noisy = pts + rng.normal(scale=0.1, size=pts.shape)
    assert 0.02 < fit_plane(noisy).rms_mm < 0.2
    three = fit_plane(pts[:3])  # the minimum the paper allows
    assert abs(abs(three.normal @ n / np.linalg.norm(n)) - 1) < 1e-9


def test_intersect_three_planes_is_seed002_eq6() -> None:
    P = np.array([5.0, -7.0, 11.0])
    normals = [np.array([1.0, 0.1, 0.0]), np.array([0.0, 1.0, 0.3]), np.array([0.2, -0.1, 1.0])]
    planes = [Plane(nrm / np.linalg.norm(nrm), P + np.cross(nrm, [0.3, 0.5, 0.7]) * 3) for nrm in normals]
    np.testing.assert_allclose(intersect_planes(*planes), P, atol=1e-9)
    with pytest.raises(DegenerateConfigurationError):
        intersect_planes(planes[0], planes[0], planes[1])


@given(rigid_transforms(max_translation_mm=500.0))
def test_planimetric_frame_recovers_a_known_frame(T: RigidTransform) -> None:
    """Build the paper's geometry in a known frame O'{x', y', z'} and map it into M with T."""
    rng = np.random.default_rng(0)
    # in the frame: alpha is z'=0, beta and gamma are vertical planes through P = (0, 60, 0)
    P_local = np.array([0.0, 60.0, 0.0])
    D_local = np.array([0.0, 0.0, 45.0])  # the cutter end, on the z' axis above O'
    alpha_pts = T.apply(_plane_points(np.array([0.0, 0.0, 1.0]), np.zeros(3), rng))
    beta_pts = T.apply(_plane_points(np.array([1.0, 0.3, 0.0]), P_local, rng))
    gamma_pts = T.apply(_plane_points(np.array([-1.0, 0.4, 0.0]), P_local, rng))
    alpha = fit_plane(alpha_pts, orient_towards=T.apply_vector([0.0, 0.0, 1.0]))
    P = intersect_planes(alpha, fit_plane(beta_pts), fit_plane(gamma_pts))
    np.testing.assert_allclose(P, T.apply(P_local), atol=1e-8)
    frame = planimetric_frame(alpha, T.apply(D_local), P)
    assert frame.is_close(T, atol_mm=1e-8, atol_rad=1e-9)


def test_errors() -> None:
    with pytest.raises(DegenerateConfigurationError):
        fit_plane([[0, 0, 0], [1, 1, 1], [2, 2, 2]])
    with pytest.raises(GeometryError):
        fit_plane([[0, 0, 0], [1, 0, 0]])
    with pytest.raises(GeometryError):
        fit_plane([[0, 0, 0], [1, 0, 0], [0, 1, 0]], orient_towards=[0, 0])
    plane = Plane(np.array([0.0, 0.0, 1.0]), np.zeros(3))
    with pytest.raises(DegenerateConfigurationError):
        line_plane_intersection([0, 0, 5], [1, 0, 0], plane)
    with pytest.raises(DegenerateConfigurationError):
        planimetric_frame(plane, [3.0, 4.0, 10.0], [3.0, 4.0, 0.0])
