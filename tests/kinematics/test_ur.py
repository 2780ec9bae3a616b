"""UR3 / UR3e kinematics: forward check poses, analytic inverse round trips, unreachable poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.errors import GeometryError
from hil.geometry.transform import RigidTransform
from hil.kinematics import UR3_JOINT_LIMITS_RAD, UR3_REACH_MM, UR_DH, ur_forward, ur_inverse
from hil.kinematics.ur import within_joint_limits, within_reach, wrap_to_pi

MODELS = ["ur3", "ur3e"]
angle = st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False)
joints = st.lists(angle, min_size=6, max_size=6).map(np.array)


def test_forward_matches_the_reference_check_pose() -> None:
    # ur-rtde.md: q = [0, -pi/2, pi/2, -pi/2, -pi/2, 0] -> [-0.2986, -0.1123, 0.3137, -2.2214, -2.2214, 0]
    T = ur_forward([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0], "ur3")
    np.testing.assert_allclose(T.t, [-298.6, -112.35, 313.65], atol=1e-9)
    expected = RigidTransform.from_rotvec([-2.2214415, -2.2214415, 0.0])
    assert (expected.inverse() @ T).rotation_angle_rad() < 1e-6  # compare rotations (trap 7)


@pytest.mark.parametrize("model", MODELS)
def test_forward_at_zero_is_the_straight_arm(model: str) -> None:
    p = UR_DH[model]
    T = ur_forward(np.zeros(6), model)
    d1, d4, d5, d6 = (p.d_m[i] * 1000 for i in (0, 3, 4, 5))
    a2, a3 = p.a_m[1] * 1000, p.a_m[2] * 1000
    np.testing.assert_allclose(T.t, [a2 + a3, -(d4 + d6), d1 - d5], atol=1e-9)
    # tool z points along -y of the base; tool x along +x (hand computed from the DH chain)
    np.testing.assert_allclose(T.R, [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


@pytest.mark.parametrize("model", MODELS)
@given(q=joints)
def test_inverse_of_forward_contains_q_and_every_solution_reproduces_the_pose(
    model: str, q: np.ndarray
) -> None:
    T = ur_forward(q, model)
    sols = ur_inverse(T, model, q_near=q)
    assert 1 <= sols.shape[0] <= 8
    assert sols.shape[1] == 6
    for s in sols:
        assert T.is_close(ur_forward(s, model), atol_mm=1e-6, atol_rad=1e-7)
    if abs(math.sin(q[4])) > 1e-3:  # away from the wrist singularity q is recovered exactly
        np.testing.assert_allclose(sols[0], q, atol=1e-6)
    dist = np.linalg.norm(sols - q, axis=1)
    assert np.all(np.diff(dist) >= -1e-12)


@pytest.mark.parametrize("model", MODELS)
def test_generic_pose_has_eight_distinct_solutions(model: str) -> None:
    q = np.array([0.2, -2.0, 1.0, -0.5, 1.2, 0.3])
    sols = ur_inverse(ur_forward(q, model), model)
    assert sols.shape == (8, 6)
    wrapped = wrap_to_pi(sols)
    for i in range(8):
        for j in range(i + 1, 8):
            assert np.max(np.abs(wrap_to_pi(wrapped[i] - wrapped[j]))) > 1e-6
    assert np.all(sols > -math.pi - 1e-12)
    assert np.all(sols <= math.pi + 1e-12)


def test_wrist_flip_out_of_reach_leaves_four_solutions() -> None:
    # For this pose the flipped wrist puts the origin of link 4 beyond the reach of the elbow.
    sols = ur_inverse(ur_forward([0.3, -1.2, 1.1, -1.4, -1.3, 0.4]), "ur3")
    assert sols.shape == (4, 6)
    assert len({round(float(q5), 9) for q5 in sols[:, 4]}) == 2


def test_wrist_singularity_keeps_q6_from_q_near() -> None:
    q = np.array([0.2, -1.0, 1.2, -0.7, 0.0, 0.9])
    sols = ur_inverse(ur_forward(q), "ur3", q_near=q)
    assert sols.shape[0] >= 1
    np.testing.assert_allclose(sols[0], q, atol=1e-6)


def test_q_near_moves_solutions_to_the_nearest_2pi_equivalent() -> None:
    q = np.array([0.3, -1.2, 1.1, -1.4, -1.3, 0.4])
    near = q + np.array([-2 * math.pi, 0, 0, 0, 0, -2 * math.pi])
    sols = ur_inverse(ur_forward(q), "ur3", q_near=near)
    np.testing.assert_allclose(sols[0], near, atol=1e-6)
    assert within_joint_limits(sols[0])


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize(
    "t_mm",
    [
        (1000.0, 0.0, 150.0),   # far beyond reach
        (0.0, 0.0, 900.0),      # straight up, too high
        (0.0, 0.0, 150.0),      # on the base axis: wrist centre closer than d4 to it
    ],
)
def test_unreachable_pose_has_no_solution(model: str, t_mm: tuple[float, float, float]) -> None:
    sols = ur_inverse(RigidTransform.from_translation(t_mm), model)
    assert sols.shape == (0, 6)


@given(
    x=st.floats(-2000, 2000), y=st.floats(-2000, 2000), z=st.floats(-2000, 2000),
    rv=st.lists(st.floats(-3, 3), min_size=3, max_size=3),
)
def test_any_returned_solution_is_exact_and_far_poses_have_none(
    x: float, y: float, z: float, rv: list[float]
) -> None:
    T = RigidTransform.from_rotvec(rv, [x, y, z])
    sols = ur_inverse(T, "ur3")
    for s in sols:
        assert T.is_close(ur_forward(s), atol_mm=1e-6, atol_rad=1e-7)
    # the flange cannot be farther from the shoulder than the summed link lengths
    p = UR_DH["ur3"]
    max_mm = 1000 * (abs(p.a_m[1]) + abs(p.a_m[2]) + p.d_m[3] + p.d_m[4] + p.d_m[5])
    if math.dist((x, y, z), (0, 0, 1000 * p.d_m[0])) > max_mm:
        assert sols.shape[0] == 0


def test_reach_and_limits_helpers() -> None:
    assert UR3_REACH_MM == 500.0
    assert UR3_JOINT_LIMITS_RAD.shape == (6, 2)
    assert within_reach([300.0, 0.0, 151.9])
    assert not within_reach([0.0, 0.0, 151.9 + 500.1])
    assert within_joint_limits(np.zeros(6))
    assert not within_joint_limits([0, 0, 0, 0, 0, 7.0])


def test_bad_input_raises_geometry_error() -> None:
    with pytest.raises(GeometryError, match="unknown UR model"):
        ur_forward(np.zeros(6), "ur5")
    with pytest.raises(GeometryError, match="6 finite"):
        ur_forward([0.0, 1.0])
    with pytest.raises(GeometryError, match="q_near"):
        ur_inverse(ur_forward(np.zeros(6)), "ur3", q_near=[math.nan] * 6)


def test_joint_frames_are_cached_by_exact_angles_and_read_only() -> None:
    """The simulated arm asks again for the pose the previous servo period ended at: the frames
    come from a cache keyed on the angles' exact bits, shared, so nobody may change them."""
    from hil.kinematics.ur import _dh_matrix, ur_joint_frames

    q = np.array([0.3, -1.2, 1.1, -0.4, 1.3, 0.2])
    first, again = ur_joint_frames(q), ur_joint_frames(q.copy())
    assert all(a is b for a, b in zip(first, again, strict=True))
    expected = np.eye(4)
    for i, (theta, d, a, alpha) in enumerate(zip(q, UR_DH["ur3"].d_mm, UR_DH["ur3"].a_mm,
                                                  UR_DH["ur3"].alpha_rad, strict=True)):
        expected = expected @ _dh_matrix(theta, d, a, alpha)
        np.testing.assert_allclose(first[i], expected, atol=1e-9)
    with pytest.raises(ValueError, match="read-only"):
        first[-1][0, 3] = 0.0
    # one ulp away is another pose, computed afresh
    other = ur_joint_frames(np.nextafter(q, 1.0))
    assert other[-1] is not first[-1]
