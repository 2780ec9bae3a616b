"""The straight-line move the servo loop streams (hil/servo/trajectory.py): it starts at the start
pose at rest and ends exactly on the target at rest, its position stays on the segment and its
attitude on the one rotation between them, and sampled at a servo period its speeds and
(second-difference) accelerations never exceed the limits it was given."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.errors import GeometryError
from hil.geometry.transform import RigidTransform
from hil.servo.trajectory import LinearMove

PERIOD_S = 0.002
finite = st.floats(-300.0, 300.0, allow_nan=False)
rotvec = st.tuples(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5), st.floats(-1.5, 1.5))


def _move(delta_mm: tuple[float, float, float], rv: tuple[float, float, float], speed: float = 50.0,
          accel: float = 200.0, w: float = 0.5, alpha: float = 2.0) -> LinearMove:
    start = RigidTransform.from_rotvec((0.1, -0.2, 0.3), (100.0, -50.0, 300.0))
    target = RigidTransform(RigidTransform.from_rotvec(rv).R @ start.R, start.t + np.asarray(delta_mm))
    return LinearMove(start, target, speed_mm_s=speed, accel_mm_s2=accel, angular_speed_rad_s=w,
                      angular_accel_rad_s2=alpha)


def _samples(m: LinearMove) -> tuple[np.ndarray, list[RigidTransform]]:
    n = math.ceil(m.duration_s / PERIOD_S) + 2
    poses = [m.pose_at(k * PERIOD_S)[0] for k in range(n + 1)]
    return np.array([T.t for T in poses]), poses


def test_a_long_move_cruises_at_its_speed_with_trapezoid_timing() -> None:
    m = _move((100.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    # 100 mm at 50 mm/s, 200 mm/s^2: 0.25 s up, 1.75 s cruise, 0.25 s down
    assert m.t_accel_s == pytest.approx(0.25)
    assert m.duration_s == pytest.approx(2.25)
    pose, v, w = m.pose_at(1.0)
    assert np.linalg.norm(v) == pytest.approx(50.0)
    assert pose.t[0] - 100.0 == pytest.approx(0.5 * 200.0 * 0.25**2 + 50.0 * 0.75)
    assert np.all(w == 0.0)


def test_a_short_move_is_a_triangle_that_never_reaches_the_speed() -> None:
    m = _move((4.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    # 4 mm at 200 mm/s^2: 2 mm up in sqrt(2*2/200) s, 2 mm down
    assert m.duration_s == pytest.approx(2 * math.sqrt(0.02))
    _, v, _ = m.pose_at(m.duration_s / 2)
    assert np.linalg.norm(v) == pytest.approx(200.0 * math.sqrt(0.02))


def test_the_rotation_can_set_the_pace() -> None:
    m = _move((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))   # 1 rad at 0.5 rad/s dominates 1 mm
    assert m.duration_s == pytest.approx(1.0 / 0.5 + 0.5 / 2.0)
    _, v, w = m.pose_at(1.0)
    assert np.linalg.norm(w) == pytest.approx(0.5)
    assert np.linalg.norm(v) == pytest.approx(0.5)   # translation in step: 1 mm over the same profile


def test_no_motion_is_an_empty_move_at_the_target() -> None:
    m = _move((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert m.duration_s == 0.0
    assert m.done(0.0)
    assert m.pose_at(0.0)[0] is m.target


@pytest.mark.parametrize("kwargs", [{"speed": 0.0}, {"speed": math.inf}, {"accel": -1.0}, {"w": math.nan},
                                    {"alpha": 0.0}])
def test_bad_limits_are_refused_naming_the_limit(kwargs: dict[str, float]) -> None:
    with pytest.raises(GeometryError, match="must be"):
        _move((10.0, 0.0, 0.0), (0.0, 0.0, 0.0), **kwargs)


def test_an_infinite_acceleration_does_not_bind() -> None:
    m = _move((0.0, 0.0, 0.0), (0.0, 0.0, 0.5), alpha=math.inf)
    assert m.duration_s == pytest.approx(0.5 / 0.5)
    assert np.all(np.isfinite(m.pose_at(0.3)[0].t))


@settings(max_examples=60, deadline=None)
@given(delta=st.tuples(finite, finite, finite), rv=rotvec, speed=st.floats(5.0, 100.0),
       accel=st.floats(50.0, 1000.0))
def test_sampled_moves_stay_within_every_limit_and_end_on_the_target(
        delta: tuple[float, float, float], rv: tuple[float, float, float], speed: float,
        accel: float) -> None:
    m = _move(delta, rv, speed, accel)
    t, poses = _samples(m)
    start, target = m.start, m.target
    assert np.allclose(t[0], start.t, atol=1e-9)
    assert poses[0].is_close(start, 1e-9, 1e-9)
    assert poses[-1].is_close(target, 1e-9, 1e-9)
    # on the segment
    d = target.t - start.t
    if np.linalg.norm(d) > 1e-6:
        s = (t - start.t) @ d / (d @ d)
        assert np.all((s >= -1e-9) & (s <= 1 + 1e-9))
        assert np.allclose(start.t + np.outer(s, d), t, atol=1e-6)
    # speed and acceleration at the period
    vel = np.diff(t, axis=0) / PERIOD_S
    acc = np.diff(vel, axis=0) / PERIOD_S
    tol = 1 + 1e-6
    assert np.linalg.norm(vel, axis=1).max() <= speed * tol
    assert np.linalg.norm(acc, axis=1).max() <= accel * tol
    ang = [(a.inverse() @ b).rotation_angle_rad() / PERIOD_S for a, b in itertools.pairwise(poses)]
    assert max(ang) <= 0.5 * tol
