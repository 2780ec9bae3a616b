"""The rate limiter about a pivot (hil.servo.limiter, issue 41): the guide's axis stays through
the entry while a turn is clipped, and the TCP never exceeds the translation limits."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.interfaces.robot import MotionLimits
from hil.controller.compensation import limiter_args
from hil.controller.config import ProcedureConfig
from hil.errors import GeometryError
from hil.geometry.transform import RigidTransform
from hil.safety.servo_check import servo_step_violation
from hil.servo.limiter import RateLimiter

DT_S = 0.002
PIVOT_MM = (0.0, 0.0, 90.0)   # the entry, 90 mm down the TCP's z axis
HOME = RigidTransform.from_rotvec((math.pi, 0.0, 0.0), (100.0, 200.0, 300.0))


def _turned_about_pivot(T: RigidTransform, rotvec_rad: tuple[float, float, float],
                        shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> RigidTransform:
    """``T`` turned by ``rotvec_rad`` (base frame) about its pivot point, the pivot then shifted."""
    p = T.apply(np.array(PIVOT_MM))
    turn = RigidTransform.from_rotvec(rotvec_rad, np.zeros(3))
    to_pivot = RigidTransform.from_translation(-p)
    return RigidTransform.from_translation(p + np.asarray(shift_mm)) @ turn @ to_pivot @ T


def _pivot_track(rl: RateLimiter, goal: RigidTransform,
                 steps: int) -> tuple[list[float], list[RigidTransform]]:
    """The pivot point's distance from where it started, and the commands, over ``steps``."""
    assert rl.command is not None
    p0 = rl.command.apply(np.array(PIVOT_MM))
    off, cmds = [], []
    for _ in range(steps):
        c = rl.step(goal, DT_S)
        cmds.append(c)
        off.append(float(np.linalg.norm(c.apply(np.array(PIVOT_MM)) - p0)))
    return off, cmds


def test_a_clipped_turn_about_the_entry_keeps_the_entry_on_the_axis() -> None:
    goal = _turned_about_pivot(HOME, (0.15, 0.05, 0.0))   # 9 deg about the entry, entry fixed
    about_entry = RateLimiter(60.0, 400.0, 0.5, 2.0, PIVOT_MM)
    about_entry.reset(HOME)
    off, cmds = _pivot_track(about_entry, goal, 600)
    assert max(off) < 1e-6                                                   # the entry never moves
    assert cmds[-1].t == pytest.approx(goal.t, abs=1e-6)
    assert cmds[-1].rotation_angle_rad() == pytest.approx(goal.rotation_angle_rad(), abs=1e-9)
    # about the TCP, the same limits move the TCP straight to its goal while the turn lags behind:
    # the axis leaves the entry by millimetres on the way
    about_tcp = RateLimiter(60.0, 400.0, 0.5, 2.0)
    about_tcp.reset(HOME)
    off_tcp, cmds_tcp = _pivot_track(about_tcp, goal, 600)
    assert max(off_tcp) > 3.0
    assert cmds_tcp[-1].t == pytest.approx(goal.t, abs=1e-6)


def test_the_entry_follows_its_own_motion_while_the_turn_lags() -> None:
    # the entry moves 4 mm and the path turns 9 deg: the entry arrives at the translation's pace
    goal = _turned_about_pivot(HOME, (0.15, 0.05, 0.0), shift_mm=(4.0, 0.0, -1.0))
    rl = RateLimiter(60.0, 400.0, 0.5, 2.0, PIVOT_MM)
    rl.reset(HOME)
    p_goal = goal.apply(np.array(PIVOT_MM))
    arrived = None
    for k in range(600):
        c = rl.step(goal, DT_S)
        if arrived is None and float(np.linalg.norm(c.apply(np.array(PIVOT_MM)) - p_goal)) < 1e-3:
            arrived = k
            turn_left_rad = (c.inverse() @ goal).rotation_angle_rad()
    assert arrived is not None
    assert arrived * DT_S < 0.3           # 4.1 mm at 400 mm/s^2: 0.2 s bang-bang, ~0.27 s braking early
    assert turn_left_rad > 0.03           # while the turn (0.16 rad at 2 rad/s^2: 0.57 s) goes on


