"""Calibration poses inside a safe cone about the start pose, checked before the arm moves.

Pose ``i`` of ``n`` (deterministic, no randomness): the tool axis tilted by ``cone * sqrt((i +
0.5) / n)`` towards the golden-angle azimuth ``i * 137.5 deg`` (a sunflower pattern: tilts fill
the cone evenly, about every axis), turned about the tool axis by ``spin * (1, -1, 0.5, -0.5, ...)``
and moved by up to ``radius_mm`` per axis (another sunflower in x/y, z alternating). Tilt axes of
many directions are what keeps the hand-eye solution non-degenerate.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.errors import LimitViolationError
from drivers.interfaces.robot import MotionLimits
from hil.geometry.transform import RigidTransform
from hil.kinematics.ur import UR3_JOINT_LIMITS_RAD, ur_inverse
from hil.rigcal.config import RigCalibrationConfig
from hil.rigcal.handeye import RigCalibrationError

FloatArray = NDArray[np.float64]
_GOLDEN_RAD = math.pi * (3.0 - math.sqrt(5.0))


def calibration_poses(start: RigidTransform, cfg: RigCalibrationConfig) -> list[RigidTransform]:
    """``cfg.poses`` TCP poses (robot base frame) about ``start`` (see the module doc)."""
    n = cfg.poses
    cone = math.radians(cfg.cone_half_angle_deg)
    spin = math.radians(cfg.spin_deg)
    spins = (1.0, -1.0, 0.5, -0.5, 0.0)
    out = []
    for i in range(n):
        frac = math.sqrt((i + 0.5) / n)
        az = i * _GOLDEN_RAD
        tilt = RigidTransform.from_rotvec((cone * frac * math.cos(az), cone * frac * math.sin(az), 0.0))
        turn = RigidTransform.from_rotvec((0.0, 0.0, spin * spins[i % len(spins)]))
        az2 = i * _GOLDEN_RAD + 1.0
        d = cfg.radius_mm * np.array([frac * math.cos(az2), frac * math.sin(az2), (-1.0) ** i * (1.0 - frac)])
        out.append(RigidTransform(start.R @ tilt.R @ turn.R, start.t + d))
    return out


def check_poses(poses: list[RigidTransform], limits: MotionLimits, device: str,
                T_flange_from_tcp: RigidTransform, robot_model: str | None) -> None:
    """Every pose inside the workspace box and, for a UR model, with an inverse-kinematics solution
    within the joint limits -- checked before the arm moves.

    Raises:
        RigCalibrationError: the first pose that fails, with its number and position.
    """
    T_tcp_from_flange = T_flange_from_tcp.inverse()
    for i, T in enumerate(poses):
        where = f"pose {i} at {np.round(T.t, 1).tolist()} mm"
        try:
            limits.check_position(device, T.t)
        except LimitViolationError as exc:
            raise RigCalibrationError(f"{where} cannot be reached: {exc.message}; lower "
                                      "[rig_calibration] radius_mm or move the start pose") from None
        if robot_model is None:
            continue
        sols = ur_inverse(T @ T_tcp_from_flange, robot_model)
        lo, hi = UR3_JOINT_LIMITS_RAD[:, 0], UR3_JOINT_LIMITS_RAD[:, 1]
        ok = [q for q in sols if np.all(q >= lo) and np.all(q <= hi)]
        if not ok:
            raise RigCalibrationError(f"{where} cannot be reached: no inverse kinematics of the "
                                      f"{robot_model} within its joint limits; lower [rig_calibration] "
                                      "cone_half_angle_deg / radius_mm or move the start pose")
