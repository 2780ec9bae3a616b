"""PLAN: the needle-guide pose on the planned path, and its reachability (UR3 inverse kinematics).

Frames: ``guide`` is the needle-guide frame (its z axis is the needle direction, its origin the
guide tip), fixed on the flange by ``T_flange_from_guide``; the robot reports and takes
``T_robot_from_tcp`` poses (the driver's TCP; ``T_flange_from_tcp``, identity when TCP = flange).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.robot import MotionLimits
from hil.controller.config import PlanningConfig
from hil.errors import GeometryError, HilError
from hil.geometry.transform import RigidTransform
from hil.kinematics.ur import UR3_JOINT_LIMITS_RAD, UR3_REACH_MM, ur_inverse

FloatArray = NDArray[np.float64]


class PlanRefusedError(HilError):
    """The plan cannot be executed; ``reason`` says why (shown to the operator)."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(f"plan refused: {reason}")


@dataclass(frozen=True)
class RigGeometry:
    """Fixed geometry of the end effector.

    Attributes:
        T_flange_from_guide: the guide frame on the flange (mm).
        flange_markers_mm: (M, 3) ring-marker centres on the flange plate, flange frame.
        T_flange_from_tcp: the driver's TCP on the flange (identity when TCP = flange).
    """

    T_flange_from_guide: RigidTransform
    flange_markers_mm: FloatArray
    T_flange_from_tcp: RigidTransform = field(default_factory=RigidTransform.identity)

    @property
    def T_tcp_from_guide(self) -> RigidTransform:
        return self.T_flange_from_tcp.inverse() @ self.T_flange_from_guide

    @property
    def flange_markers_tcp_mm(self) -> FloatArray:
        """The flange markers in the TCP frame."""
        return self.T_flange_from_tcp.inverse().apply(self.flange_markers_mm)


@dataclass(frozen=True)
class GuidePlan:
    """A reachable guide pose at the stand-off (robot frame, mm).

    Attributes:
        entry_robot_mm, target_robot_mm: the path in the robot frame (at registration).
        T_robot_from_guide: guide at the stand-off, z along entry->target.
        T_robot_from_tcp: the TCP pose to command for it.
        q_rad: the inverse-kinematics solution chosen (nearest the current joints), or None when
            kinematics are not checked.
        standoff_mm: distance of the guide origin above the entry along the path.
    """

    entry_robot_mm: FloatArray
    target_robot_mm: FloatArray
    T_robot_from_guide: RigidTransform
    T_robot_from_tcp: RigidTransform
    q_rad: FloatArray | None
    standoff_mm: float

    @property
    def axis_robot(self) -> FloatArray:
        d = self.target_robot_mm - self.entry_robot_mm
        out: FloatArray = d / np.linalg.norm(d)
        return out


def guide_pose_on_path(
    entry_mm: FloatArray, target_mm: FloatArray, standoff_mm: float,
    x_hint: FloatArray | None = None,
) -> RigidTransform:
    """The guide pose whose z axis runs from entry to target and whose origin is ``standoff_mm``
    before the entry on that line (seed 001 2.3: the guide tube points along the path).

    The roll about the axis is free; it is chosen so the guide x axis is as close as possible to
    ``x_hint`` (e.g. the current guide x axis, so the wrist does not spin), else to robot x.

    Raises:
        GeometryError: entry and target coincide.
    """
    d = np.asarray(target_mm, dtype=np.float64) - np.asarray(entry_mm, dtype=np.float64)
    n = float(np.linalg.norm(d))
    if n < 1e-6:
        raise GeometryError("entry and target coincide; the path has no direction")
    z = d / n
    candidates = [] if x_hint is None else [np.asarray(x_hint, dtype=np.float64)]
    candidates += [np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])]
    for h in candidates:
        x = h - float(h @ z) * z
        if float(np.linalg.norm(x)) > 1e-3:
            x = x / np.linalg.norm(x)
            break
    y = np.cross(z, x)
    R = np.column_stack([x, y, z])
    return RigidTransform(R, np.asarray(entry_mm, dtype=np.float64) - standoff_mm * z)


def plan_guide(
    entry_robot_mm: FloatArray, target_robot_mm: FloatArray, rig: RigGeometry, cfg: PlanningConfig,
    limits: MotionLimits, *, q_near: FloatArray | None = None, x_hint: FloatArray | None = None,
) -> GuidePlan:
    """Place the guide on the path at the stand-off and check that the robot can go there.

    Checks, in order: a path direction exists; the TCP lies in the workspace box; the flange is
    within the arm's reach; an inverse-kinematics solution exists; it keeps ``joint_margin_rad``
    from every joint limit. The solution nearest ``q_near`` is kept.

    Raises:
        PlanRefusedError: with the first failed check as the reason.
    """
    try:
        T_robot_from_guide = guide_pose_on_path(entry_robot_mm, target_robot_mm, cfg.standoff_mm, x_hint)
    except GeometryError as exc:
        raise PlanRefusedError(str(exc)) from None
    T_robot_from_tcp = T_robot_from_guide @ rig.T_tcp_from_guide.inverse()
    p = T_robot_from_tcp.t
    lo, hi = np.asarray(limits.workspace_min_mm), np.asarray(limits.workspace_max_mm)
    if np.any(p < lo) or np.any(p > hi):
        raise PlanRefusedError(
            f"stand-off TCP {np.round(p, 1).tolist()} mm lies outside the workspace box "
            f"{list(limits.workspace_min_mm)}..{list(limits.workspace_max_mm)} mm")
    q: FloatArray | None = None
    if cfg.check_kinematics:
        T_robot_from_flange = T_robot_from_tcp @ rig.T_flange_from_tcp.inverse()
        reach = float(np.linalg.norm(T_robot_from_flange.t))
        if reach > UR3_REACH_MM + 100.0:
            raise PlanRefusedError(f"stand-off flange {reach:.0f} mm from the base is beyond the "
                                   f"{cfg.robot_model} reach ({UR3_REACH_MM:.0f} mm)")
        sols = ur_inverse(T_robot_from_flange, cfg.robot_model, q_near)
        if len(sols) == 0:
            raise PlanRefusedError(f"no inverse-kinematics solution for the stand-off pose "
                                   f"(flange at {np.round(T_robot_from_flange.t, 1).tolist()} mm)")
        lo_q = UR3_JOINT_LIMITS_RAD[:, 0] + cfg.joint_margin_rad
        hi_q = UR3_JOINT_LIMITS_RAD[:, 1] - cfg.joint_margin_rad
        ok = [s for s in sols if np.all(s >= lo_q) and np.all(s <= hi_q)]
        if not ok:
            raise PlanRefusedError(f"all {len(sols)} inverse-kinematics solutions come within "
                                   f"{cfg.joint_margin_rad} rad of a joint limit")
        q = ok[0]
    entry = np.asarray(entry_robot_mm, dtype=np.float64)
    target = np.asarray(target_robot_mm, dtype=np.float64)
    return GuidePlan(entry, target, T_robot_from_guide, T_robot_from_tcp, q, cfg.standoff_mm)
