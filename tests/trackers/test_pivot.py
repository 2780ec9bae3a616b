"""Pivot calibration and tracker -> optical registration (hil.tracking)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.errors import CalibrationError
from hil.geometry.transform import RigidTransform
from hil.tracking.pivot import pivot_calibration, tip_in_tracker
from hil.tracking.tracker_registration import StylusTouch, register_tracker_to_optical


def pivot_poses(tip: np.ndarray, pivot: np.ndarray, n: int, rng: np.random.Generator, *,
                cone_rad: float = 0.5, noise_mm: float = 0.0,
                axis_only: bool = False) -> list[RigidTransform]:
    """Sensor poses of a tool whose tip (offset ``tip`` in the sensor frame) rests at ``pivot``."""
    out = []
    for _ in range(n):
        if axis_only:
            rotvec = np.array([0.0, 0.0, rng.uniform(-math.pi, math.pi)])
        else:
            d = rng.normal(size=2)
            rotvec = np.array([*(cone_rad * d / max(1.0, np.linalg.norm(d))), rng.uniform(-math.pi, math.pi)])
        R = RigidTransform.from_rotvec(rotvec).R
        t = pivot - R @ tip + rng.normal(scale=noise_mm, size=3)
        out.append(RigidTransform(R, t))
    return out


@given(st.tuples(*[st.floats(-150, 150)] * 3), st.tuples(*[st.floats(-400, 400)] * 3),
       st.integers(0, 2**32 - 1))
@settings(max_examples=40)
def test_recovers_a_known_tip_offset_exactly_without_noise(tip: tuple[float, ...], pivot: tuple[float, ...],
                                                            seed: int) -> None:
    rng = np.random.default_rng(seed)
    poses = pivot_poses(np.array(tip), np.array(pivot), 20, rng)
    cal = pivot_calibration(poses)
    np.testing.assert_allclose(cal.tip_offset_sensor_mm, tip, atol=1e-6)
    np.testing.assert_allclose(cal.pivot_tracker_mm, pivot, atol=1e-6)
    assert cal.rms_mm < 1e-6


def test_recovers_a_known_tip_offset_with_noise() -> None:
    rng = np.random.default_rng(3)
    tip, pivot = np.array([2.0, -1.5, 145.0]), np.array([310.0, -20.0, 80.0])
    poses = pivot_poses(tip, pivot, 300, rng, noise_mm=0.3)
    cal = pivot_calibration(poses)
    assert np.linalg.norm(cal.tip_offset_sensor_mm - tip) < 0.3
    assert np.linalg.norm(cal.pivot_tracker_mm - pivot) < 0.3
    # Per-pose residual of isotropic 0.3 mm noise: RMS about sqrt(3) x 0.3 mm.
    assert 0.35 < cal.rms_mm < 0.65
    assert cal.n_poses == 300
    assert cal.rotation_spread_deg > 25
    np.testing.assert_allclose(tip_in_tracker(poses[0], cal.tip_offset_sensor_mm), pivot, atol=1.5)


def test_relative_to_a_moving_reference() -> None:
    rng = np.random.default_rng(5)
    tip, pivot_in_ref = np.array([0.0, 0.0, 120.0]), np.array([30.0, 10.0, -5.0])
    rel = pivot_poses(tip, pivot_in_ref, 50, rng)
    refs = [RigidTransform.from_rotvec(rng.normal(scale=0.2, size=3), rng.normal(scale=20, size=3))
            for _ in rel]
    poses = [r @ p for r, p in zip(refs, rel, strict=True)]
    cal = pivot_calibration(poses, references=refs)
    np.testing.assert_allclose(cal.tip_offset_sensor_mm, tip, atol=1e-6)
    np.testing.assert_allclose(cal.pivot_tracker_mm, pivot_in_ref, atol=1e-6)
    with pytest.raises(CalibrationError, match="reference"):
        pivot_calibration(poses, references=refs[:-1])


def test_refuses_degenerate_input() -> None:
    rng = np.random.default_rng(1)
    tip, pivot = np.array([0.0, 0.0, 100.0]), np.zeros(3)
    with pytest.raises(CalibrationError, match="at least 4"):
        pivot_calibration(pivot_poses(tip, pivot, 3, rng))
    with pytest.raises(CalibrationError, match="ill-conditioned"):
        pivot_calibration(pivot_poses(tip, pivot, 30, rng, axis_only=True))
    still = [RigidTransform.from_translation([0, 0, -100])] * 10
    with pytest.raises(CalibrationError, match="swivel"):
        pivot_calibration(still)


MARKERS_OPTICAL = np.array([[0.0, 0.0, 900.0], [80.0, 0.0, 910.0], [0.0, 60.0, 905.0], [70.0, 70.0, 880.0]])


def _touches(T_optical_from_tracker: RigidTransform, tip: np.ndarray, rng: np.random.Generator,
             jitter_mm: float = 0.05) -> list[StylusTouch]:
    touches = []
    T_tracker_from_optical = T_optical_from_tracker.inverse()
    for k, m in enumerate(MARKERS_OPTICAL):
        p_tracker = T_tracker_from_optical.apply(m)
        poses = []
        for _ in range(10):
            R = RigidTransform.from_rotvec(rng.normal(scale=0.4, size=3)).R
            poses.append(RigidTransform(R, p_tracker - R @ tip + rng.normal(scale=jitter_mm, size=3)))
        touches.append(StylusTouch(f"M{k + 1}", tuple(poses)))
    return touches


def test_registration_recovers_the_tracker_to_optical_transform() -> None:
    rng = np.random.default_rng(11)
    T = RigidTransform.from_rotvec([0.3, -1.2, 0.4], [150.0, -40.0, 700.0])
    tip = np.array([1.0, 2.0, 130.0])
    reg = register_tracker_to_optical(_touches(T, tip, rng), MARKERS_OPTICAL, tip)
    assert reg.T_optical_from_tracker.is_close(T, atol_mm=0.1, atol_rad=1e-3)
    assert reg.fre_rms_mm < 0.1
    assert reg.labels == ("M1", "M2", "M3", "M4")
    assert np.all(reg.touch_spread_mm < 0.2)
    doc = reg.to_dict()
    assert len(doc["markers"]) == 4  # type: ignore[arg-type]


def test_registration_refuses_a_shaky_touch_and_bad_layouts() -> None:
    rng = np.random.default_rng(2)
    T = RigidTransform.identity()
    tip = np.array([0.0, 0.0, 100.0])
    shaky = _touches(T, tip, rng, jitter_mm=3.0)
    with pytest.raises(CalibrationError, match="moved"):
        register_tracker_to_optical(shaky, MARKERS_OPTICAL, tip)
    good = _touches(T, tip, rng)
    with pytest.raises(CalibrationError, match="4 touches for 3 markers"):
        register_tracker_to_optical(good, MARKERS_OPTICAL[:3], tip)
    line = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0], [30.0, 0.0, 0.0]])
    with pytest.raises(CalibrationError, match="collinear"):
        register_tracker_to_optical(good, line, tip)


def test_needle_tip_error_against_the_plan() -> None:
    from hil.tracking.needle import needle_tip_error

    T_ot = RigidTransform.from_rotvec([0.0, 0.0, 0.5], [10.0, 0.0, 0.0])
    entry, target = np.array([0.0, 0.0, 800.0]), np.array([0.0, 0.0, 900.0])
    tip_s = np.array([0.0, 0.0, 100.0])  # sensor on the shaft, tip 100 mm ahead along sensor z
    # Needle 2 mm off the path laterally, tip 30 mm short of the target, tilted 0.1 rad.
    R_opt = RigidTransform.from_rotvec([0.1, 0.0, 0.0]).R
    tip_opt = np.array([2.0, 0.0, 870.0])
    T_opt_sensor = RigidTransform(R_opt, tip_opt - R_opt @ tip_s)
    T_tracker_sensor = T_ot.inverse() @ T_opt_sensor
    err = needle_tip_error(T_tracker_sensor, tip_s, T_ot, entry, target)
    np.testing.assert_allclose(err.tip_optical_mm, tip_opt, atol=1e-9)
    assert err.lateral_error_mm == pytest.approx(2.0)
    assert err.depth_to_target_mm == pytest.approx(30.0)
    assert err.distance_to_target_mm == pytest.approx(math.hypot(2.0, 30.0))
    assert err.direction_error_rad == pytest.approx(0.1)


def test_reference_motion_maps_planned_points_to_where_they_are_now() -> None:
    from hil.tracking.needle import reference_motion

    T_ot = RigidTransform.from_rotvec([0.3, -0.2, 1.0], [100.0, 50.0, 700.0])
    motion_opt = RigidTransform.from_rotvec([0.0, 0.02, 0.0], [0.0, 0.0, 6.0])  # breathing-like
    ref_then = RigidTransform.from_rotvec([0.1, 0.2, 0.3], [200.0, 0.0, 50.0])
    ref_now = T_ot.inverse() @ motion_opt @ T_ot @ ref_then
    M = reference_motion(T_ot, ref_then, ref_now)
    assert M.is_close(motion_opt, atol_mm=1e-9, atol_rad=1e-12)
