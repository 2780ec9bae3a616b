"""Abstract device interfaces shared by the core and every driver (real, simulated, plugin).

Units at this boundary: millimetres, radians, nanoseconds (``t_ns``: host monotonic clock),
and the core's :class:`hil.geometry.RigidTransform`.
"""

from drivers.interfaces.camera import Frame, FrameTime, StereoCamera, StereoFrame
from drivers.interfaces.errors import (
    DeviceFaultError,
    DeviceTimeoutError,
    DisconnectedError,
    DriverError,
    LifecycleError,
    LimitViolationError,
    ProtocolError,
    SafetyStopError,
)
from drivers.interfaces.lifecycle import Device, DeviceState
from drivers.interfaces.robot import MotionLimits, Robot, RobotMode, RobotState, SafetyStatus
from drivers.interfaces.tracker import PoseTracker, TrackerSample

__all__ = [
    "Device",
    "DeviceFaultError",
    "DeviceState",
    "DeviceTimeoutError",
    "DisconnectedError",
    "DriverError",
    "Frame",
    "FrameTime",
    "LifecycleError",
    "LimitViolationError",
    "MotionLimits",
    "PoseTracker",
    "ProtocolError",
    "Robot",
    "RobotMode",
    "RobotState",
    "SafetyStatus",
    "SafetyStopError",
    "StereoCamera",
    "StereoFrame",
    "TrackerSample",
]
