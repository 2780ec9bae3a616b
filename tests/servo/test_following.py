"""Following-error supervision (hil.safety.following): an arm that follows with the modelled lag
never faults, whatever the commands; one that stalls or turns away faults after exactly the bound's
duration, with the figures; a divergence shorter than the duration is tolerated."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.interfaces.robot import FollowingModel, MotionLimits
from hil.geometry.transform import rotvec_to_matrix
from hil.safety.following import FollowingMonitor

DT_S = 0.002
MODEL = FollowingModel(0.03, 2.0, 1.5, 0.1, "test arm")


def _lagged_arm(commands: list[np.ndarray], tau_s: float) -> list[np.ndarray]:
    """Positions of an arm that follows ``commands`` (one per period) through a first-order lag:
    what the arm reports at the start of each period."""
    a = 1.0 - math.exp(-DT_S / tau_s)
    out, x = [], commands[0].copy()
    for c in commands:
        out.append(x.copy())
        x = x + (c - x) * a
    return out


def _piecewise_commands(velocities: list[tuple[float, float, float]]) -> list[np.ndarray]:
    """Commands one period apart from (0, 0, 300) mm: piecewise-constant velocities (mm/s; up to
    60, the compensation limit), 20 periods each."""
    cmds, x = [], np.array([0.0, 0.0, 300.0])
    for v in velocities:
        for _ in range(20):
            x = x + np.asarray(v) * DT_S
            cmds.append(x.copy())
    return cmds


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-60.0, 60.0)] * 3), min_size=2, max_size=30))
def test_an_arm_that_follows_with_the_modelled_lag_never_faults(
        velocities: list[tuple[float, float, float]]) -> None:
    cmds = _piecewise_commands(velocities)
    arm = _lagged_arm(cmds, MODEL.time_constant_s)
    mon = FollowingMonitor(MODEL)
    mon.start(np.eye(3), arm[0])
    for k, (c, a) in enumerate(zip(cmds, arm, strict=True)):
        assert mon.update(k * 2_000_000, np.eye(3), c, np.eye(3), a) is None
        assert mon.last_error_mm < 1e-9


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-60.0, 60.0)] * 3), min_size=2, max_size=12),
       st.integers(0, 40))
def test_a_stamped_old_report_is_compared_with_the_expectation_when_it_was_sampled(
        velocities: list[tuple[float, float, float]], age_periods: int) -> None:
    # the same healthy arm, its every report `age_periods` old (up to 80 ms) and stamped so
    cmds = _piecewise_commands(velocities)
    arm = _lagged_arm(cmds, MODEL.time_constant_s)
    mon = FollowingMonitor(MODEL)
    mon.start(np.eye(3), arm[0])
    for k, c in enumerate(cmds):
        j = max(k - age_periods, 0)
        assert mon.update(k * 2_000_000, np.eye(3), c, np.eye(3), arm[j], sample_t_ns=j * 2_000_000) is None
        assert mon.last_error_mm < 1e-9


def _x(mm: float) -> np.ndarray:
    """A point ``mm`` along x from (0, 0, 300) mm."""
    return np.array([mm, 0.0, 300.0])


def test_a_sample_time_between_updates_is_interpolated_and_one_before_the_session_is_its_start() -> None:
    mon = FollowingMonitor(FollowingModel(0.0, 2.0, 1.5, 0.1, "no lag"))   # expectation = last command
    p0 = _x(0.0)
    mon.start(np.eye(3), p0)
    for k in range(5):   # commands 1 mm apart in x; the expectation at update k is command k - 1
        mon.update(10**9 + k * 2_000_000, np.eye(3), _x(k + 1.0), np.eye(3), p0)
    # the expectation at update 4 (t = 8 ms) is x = 4 mm, at update 3 (6 ms) x = 3 mm
    mon.update(10**9 + 10_000_000, np.eye(3), _x(6.0), np.eye(3), _x(3.25),
               sample_t_ns=10**9 + 6_500_000)
    assert mon.last_error_mm == pytest.approx(0.0, abs=1e-12)
    mon.update(10**9 + 12_000_000, np.eye(3), _x(7.0), np.eye(3), p0,
               sample_t_ns=10**9 - 50_000_000)   # sampled before the session: it rested at p0
    assert mon.last_error_mm == pytest.approx(0.0, abs=1e-12)
    mon.update(10**9 + 14_000_000, np.eye(3), _x(8.0), np.eye(3), _x(7.0),
               sample_t_ns=10**9 + 20_000_000)   # stamped after the update: the newest expectation
    assert mon.last_error_mm == pytest.approx(0.0, abs=1e-12)


def test_a_stalled_arm_faults_after_exactly_the_duration_with_the_figures() -> None:
    mon = FollowingMonitor(MODEL)
    stalled = np.array([0.0, 0.0, 300.0])
    mon.start(np.eye(3), stalled)
    fault, k = None, 0
    first_beyond: int | None = None
    while fault is None:
        cmd = stalled + np.array([10.0 * k * DT_S, 0.0, 0.0])   # the target moves on at 10 mm/s
        fault = mon.update(k * 2_000_000, np.eye(3), cmd, np.eye(3), stalled)
        if first_beyond is None and mon.last_error_mm > MODEL.max_error_mm:
            first_beyond = k
        k += 1
    assert first_beyond is not None
    assert (k - 1 - first_beyond) * DT_S == pytest.approx(MODEL.max_duration_s)
    assert fault.duration_s == pytest.approx(0.1)
    assert 2.0 < fault.error_mm == fault.max_error_mm < 3.1
    assert fault.error_deg == 0.0
    assert fault.actual_mm == (0.0, 0.0, 300.0)
    assert "arm not following its servo targets" in fault.message()
    assert "bound 2 mm / 1.5 deg for 100 ms, servo lag 30 ms: test arm" in fault.message()
    assert not mon.active   # reported once; the caller ends the session


def test_a_divergence_shorter_than_the_duration_is_tolerated() -> None:
    mon = FollowingMonitor(MODEL)
    p = np.array([0.0, 0.0, 300.0])
    mon.start(np.eye(3), p)
    for k in range(200):
        glitch = 40 <= k < 40 + 49   # 98 ms beyond the bound, then back
        actual = p + (np.array([5.0, 0.0, 0.0]) if glitch else 0.0)
        assert mon.update(k * 2_000_000, np.eye(3), p, np.eye(3), actual) is None


def test_an_arm_that_turns_away_faults_on_the_angle() -> None:
    mon = FollowingMonitor(MODEL)
    p = np.array([0.0, 0.0, 300.0])
    mon.start(np.eye(3), p)
    turned = rotvec_to_matrix(np.array([0.0, 0.0, math.radians(2.0)]))
    fault = None
    for k in range(100):
        fault = mon.update(k * 2_000_000, np.eye(3), p, turned, p)
        if fault is not None:
            break
    assert fault is not None
    assert fault.error_mm == 0.0
    assert fault.error_deg == pytest.approx(2.0, abs=1e-6)


def test_safety_overrides_replace_the_robots_bounds_and_say_so() -> None:
    limits = MotionLimits(following_error_mm=0.5, following_error_duration_s=0.05)
    m = limits.following(MODEL)
    assert (m.time_constant_s, m.max_error_mm, m.max_error_deg, m.max_duration_s) == (0.03, 0.5, 1.5, 0.05)
    assert m.source == "test arm; bounds from [safety]"
    assert MotionLimits().following(MODEL) is MODEL
    with pytest.raises(ValueError, match="bounds > 0"):
        FollowingModel(0.03, 0.0, 1.5, 0.1)
