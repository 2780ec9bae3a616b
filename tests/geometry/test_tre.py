"""Fitzpatrick-West-Maurer expected TRE and FRE against Monte-Carlo trials and known cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform
from hil.geometry.tre import expected_fre_mm, expected_tre_mm, fle_from_fre_mm

FIDUCIALS = np.array(
    [[0.0, 0.0, 0.0], [90.0, 10.0, 5.0], [20.0, 70.0, -10.0], [-40.0, 50.0, 30.0], [60.0, -30.0, 40.0]]
)


@pytest.mark.parametrize(
    "target", [[25.0, 20.0, 10.0], [150.0, 120.0, -200.0], [-100.0, 0.0, 80.0]], ids=["centre", "far", "side"]
)
def test_tre_matches_monte_carlo_within_a_few_percent(target: list[float]) -> None:
    rng = np.random.default_rng(7)
    sigma = 0.4
    fle = sigma * math.sqrt(3.0)
    T = RigidTransform.from_rotvec([1.0, -0.5, 0.25], [200.0, -50.0, 900.0])
    truth = T.apply(FIDUCIALS)
    target_true = T.apply(np.asarray(target))
    trials = 4000
    tre2 = np.empty(trials)
    for i in range(trials):
        noisy = truth + rng.normal(scale=sigma, size=truth.shape)
        reg = register_horn(noisy, FIDUCIALS)
        tre2[i] = float(np.sum((reg.T_fixed_from_moving.apply(np.asarray(target)) - target_true) ** 2))
    predicted = expected_tre_mm(FIDUCIALS, target, fle)
    assert math.sqrt(float(tre2.mean())) == pytest.approx(predicted, rel=0.04)


def test_tre_at_centroid_is_fle_over_sqrt_n_and_grows_with_distance() -> None:
    c = FIDUCIALS.mean(axis=0)
    assert expected_tre_mm(FIDUCIALS, c, 1.0) == pytest.approx(1.0 / math.sqrt(5.0))
    near = expected_tre_mm(FIDUCIALS, c + np.array([10.0, 0, 0]), 1.0)
    far = expected_tre_mm(FIDUCIALS, c + np.array([300.0, 0, 0]), 1.0)
    assert 1.0 / math.sqrt(5.0) < near < far
    # invariant under a rigid motion of fiducials and target together
    T = RigidTransform.from_rotvec([0.3, 0.4, 0.5], [1.0, 2.0, 3.0])
    moved = expected_tre_mm(T.apply(FIDUCIALS), T.apply(c + np.array([300.0, 0, 0])), 1.0)
    assert moved == pytest.approx(far)


def test_tre_for_symmetric_configuration_closed_form() -> None:
    """Four fiducials on a square of half-side a in the xy plane, target on the z axis at height h.

    Principal axes x, y, z: f_x^2 = f_y^2 = a^2 (distance of points from the x axis is |y| = a),
    f_z^2 = 2 a^2; d_x^2 = d_y^2 = h^2, d_z = 0. <TRE^2> = FLE^2/4 (1 + (2 h^2 / a^2) / 3).
    """
    a, h, fle = 50.0, 120.0, 0.8
    fid = np.array([[a, a, 0], [-a, a, 0], [-a, -a, 0], [a, -a, 0]], dtype=float)
    expected = math.sqrt(fle**2 / 4 * (1 + (2 * h**2 / a**2) / 3))
    assert expected_tre_mm(fid, [0.0, 0.0, h], fle) == pytest.approx(expected, rel=1e-12)


def test_fre_expectation_and_inverse() -> None:
    assert expected_fre_mm(4, 2.0) == pytest.approx(math.sqrt(0.5) * 2.0)
    assert expected_fre_mm(3, 1.0) == pytest.approx(math.sqrt(1 / 3))
    assert fle_from_fre_mm(4, expected_fre_mm(4, 1.7)) == pytest.approx(1.7)


def test_errors() -> None:
    with pytest.raises(GeometryError):
        expected_tre_mm(FIDUCIALS[:2], [0, 0, 0], 1.0)
    with pytest.raises(DegenerateConfigurationError):
        expected_tre_mm([[0, 0, 0], [1, 1, 1], [2, 2, 2]], [0, 0, 0], 1.0)
    with pytest.raises(GeometryError):
        expected_tre_mm(FIDUCIALS, [0, 0, np.nan], 1.0)
    with pytest.raises(GeometryError):
        expected_tre_mm(FIDUCIALS, [0, 0], 1.0)
    with pytest.raises(GeometryError):
        expected_tre_mm(FIDUCIALS, [0, 0, 0], -1.0)
    with pytest.raises(GeometryError):
        expected_fre_mm(2, 1.0)
    with pytest.raises(GeometryError):
        fle_from_fre_mm(4, math.inf)