def test_the_tcp_keeps_to_the_translation_limits_with_a_long_lever() -> None:
    # 300 mm down the axis, a turn at 0.5 rad/s would move the TCP at 150 mm/s: held to 50
    pivot = (0.0, 0.0, 300.0)
    rl = RateLimiter(50.0, 200.0, 0.5, 2.0, pivot)
    rl.reset(HOME)
    p = HOME.apply(np.array(pivot))
    turn = RigidTransform.from_rotvec((0.6, 0.0, 0.0), np.zeros(3))
    goal = RigidTransform.from_translation(p) @ turn @ RigidTransform.from_translation(-p) @ HOME
    v_prev = np.zeros(3)
    prev = HOME
    for _ in range(3000):
        c = rl.step(goal, DT_S)
        v = (c.t - prev.t) / DT_S
        assert float(np.linalg.norm(v)) <= 50.0 * (1 + 1e-6)
        assert float(np.linalg.norm(v - v_prev)) / DT_S <= 200.0 * (1 + 1e-6)
        assert float(np.linalg.norm(c.apply(np.array(pivot)) - p)) < 1e-6   # still about the entry
        v_prev, prev = v, c
    assert prev.t == pytest.approx(goal.t, abs=1e-3)


@settings(max_examples=60, deadline=None)
@given(pivot_z=st.floats(0.0, 400.0), seed=st.integers(0, 2**31 - 1), scale=st.floats(0.05, 1.0))
def test_no_step_ever_breaks_the_servo_check(pivot_z: float, seed: int, scale: float) -> None:
    """Whatever the targets (jumps, turns, reversals) and the pivot, every step passes the servo
    loop's own step check against limits equal to the limiter's."""
    rng = np.random.default_rng(seed)
    limits = MotionLimits(workspace_min_mm=(-1e4,) * 3, workspace_max_mm=(1e4,) * 3, max_speed_mm_s=60.0,
                          max_accel_mm_s2=400.0, max_angular_speed_rad_s=0.5)
    rl = RateLimiter(60.0, 400.0, 0.5, 2.0, (0.0, 0.0, pivot_z))
    rl.reset(HOME)
    prev, v_prev = HOME, np.zeros(3)
    goal = HOME
    for k in range(400):
        if k % 25 == 0:
            goal = RigidTransform.from_rotvec(rng.normal(0.0, 0.3, 3), rng.normal(0.0, 20.0, 3)) @ HOME
        c = rl.step(goal, DT_S, speed_scale=scale)
        assert servo_step_violation(limits, prev.R, prev.t, v_prev, c.R, c.t, DT_S) is None
        assert rl.velocity_mm_s is not None
        prev, v_prev = c, rl.velocity_mm_s


def test_a_pivot_that_is_not_a_point_is_refused() -> None:
    with pytest.raises(GeometryError, match="pivot_tcp_mm"):
        RateLimiter(60.0, 400.0, 0.5, 2.0, (0.0, math.nan, 1.0))


def test_the_configured_pivot_is_the_entry_down_the_guide() -> None:
    T_tcp_from_guide = RigidTransform.from_rotvec((0.0, 0.0, 0.3), (1.0, 2.0, 60.0))
    proc = ProcedureConfig.model_validate({"planning": {"standoff_mm": 25.0}})
    *limits, pivot = limiter_args(proc, T_tcp_from_guide)
    assert limits == [60.0, 400.0, 0.5, 2.0]
    assert pivot == pytest.approx((1.0, 2.0, 85.0))
    tcp = ProcedureConfig.model_validate({"compensation": {"rate_limit_pivot": "tcp"}})
    assert limiter_args(tcp, T_tcp_from_guide)[4] == (0.0, 0.0, 0.0)
