"""Multi-pose hand-eye solver on synthetic poses with a known answer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.geometry.transform import RigidTransform
from hil.rigcal.handeye import PoseSample, RigCalibrationError, SolverSettings, solve_hand_eye

CAD = np.array([[40.0, 90.0, 10.0], [-35.0, 105.0, 10.0], [-10.0, 140.0, 10.0], [30.0, 150.0, 25.0]])
Z_TRUE = RigidTransform.from_rotvec((math.pi, 0.02, -0.01), (60.0, 300.0, 1120.0))
START = RigidTransform.from_rotvec((math.pi, 0.0, 0.0), (0.0, 250.0, 250.0))


def _true_layout(seed: int = 0) -> np.ndarray:
    return CAD + 0.3 * np.random.default_rng(seed).normal(size=CAD.shape)


def _poses(n: int, tilt_deg: float = 20.0, axes: str = "xyz") -> list[RigidTransform]:
    rng = np.random.default_rng(1)
    out = []
    for _ in range(n):
        rv = np.zeros(3)
        for a in axes:
            rv["xyz".index(a)] = math.radians(rng.uniform(-tilt_deg, tilt_deg))
        out.append(START @ RigidTransform.from_rotvec(rv, rng.uniform(-40, 40, size=3)))
    return out


def _samples(poses: list[RigidTransform], layout: np.ndarray, noise_mm: float = 0.03,
             seed: int = 2) -> list[PoseSample]:
    rng = np.random.default_rng(seed)
    return [PoseSample(i, T, (Z_TRUE @ T).apply(layout) + noise_mm * rng.normal(size=layout.shape))
            for i, T in enumerate(poses)]


def test_recovers_the_true_layout_and_base_pose() -> None:
    layout = _true_layout()
    res = solve_hand_eye(_samples(_poses(20), layout), CAD)
    err = np.sqrt(np.mean(np.sum((res.markers_tcp_mm - layout) ** 2, axis=1)))
    assert err < 0.05
    assert res.T_optical_from_robot.is_close(Z_TRUE, atol_mm=0.1, atol_rad=1e-4)
    assert res.outliers == []
    assert res.poses_used == 15
    assert sum(p.role == "held_out" for p in res.poses) == 5
    assert res.validation_mm_rms is not None
    assert res.validation_mm_rms < 0.1
    assert res.residual_mm_rms < 0.1


@settings(max_examples=5, deadline=None)
@given(st.permutations(list(range(16))))
def test_result_does_not_depend_on_pose_order(perm: list[int]) -> None:
    samples = _samples(_poses(16), _true_layout())
    a = solve_hand_eye(samples, CAD)
    b = solve_hand_eye([samples[i] for i in perm], CAD)
    np.testing.assert_array_equal(a.markers_tcp_mm, b.markers_tcp_mm)
    np.testing.assert_array_equal(a.T_optical_from_robot.as_matrix(), b.T_optical_from_robot.as_matrix())
    assert a.poses == b.poses


def test_a_bad_pose_is_rejected_as_an_outlier() -> None:
    samples = _samples(_poses(20), _true_layout())
    bad = samples[6]
    samples[6] = PoseSample(bad.index, bad.T_robot_from_tcp @ RigidTransform.from_translation((3.0, 0, 0)),
                            bad.markers_optical_mm)   # a stale robot pose paired with a fresh image
    res = solve_hand_eye(samples, CAD)
    if 6 in [p.index for p in res.poses if p.role == "held_out"]:
        pytest.fail("pose 6 should be fitted in this arrangement")
    assert res.outliers == [6]
    assert res.residual_mm_rms < 0.1


def test_too_few_poses() -> None:
    with pytest.raises(RigCalibrationError, match="too few poses: 5 collected, need >= 8"):
        solve_hand_eye(_samples(_poses(5), CAD), CAD)


def test_rotation_about_one_axis_only_is_named() -> None:
    axis_x = r"degenerate rotation axes.*axis \[-?1\.0, -?0\.0, -?0\.0\]"
    with pytest.raises(RigCalibrationError, match=axis_x):
        solve_hand_eye(_samples(_poses(12, axes="x"), CAD), CAD)


def test_poses_without_rotation_are_too_similar() -> None:
    with pytest.raises(RigCalibrationError, match="poses too similar"):
        solve_hand_eye(_samples(_poses(12, tilt_deg=2.0), CAD), CAD)


def test_markers_not_seen_names_the_pose() -> None:
    samples = _samples(_poses(12), CAD)
    m = samples[3].markers_optical_mm.copy()
    m[:2] = np.nan
    samples[3] = PoseSample(3, samples[3].T_robot_from_tcp, m)
    with pytest.raises(RigCalibrationError, match="markers not seen: pose 3 has 2 flange markers"):
        solve_hand_eye(samples, CAD)


def test_a_pose_missing_one_marker_is_still_used() -> None:
    layout = _true_layout()
    samples = _samples(_poses(16), layout)
    m = samples[2].markers_optical_mm.copy()
    m[1] = np.nan
    samples[2] = PoseSample(2, samples[2].T_robot_from_tcp, m)
    res = solve_hand_eye(samples, CAD, SolverSettings(holdout_every=0))
    assert res.poses_used == 16
    assert res.validation_mm_rms is None
    assert np.sqrt(np.mean(np.sum((res.markers_tcp_mm - layout) ** 2, axis=1))) < 0.05


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000))
def test_closed_form_start_is_exact_without_noise(seed: int) -> None:
    from hil.rigcal.handeye import initial_estimate

    rng = np.random.default_rng(seed)
    Z = RigidTransform.from_rotvec(rng.normal(size=3), rng.uniform(-500, 500, size=3))
    poses = [START @ RigidTransform.from_rotvec(rng.uniform(-0.4, 0.4, size=3), rng.uniform(-40, 40, size=3))
             for _ in range(8)]
    samples = [PoseSample(i, T, (Z @ T).apply(CAD)) for i, T in enumerate(poses)]
    Z0, layout0 = initial_estimate(samples, CAD)
    assert Z0.is_close(Z, atol_mm=1e-6, atol_rad=1e-9)
    np.testing.assert_allclose(layout0, CAD, atol=1e-6)


# A stereo calibration a fraction of a pixel off, as the simulator's worst drawn rig showed it:
# scales of a few per mille, depth bent by a few 1e-6 per mm (hil.geometry.projective).
WARP = np.array([0.003, 0.0035, 0.0057, 0.0004, -0.0008, 0.001, 3.6e-6, 1.0e-6, -2.4e-6])


def _warped(samples: list[PoseSample], warp: np.ndarray = WARP) -> list[PoseSample]:
    from hil.geometry.projective import apply_homography, warp_matrix

    pts = np.concatenate([s.markers_optical_mm for s in samples])
    W = warp_matrix(pts.mean(axis=0), warp)
    return [PoseSample(s.index, s.T_robot_from_tcp, apply_homography(W, s.markers_optical_mm))
            for s in samples]


def _layout_err(res_layout: np.ndarray, layout: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((res_layout - layout) ** 2, axis=1))))


def test_a_stereo_calibration_error_stays_out_of_the_layout() -> None:
    layout = _true_layout()
    samples = _warped(_samples(_poses(20), layout, noise_mm=0.01))
    rigid = solve_hand_eye(samples, CAD)
    assert rigid.optical_correction is None
    assert rigid.optical_correction_mm is None
    res = solve_hand_eye(samples, CAD, SolverSettings(optical_correction=True))
    assert _layout_err(rigid.markers_tcp_mm, layout) > 0.15    # the layout took the camera's error
    assert _layout_err(res.markers_tcp_mm, layout) < 0.02
    assert res.residual_mm_rms < 0.03 < rigid.residual_mm_rms
    assert res.optical_correction is not None
    assert res.optical_correction_mm is not None
    assert 0.2 < res.optical_correction_mm < 5.0
    # corrected, the camera measures metric distances again (whatever the rigid gauge)
    corrected = [res.optical_correction.apply(s.markers_optical_mm) for s in samples]
    truth = [(Z_TRUE @ s.T_robot_from_tcp).apply(layout) for s in samples]
    for i, j in ((0, 7), (3, 15), (9, 19)):
        d_meas = np.linalg.norm(corrected[i] - corrected[j], axis=1)
        d_true = np.linalg.norm(truth[i] - truth[j], axis=1)
        np.testing.assert_allclose(d_meas, d_true, atol=0.03)


def test_without_a_stereo_error_the_correction_is_nearly_the_identity() -> None:
    layout = _true_layout()
    res = solve_hand_eye(_samples(_poses(20), layout, noise_mm=0.01), CAD,
                         SolverSettings(optical_correction=True))
    assert res.optical_correction_mm is not None
    assert res.optical_correction_mm < 0.03
    assert _layout_err(res.markers_tcp_mm, layout) < 0.02


def test_a_correction_past_its_bound_is_refused() -> None:
    samples = _warped(_samples(_poses(20), _true_layout(), noise_mm=0.01), 4.0 * WARP)
    with pytest.raises(RigCalibrationError, match=r"stereo calibration disagrees with the arm's motion by "
                                                  r"up to \d+\.\d\d mm .*max_optical_correction_mm"):
        solve_hand_eye(samples, CAD, SolverSettings(optical_correction=True, max_optical_correction_mm=0.5))
