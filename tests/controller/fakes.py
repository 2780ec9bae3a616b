"""A minimal in-memory robot, a base for stub cameras, and an estimate with its setpoint chain
set, for controller unit tests (no simulator)."""

from __future__ import annotations

import numpy as np

from drivers.interfaces.camera import StereoCamera
from drivers.interfaces.errors import DisconnectedError
from drivers.interfaces.robot import FollowingModel, MotionLimits, Robot, RobotMode, RobotState, SafetyStatus
from hil.clock import ManualClock
from hil.controller.config import ProcedureConfig
from hil.controller.estimate import Estimate
from hil.controller.plan_file import load_plan
from hil.controller.planning import GuidePlan, RigGeometry
from hil.controller.registration import RobotRegistration
from hil.geometry.transform import RigidTransform
from hil.vision.camera_model import StereoCalibration


class FakeRobot(Robot):
    """Records every command that reaches the driver; the pose jumps to each target."""

    def __init__(self, clock: ManualClock, limits: MotionLimits | None = None,
                 T_flange_from_tcp: RigidTransform | None = None) -> None:
        super().__init__("robot", limits or MotionLimits(),
                         T_flange_from_tcp=T_flange_from_tcp or RigidTransform.identity())
        self.clock = clock
        self.pose = RigidTransform.from_translation((0.0, 0.0, 300.0))
        self.calls: list[tuple[str, RigidTransform | None]] = []
        self.safety_status = SafetyStatus.NORMAL
        self.state_delay_ns = 0
        self.stall = False   # servo targets are accepted but the pose no longer moves

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    @property
    def control_rate_hz(self) -> float:
        return 125.0

    @property
    def following_model(self) -> FollowingModel:
        """The pose jumps to each target: no lag (``stall`` makes it stop following)."""
        return FollowingModel(0.0, 2.0, 1.5, 0.1, "fake robot")

    def _move_linear(self, T: RigidTransform, speed_mm_s: float, accel_mm_s2: float, blocking: bool) -> None:
        self.calls.append(("move_linear", T))
        self.pose = T

    def _servo(self, T: RigidTransform, period_s: float) -> None:
        self.calls.append(("servo", T))
        if not self.stall:
            self.pose = T

    def _stop(self, decel_mm_s2: float) -> None:
        self.calls.append(("stop", None))

    def _state_now(self) -> RobotState:
        return RobotState(self.pose, np.zeros(6), RobotMode.IDLE, self.safety_status,
                          self.clock.now_ns() - self.state_delay_ns)


class DroppingRobot(FakeRobot):
    """Its stop raises while ``down`` (a lost link)."""

    down = False

    def _stop(self, decel_mm_s2: float) -> None:
        if self.down:
            raise DisconnectedError(self.name, "link lost (test)")
        super()._stop(decel_mm_s2)


class StubCamera(StereoCamera):
    """A stereo camera with no device behind it (open/close do nothing); subclasses write
    ``grab``. ``calibration``: what it says it knows (default: none)."""

    def __init__(self, frame_rate_hz: float = 30.0, image_size: tuple[int, int] = (8, 8),
                 calibration: StereoCalibration | None = None) -> None:
        super().__init__("camera")
        self._frame_rate_hz = frame_rate_hz
        self._image_size = image_size
        self._calibration = calibration

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    @property
    def calibration(self) -> StereoCalibration | None:
        return self._calibration

    @property
    def frame_rate_hz(self) -> float:
        return self._frame_rate_hz

    @property
    def exposure_us(self) -> float:
        return 1000.0

    @property
    def image_size(self) -> tuple[int, int]:
        return self._image_size


def chain_estimate(T_robot_from_optical: RigidTransform, T_robot_from_tcp: RigidTransform,
                   T_center: RigidTransform, T_bias: RigidTransform) -> Estimate:
    """An estimate of configs/plans/sim_plan.json whose setpoint chain has the given parts: the
    robot registration, the planned TCP pose (robot frame), the entry-centred frame and the bias."""
    est = Estimate(load_plan("configs/plans/sim_plan.json"),
                   RigGeometry(RigidTransform.identity(), np.zeros((3, 3)), RigidTransform.identity()),
                   ProcedureConfig())
    est.robot_reg = RobotRegistration(T_robot_from_optical, 0.1, 12)
    est.guide_plan = GuidePlan(np.zeros(3), np.array([0.0, 0.0, -80.0]), RigidTransform.identity(),
                               T_robot_from_tcp, None, 20.0)
    est.T_center, est.T_bias = T_center, T_bias
    return est
