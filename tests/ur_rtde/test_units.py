"""Driver boundary units: pose/unit conversion, safety bits, move timing, config, factory."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from drivers.interfaces.errors import ProtocolError
from drivers.interfaces.lifecycle import DeviceState
from drivers.interfaces.robot import MotionLimits, SafetyStatus
from drivers.ur_rtde.config import UrRtdeConfig, UrRtdeRobotConfig
from drivers.ur_rtde.plugin import factory
from drivers.ur_rtde.robot import UrRtdeRobot, pose_from_ur, pose_to_ur, safety_from_bits, trapezoid_time_s
from hil.clock import ManualClock
from hil.geometry.transform import RigidTransform
from plugins.registry import DriverContext

coord = st.floats(-2000, 2000, allow_nan=False)
rv = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3)


@given(x=coord, y=coord, z=coord, rotvec=rv)
def test_pose_round_trip_mm_to_ur_and_back(x: float, y: float, z: float, rotvec: list[float]) -> None:
    T = RigidTransform.from_rotvec(rotvec, [x, y, z])
    ur = pose_to_ur(T)
    np.testing.assert_allclose(ur[:3], np.array([x, y, z]) / 1000.0, rtol=0, atol=1e-12)
    assert T.is_close(pose_from_ur(ur), atol_mm=1e-9, atol_rad=1e-9)


def test_pose_from_ur_is_metres_and_axis_angle() -> None:
    T = pose_from_ur([0.1, -0.2, 0.3, 0.0, 0.0, math.pi / 2])
    np.testing.assert_allclose(T.t, [100.0, -200.0, 300.0])
    np.testing.assert_allclose(T.apply_vector([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("bad", [[0.0] * 5, [0.0, 0.0, 0.0, 0.0, math.nan, 0.0]])
def test_pose_from_ur_rejects_garbage(bad: list[float]) -> None:
    with pytest.raises(ProtocolError, match="6 finite numbers"):
        pose_from_ur(bad)


@pytest.mark.parametrize(
    ("bits", "expected"),
    [
        (1, SafetyStatus.NORMAL),
        ((1 << 2) | (1 << 10), SafetyStatus.PROTECTIVE_STOP),
        (1 << 4, SafetyStatus.PROTECTIVE_STOP),          # safeguard stop
        ((1 << 6) | (1 << 7) | (1 << 10), SafetyStatus.EMERGENCY_STOP),
        (1 << 5, SafetyStatus.EMERGENCY_STOP),           # system e-stop
        ((1 << 2) | (1 << 7), SafetyStatus.EMERGENCY_STOP),  # e-stop wins
        (1 << 9, SafetyStatus.FAULT),
        (1 << 8, SafetyStatus.FAULT),
    ],
)
def test_safety_bits_map_to_status(bits: int, expected: SafetyStatus) -> None:
    assert safety_from_bits(bits) is expected


def test_trapezoid_time() -> None:
    assert trapezoid_time_s(0.0, 100.0, 500.0) == 0.0
    assert trapezoid_time_s(50.0, 100.0, 500.0) == pytest.approx(0.7)  # 0.2 + 0.3 + 0.2
    assert trapezoid_time_s(10.0, 100.0, 500.0) == pytest.approx(2 * math.sqrt(10.0 / 500.0))


def test_config_defaults_and_rates() -> None:
    cfg = UrRtdeRobotConfig(driver="ur_rtde", host="10.0.0.2")
    assert cfg.rate_hz == 125.0
    assert cfg.servo_lookahead_time_s == 0.05
    assert cfg.servo_gain == 500.0
    assert UrRtdeRobotConfig(driver="ur_rtde", host="h", controller="e_series").rate_hz == 500.0
    assert UrRtdeConfig is UrRtdeRobotConfig


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"hostname": "x"}, "Extra inputs are not permitted"),
        ({"servo_lookahead_time_s": 0.01}, "greater than or equal to 0.03"),
        ({"servo_gain": 5000}, "less than or equal to 2000"),
        ({"frequency_hz": 500.0}, "exceeds the cb3 RTDE rate 125 Hz"),
        ({"controller": "cb2"}, "Input should be 'cb3' or 'e_series'"),
    ],
)
def test_config_rejects_bad_values(fields: dict[str, object], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        UrRtdeRobotConfig.model_validate({"driver": "ur_rtde", "host": "h", **fields})


def test_factory_builds_a_configured_robot_without_connecting() -> None:
    ctx = DriverContext(role="robot", clock=ManualClock(), limits=MotionLimits(), config_dir=Path("."))
    r = factory(UrRtdeRobotConfig(driver="ur_rtde", host="192.0.2.1", controller="e_series"), ctx)
    assert isinstance(r, UrRtdeRobot)
    assert r.state is DeviceState.CONFIGURED
    assert r.control_rate_hz == 500.0
    assert r.name == "robot"
