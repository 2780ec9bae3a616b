"""ICP: principal-axes start converges from large rotations where plain ICP fails; trimming."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.icp import icp, principal_alignment_candidates
from hil.geometry.transform import RigidTransform


def asymmetric_surface(n: int, rng: np.random.Generator) -> np.ndarray:
    """Points on a bumpy ellipsoid (semi-axes 60/35/20 mm) with no rotational symmetry."""
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    bump = 15.0 * np.exp(-np.sum((u - np.array([0.6, 0.6, 0.5])) ** 2, axis=1) / 0.1)
    return u * np.array([60.0, 35.0, 20.0]) + u * bump[:, None]


@pytest.fixture(scope="module")
def clouds() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(42)
    target = asymmetric_surface(2000, rng)
    source_in_target = target[rng.choice(2000, size=400, replace=False)]
    return target, source_in_target


@pytest.mark.parametrize(
    ("axis", "angle_deg"),
    [([0.3, -0.8, 0.5], 150.0), ([1.0, 0.0, 0.0], 179.0), ([0.0, 0.0, 1.0], 90.0), ([1.0, -1.0, 0.5], 120.0)],
)
def test_principal_start_converges_where_plain_icp_fails(
    clouds: tuple[np.ndarray, np.ndarray], axis: list[float], angle_deg: float
) -> None:
    target, source_true = clouds
    k = np.asarray(axis) / np.linalg.norm(axis)
    T = RigidTransform.from_rotvec(k * math.radians(angle_deg), [25.0, -10.0, 40.0])
    source = T.inverse().apply(source_true)

    plain = icp(source, target, init="identity")
    plain_err = plain.T_target_from_source.inverse() @ T
    assert math.degrees(plain_err.rotation_angle_rad()) > 10.0  # stuck in a local minimum

    good = icp(source, target)
    assert good.initial_candidates == 4
    assert good.converged
    assert good.rms_mm < 1e-6
    assert good.T_target_from_source.is_close(T, atol_mm=1e-6, atol_rad=1e-8)
    assert 1 <= good.iterations < 100
    assert good.inlier_fraction == 1.0


def test_trimmed_icp_rejects_outliers(clouds: tuple[np.ndarray, np.ndarray]) -> None:
    target, source_true = clouds
    rng = np.random.default_rng(5)
    outliers = rng.uniform(-150, 150, size=(40, 3)) + np.array([0.0, 0.0, 120.0])  # 10% clutter
    T = RigidTransform.from_rotvec([0.1, 0.2, -0.15], [3.0, 2.0, -4.0])
    source = T.inverse().apply(np.vstack([source_true, outliers]))
    untrimmed = icp(source, target, init="identity")
    trimmed = icp(source, target, init="identity", trim_fraction=0.15)
    err_u = (untrimmed.T_target_from_source.inverse() @ T).translation_norm()
    err_t = (trimmed.T_target_from_source.inverse() @ T).translation_norm()
    assert err_t < 1e-6
    assert err_u > 100 * err_t
    assert trimmed.inlier_fraction == pytest.approx(1 - math.floor(0.15 * 440) / 440)


def test_explicit_start_and_iteration_cap(clouds: tuple[np.ndarray, np.ndarray]) -> None:
    target, source_true = clouds
    T = RigidTransform.from_rotvec([0.0, 0.0, 0.2], [1.0, 0.0, 0.0])
    source = T.inverse().apply(source_true)
    capped = icp(source, target, init=RigidTransform.identity(), max_iterations=1)
    assert capped.iterations == 1
    assert not capped.converged
    assert capped.initial_candidates == 1
    exact = icp(source, target, init=T)
    assert exact.converged
    assert exact.rms_mm < 1e-9


def test_principal_candidates_are_proper_and_distinct(clouds: tuple[np.ndarray, np.ndarray]) -> None:
    target, _ = clouds
    cands = principal_alignment_candidates(target, target)
    assert len(cands) == 4
    assert any(c.is_close(RigidTransform.identity(), 1e-9, 1e-9) for c in cands)
    for a in cands:
        assert np.linalg.det(a.R) == pytest.approx(1.0)
        others = [b for b in cands if b is not a]
        assert all(abs(math.degrees((a.inverse() @ b).rotation_angle_rad()) - 180.0) < 1e-6 for b in others)


def test_errors(clouds: tuple[np.ndarray, np.ndarray]) -> None:
    target, source = clouds
    with pytest.raises(GeometryError):
        icp(source, target, trim_fraction=0.95)
    with pytest.raises(GeometryError):
        icp(source, target, max_iterations=0)
    with pytest.raises(GeometryError):
        icp(source, target, tolerance_mm=0.0)
    with pytest.raises(GeometryError):
        icp(source[:4], target, trim_fraction=0.5)
    with pytest.raises(DegenerateConfigurationError):
        icp(np.outer(np.arange(10.0), [1.0, 2.0, 3.0]), target)
    with pytest.raises(GeometryError):
        icp(np.vstack([source, [np.nan, 0.0, 0.0]]), target)
