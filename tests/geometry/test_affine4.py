"""Seed 000 four-marker affine frames: exact on rigid noise-free data, worse than Horn under noise."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.affine4 import affine_frame, register_affine4
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform

from .strategies import rigid_transforms

MARKERS = np.array([[0.0, 0.0, 0.0], [80.0, 10.0, 5.0], [15.0, 70.0, -8.0], [30.0, 25.0, 60.0]])


def test_affine_frame_is_seed000_eq2() -> None:
    T1 = affine_frame(MARKERS)
    np.testing.assert_allclose(T1[:3, 0], MARKERS[1] - MARKERS[0])
    np.testing.assert_allclose(T1[:3, 1], MARKERS[2] - MARKERS[0])
    np.testing.assert_allclose(T1[:3, 2], MARKERS[3] - MARKERS[0])
    np.testing.assert_allclose(T1[:3, 3], MARKERS[0])
    np.testing.assert_allclose(T1[3], [0, 0, 0, 1])
    # eq 3: P_image = T1 P_affine; the markers have affine coordinates e1, e2, e3
    np.testing.assert_allclose(T1 @ [0, 1, 0, 1], np.append(MARKERS[2], 1.0))


@given(rigid_transforms())
def test_exact_for_rigid_noise_free_markers(T: RigidTransform) -> None:
    moving = MARKERS
    fixed = T.apply(moving)
    aff = register_affine4(fixed, moving)
    np.testing.assert_allclose(aff.matrix_fixed_from_moving, T.as_matrix(), atol=1e-9)
    assert aff.nearest_rigid.is_close(T, 1e-9, 1e-9)
    target = np.array([200.0, -100.0, 50.0])
    np.testing.assert_allclose(aff.apply(target), T.apply(target), atol=1e-8)
    assert aff.fre_rms_mm < 1e-9


def test_degrades_with_noise_compared_with_horn() -> None:
    """Affine interpolation turns localisation noise into shear/scale: larger TRE than Horn."""
    rng = np.random.default_rng(11)
    T = RigidTransform.from_rotvec([0.2, 0.9, -0.3], [50.0, 100.0, 900.0])
    truth = T.apply(MARKERS)
    target = np.array([40.0, 40.0, 150.0])  # beyond the markers, like a deep lesion
    target_true = T.apply(target)
    tre_affine, tre_horn, fre_affine = [], [], []
    for _ in range(500):
        noisy = truth + rng.normal(scale=0.5, size=truth.shape)
        aff = register_affine4(noisy, MARKERS)
        horn = register_horn(noisy, MARKERS)
        tre_affine.append(float(np.linalg.norm(aff.apply(target) - target_true)))
        tre_horn.append(float(np.linalg.norm(horn.T_fixed_from_moving.apply(target) - target_true)))
        fre_affine.append(aff.fre_rms_mm)
    rms_a = math.sqrt(float(np.mean(np.square(tre_affine))))
    rms_h = math.sqrt(float(np.mean(np.square(tre_horn))))
    assert rms_a > 1.5 * rms_h
    assert max(fre_affine) < 1e-9  # it interpolates: FRE says nothing about its error


def test_errors() -> None:
    with pytest.raises(GeometryError):
        register_affine4(MARKERS[:3], MARKERS[:3])
    with pytest.raises(GeometryError):
        register_affine4(np.vstack([MARKERS, MARKERS[:1]]), np.vstack([MARKERS, MARKERS[:1]]))
    coplanar = MARKERS.copy()
    coplanar[:, 2] = 0.0
    with pytest.raises(DegenerateConfigurationError):
        register_affine4(coplanar, MARKERS)
    with pytest.raises(DegenerateConfigurationError):
        register_affine4(MARKERS, np.zeros((4, 3)))
