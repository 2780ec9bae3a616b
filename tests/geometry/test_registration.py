"""Paired-point registration: exact recovery, Horn == SVD, weights, noise statistics, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.registration import horn_matrix, register, register_horn, register_svd
from hil.geometry.transform import RigidTransform
from hil.geometry.tre import expected_fre_mm

from .strategies import point_sets, rigid_transforms

METHODS = [register_horn, register_svd]


@settings(max_examples=150)
@given(point_sets(), rigid_transforms())
def test_exact_data_recovers_transform_to_1e9(moving: np.ndarray, T: RigidTransform) -> None:
    fixed = T.apply(moving)
    for fn in METHODS:
        reg = fn(fixed, moving)
        assert reg.T_fixed_from_moving.is_close(T, atol_mm=1e-9, atol_rad=1e-9), fn.__name__
        assert reg.fre_rms_mm < 1e-9
        assert reg.residuals_mm.shape == (moving.shape[0],)
        assert np.all(reg.residuals_mm < 1e-9)


@settings(max_examples=100)
@given(point_sets(min_points=3, max_points=8), rigid_transforms(), st.integers(0, 2**32 - 1))
def test_horn_equals_svd_on_noisy_data(moving: np.ndarray, T: RigidTransform, seed: int) -> None:
    rng = np.random.default_rng(seed)
    fixed = T.apply(moving) + rng.normal(scale=2.0, size=moving.shape)
    w = rng.uniform(0.2, 2.0, size=moving.shape[0])
    for weights in (None, w):
        h = register_horn(fixed, moving, weights)
        s = register_svd(fixed, moving, weights)
        assert h.T_fixed_from_moving.is_close(s.T_fixed_from_moving, atol_mm=1e-8, atol_rad=1e-10)
        assert h.fre_rms_mm == pytest.approx(s.fre_rms_mm, rel=1e-9, abs=1e-12)
        assert (h.method, s.method) == ("horn", "svd")


def test_horn_matrix_is_seed000_eqs_18_to_20() -> None:
    A = np.arange(1.0, 10.0).reshape(3, 3) ** 1.5
    C = horn_matrix(A)
    B = A - A.T
    assert C[0, 0] == pytest.approx(np.trace(A))
    np.testing.assert_allclose(C[0, 1:], [B[1, 2], B[2, 0], B[0, 1]])
    np.testing.assert_allclose(C[1:, 0], C[0, 1:])
    np.testing.assert_allclose(C[1:, 1:], A + A.T - np.trace(A) * np.eye(3))
    np.testing.assert_allclose(C, C.T)


def test_planar_points_give_a_proper_rotation_not_a_reflection() -> None:
    moving = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 30.0, 0.0], [40.0, 35.0, 0.0]])
    T = RigidTransform.from_rotvec([0.2, 2.5, -0.4], [10.0, 20.0, 30.0])
    rng = np.random.default_rng(4)
    fixed = T.apply(moving) + rng.normal(scale=0.5, size=moving.shape)
    for fn in METHODS:
        R = fn(fixed, moving).T_fixed_from_moving.R
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert fn(fixed, moving).T_fixed_from_moving.is_close(T, atol_mm=2.0, atol_rad=0.05)


def test_weights_zero_out_an_outlier() -> None:
    rng = np.random.default_rng(1)
    moving = rng.uniform(-50, 50, size=(6, 3))
    T = RigidTransform.from_rotvec([0.1, -0.3, 0.7], [5.0, -8.0, 100.0])
    fixed = T.apply(moving)
    fixed[5] += [30.0, 0.0, 0.0]
    for fn in METHODS:
        reg = fn(fixed, moving, weights=[1, 1, 1, 1, 1, 0])
        assert reg.T_fixed_from_moving.is_close(T, 1e-9, 1e-9)
        assert reg.residuals_mm[5] == pytest.approx(30.0, abs=1e-9)
        assert reg.fre_rms_mm < 1e-9  # weighted RMS ignores the zero-weight pair


def test_fre_under_noise_matches_fitzpatrick_expectation() -> None:
    """<FRE^2> = (1 - 2/N) FLE^2 (FWM 1998) over many trials, for N = 4 and N = 8."""
    rng = np.random.default_rng(2026)
    sigma = 0.5  # per axis; FLE_rms = sigma * sqrt(3)
    fle = sigma * math.sqrt(3.0)
    for n in (4, 8):
        moving = rng.uniform(-80, 80, size=(n, 3))
        T = RigidTransform.from_rotvec([0.3, 0.2, -1.0], [100.0, 0.0, 800.0])
        truth = T.apply(moving)
        trials = 4000
        fre2 = np.empty(trials)
        for i in range(trials):
            fixed = truth + rng.normal(scale=sigma, size=truth.shape)
            fre2[i] = register_horn(fixed, moving).fre_rms_mm ** 2
        expected = expected_fre_mm(n, fle) ** 2
        # the mean of chi-square-like FRE^2 over 4000 trials has < 2% standard error here
        assert float(fre2.mean()) == pytest.approx(expected, rel=0.05)


@pytest.mark.parametrize("fn", METHODS)
def test_degenerate_inputs_raise_typed_errors(fn: object) -> None:
    reg = fn
    good = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    cases: list[tuple[object, object, type[Exception]]] = [
        (good[:2], good[:2], GeometryError),  # < 3 points
        (good, good[:3], GeometryError),  # different counts
        (np.where(good == 10, np.nan, good), good, GeometryError),  # NaN
        (good, np.where(good == 10, np.inf, good), GeometryError),  # inf
        (np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2], [5, 5, 5]]), good, DegenerateConfigurationError),
        (good, np.zeros((4, 3)), DegenerateConfigurationError),  # coincident
        (good, np.ones((4, 2)), GeometryError),  # wrong shape
    ]
    for fixed, moving, err in cases:
        with pytest.raises(err):
            reg(fixed, moving)  # type: ignore[operator]
    with pytest.raises(GeometryError):
        reg(good, good, weights=[1, 1, 0, 0])  # type: ignore[operator]
    with pytest.raises(GeometryError):
        reg(good, good, weights=[1, 1, -1, 1])  # type: ignore[operator]
    with pytest.raises(GeometryError):
        reg(good, good, weights=[1, 1, 1])  # type: ignore[operator]


def test_register_dispatch() -> None:
    good = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    assert register(good, good, method="svd").method == "svd"
    assert register(good, good).method == "horn"
    with pytest.raises(GeometryError):
        register(good, good, method="icp")


def test_seed000_table1_figures() -> None:
    """Seed 000 Table 1: CT <- optical (before) and optical before <- after registrations."""
    ct = np.array([(-17.91, -67.45, -1225.5), (-13.4, -107.17, -1105.5), (-88.75, -121.47, -1114.3),
                   (-112.63, -222.2, -1360.7)])
    before = np.array([(77.608, 37.669, 803.65), (-37.568, 44.011, 847.83), (-29.322, -33.809, 874.44),
                       (210.39, -48.611, 955.56)])
    after = np.array([(54.098, 75.004, 789.39), (-58.37, 52.137, 831.73), (-37.175, -23.39, 839.09),
                      (206.04, -8.459, 920.66)])
    reg = register_horn(ct, before)
    assert reg.fre_rms_mm == pytest.approx(6.238841, abs=1e-6)
    assert math.degrees(reg.T_fixed_from_moving.rotation_angle_rad()) == pytest.approx(120.563518, abs=1e-6)
    motion = register_horn(after, before)
    assert motion.fre_rms_mm == pytest.approx(2.694689, abs=1e-6)
    assert register_svd(after, before).T_fixed_from_moving.is_close(motion.T_fixed_from_moving, 1e-9, 1e-12)
