"""RigidTransform: round trips, composition, the papers' Euler conventions, rotvec near pi."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.errors import GeometryError
from hil.geometry.transform import RigidTransform, as_points, matrix_to_rotvec, quaternion_to_matrix

from .strategies import rigid_transforms

angles = st.floats(-math.pi, math.pi, allow_nan=False)
half = st.floats(-math.pi / 2 + 1e-3, math.pi / 2 - 1e-3, allow_nan=False)


@given(rigid_transforms())
def test_matrix_round_trip(T: RigidTransform) -> None:
    assert RigidTransform.from_matrix(T.as_matrix()).is_close(T, 1e-9, 1e-12)


@given(rigid_transforms())
def test_quaternion_and_rotvec_round_trips(T: RigidTransform) -> None:
    q = T.as_quaternion()
    assert q[0] >= 0
    assert abs(np.linalg.norm(q) - 1) < 1e-12
    assert RigidTransform.from_quaternion(q, T.t).is_close(T, 1e-9, 1e-9)
    assert RigidTransform.from_rotvec(T.as_rotvec(), T.t).is_close(T, 1e-9, 1e-9)


@given(rigid_transforms(), rigid_transforms(), rigid_transforms())
def test_composition_associative_and_inverse(a: RigidTransform, b: RigidTransform, c: RigidTransform) -> None:
    assert ((a @ b) @ c).is_close(a @ (b @ c), 1e-7, 1e-9)
    assert (a @ a.inverse()).is_close(RigidTransform.identity(), 1e-9, 1e-9)
    p = np.array([[1.0, 2.0, 3.0], [-40.0, 5.0, 600.0]])
    np.testing.assert_allclose((a @ b).apply(p), a.apply(b.apply(p)), atol=1e-9)
    np.testing.assert_allclose(a.inverse().apply(a.apply(p)), p, atol=1e-9)


def _seed000_eq14(psi: float, theta: float, phi: float) -> np.ndarray:
    """Seed 000 eq 14 written out element by element (ZYX: yaw psi, pitch theta, roll phi).

    The printed eq 14 has three typos against the product Rz(psi) Ry(theta) Rx(phi) its text
    describes (r13 has sin(phi) for cos(phi), r22 cos(theta) for cos(phi), r23 sin(theta) for
    sin(phi)); the corrected elements are used here.
    """
    c, s = math.cos, math.sin
    return np.array(
        [
            [c(psi) * c(theta), -s(psi) * c(phi) + c(psi) * s(theta) * s(phi),
             s(psi) * s(phi) + c(psi) * s(theta) * c(phi)],
            [s(psi) * c(theta), c(psi) * c(phi) + s(psi) * s(theta) * s(phi),
             -c(psi) * s(phi) + s(psi) * s(theta) * c(phi)],
            [-s(theta), c(theta) * s(phi), c(theta) * c(phi)],
        ]
    )


def _seed002_eq23(alpha: float, beta: float, gamma: float) -> np.ndarray:
    """Seed 002 eq 23 written out element by element: R(x, alpha) R(y, beta) R(z, gamma)."""
    c, s = math.cos, math.sin
    ca, sa, cb, sb, cg, sg = c(alpha), s(alpha), c(beta), s(beta), c(gamma), s(gamma)
    return np.array(
        [
            [cb * cg, -cb * sg, sb],
            [sa * sb * cg + ca * sg, ca * cg - sa * sb * sg, -sa * cb],
            [sa * sg - ca * sb * cg, ca * sb * sg + sa * cg, ca * cb],
        ]
    )


@given(angles, half, angles)
def test_euler_zyx_matches_seed000_eq14(psi: float, theta: float, phi: float) -> None:
    T = RigidTransform.from_euler_zyx(psi, theta, phi)
    np.testing.assert_allclose(T.R, _seed000_eq14(psi, theta, phi), atol=1e-12)
    back = RigidTransform.from_euler_zyx(*T.as_euler_zyx())
    assert back.is_close(T, 1e-12, 1e-9)
    np.testing.assert_allclose(T.as_euler_zyx(), (psi, theta, phi), atol=1e-9)


@given(angles, half, angles)
def test_euler_xyz_matches_seed002_eq23(alpha: float, beta: float, gamma: float) -> None:
    T = RigidTransform.from_euler_xyz(alpha, beta, gamma)
    np.testing.assert_allclose(T.R, _seed002_eq23(alpha, beta, gamma), atol=1e-12)
    np.testing.assert_allclose(T.as_euler_xyz(), (alpha, beta, gamma), atol=1e-9)


def test_euler_gimbal_lock_still_round_trips() -> None:
    T = RigidTransform.from_euler_zyx(0.3, math.pi / 2, -0.2)
    assert RigidTransform.from_euler_zyx(*T.as_euler_zyx()).is_close(T, 1e-9, 1e-9)
    U = RigidTransform.from_euler_xyz(0.3, -math.pi / 2, 0.1)
    assert RigidTransform.from_euler_xyz(*U.as_euler_xyz()).is_close(U, 1e-9, 1e-9)


def test_quaternion_matrix_is_seed000_eq16_for_a_known_rotation() -> None:
    # 90 deg about z: q = [cos 45, 0, 0, sin 45]
    R = quaternion_to_matrix([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)


@pytest.mark.parametrize("eps", [0.0, 1e-9, 1e-6, 1e-3])
@pytest.mark.parametrize("axis", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [1, -2, 0.5]])
def test_rotvec_near_pi(axis: list[float], eps: float) -> None:
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    angle = math.pi - eps
    T = RigidTransform.from_rotvec(k * angle)
    rv = matrix_to_rotvec(T.R)
    assert abs(np.linalg.norm(rv) - angle) < 1e-9
    # near pi the sign of the axis is ambiguous; the rotation must be the same either way
    assert RigidTransform.from_rotvec(rv).is_close(T, 1e-12, 1e-8)
    assert abs(T.rotation_angle_rad() - angle) < 1e-9


def test_small_angles_are_precise() -> None:
    T = RigidTransform.from_rotvec([1e-10, 0.0, 0.0])
    assert abs(T.rotation_angle_rad() - 1e-10) < 1e-18
    assert not T.is_close(RigidTransform.identity(), atol_rad=1e-11)


def test_invalid_inputs_raise_typed_errors() -> None:
    with pytest.raises(GeometryError):
        RigidTransform(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(GeometryError):
        RigidTransform(np.eye(3), [0.0, np.nan, 0.0])
    with pytest.raises(GeometryError):
        RigidTransform.from_matrix(np.ones((4, 4)))
    with pytest.raises(GeometryError):
        RigidTransform.from_quaternion([0.0, 0.0, 0.0, 0.0])
    with pytest.raises(GeometryError):
        as_points([[1.0, 2.0]])
    with pytest.raises(GeometryError):
        as_points([[1.0, 2.0, np.inf]])


def test_rotvec_whose_norm_overflows_is_a_geometry_error() -> None:
    """Finite components whose norm overflows a float (> 1.8e308) name the problem instead of a
    ValueError from math.sin(inf); large but representable angles still work (no overflow in the
    squares)."""
    from hil.geometry.transform import rotvec_to_matrix

    with pytest.raises(GeometryError, match="overflows"):
        rotvec_to_matrix([1.5e308, 1.5e308, 1.5e308])
    R = rotvec_to_matrix([1e200, 0.0, 0.0])
    assert np.allclose(R @ R.T, np.eye(3))
    assert R[0, 0] == 1.0


@pytest.mark.parametrize(
    "points", [[10**400, 0, 0], [[1.0, 2.0], [3.0]], ["a", 1.0, 2.0], [{"a": 1}, 1.0, 2.0]]
)
def test_as_points_refuses_non_numbers_with_a_geometry_error(points: object) -> None:
    """Whatever numpy raises converting the input (TypeError, ValueError, OverflowError for an
    integer beyond float range, as a JSON file can hold) becomes the documented GeometryError."""
    with pytest.raises(GeometryError, match="fiducials_mm is not an array of numbers"):
        as_points(points, "fiducials_mm")


def test_composition_and_inverse_are_read_only_contiguous_and_exact() -> None:
    """``@`` and ``inverse`` skip the constructor's checks (their inputs were checked): the result
    is the same product, as read-only C-contiguous float64 arrays."""
    A = RigidTransform.from_rotvec([0.3, -0.2, 0.9], [10.0, -5.0, 2.5])
    B = RigidTransform.from_rotvec([-1.1, 0.4, 0.2], [-3.0, 7.0, 120.0])
    for T, (R, t) in [(A @ B, (A.R @ B.R, A.R @ B.t + A.t)), (A.inverse(), (A.R.T, -A.R.T @ A.t))]:
        assert T.R.tobytes() == np.ascontiguousarray(R).tobytes()
        assert T.t.tobytes() == t.tobytes()
        assert T.R.flags.c_contiguous
        assert not T.R.flags.writeable
        assert not T.t.flags.writeable
