"""Timestamp-correcting adapters: a device wrapped so its stamps mark the true time of what it
reports, using a rig calibration's time offsets (stamp minus true time, :mod:`hil.rigcal.rigfile`).

Each adapter implements the same driver interface and delegates everything; only ``t_ns`` of
frames, robot states and tracker samples changes (``t_ns - offset``). A camera's corrected frames
say ``time_source = exposure``. The lifecycle is the inner device's (``state``, ``open``,
``close`` and the active check are delegated), so a device can be wrapped before or after it is
opened, and closing either closes both. The controller then pairs frames with robot states at the right
time and its prediction horizon (frame age + actuation lag) covers the real latency.
"""

from __future__ import annotations

import dataclasses

from drivers.interfaces.camera import FrameTime, StereoCamera, StereoFrame
from drivers.interfaces.lifecycle import Device, DeviceState
from drivers.interfaces.robot import FollowingModel, Robot, RobotState
from drivers.interfaces.tracker import PoseTracker, TrackerSample
from hil.geometry.transform import RigidTransform
from hil.rigcal.rigfile import RigCalibration
from hil.vision.camera_model import StereoCalibration


class _Delegating:
    """Lifecycle delegated to ``inner`` (mixed into each adapter before the interface class)."""

    inner: Device

    @property
    def state(self) -> DeviceState:
        return self.inner.state

    def open(self) -> None:
        self.inner.open()

    def close(self) -> None:
        self.inner.close()

    def require_active(self, operation: str) -> None:
        self.inner.require_active(operation)

    def _open(self) -> None:  # never called: open() is the inner device's
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError


def _inner_attr(wrapper: object, name: str) -> object:
    """An attribute the wrapper lacks, from the wrapped device (a driver's extras, such as the
    simulator's ``world``). What the core needs is part of the interface and delegated explicitly."""
    inner = wrapper.__dict__.get("inner")
    if inner is None or name.startswith("__"):
        raise AttributeError(name)
    return getattr(inner, name)


class TimeAlignedCamera(_Delegating, StereoCamera):
    """A stereo camera whose frames are stamped ``offset_ns`` earlier (at exposure)."""

    inner: StereoCamera

    def __init__(self, inner: StereoCamera, offset_ns: int) -> None:
        super().__init__(inner.name)
        self.inner, self.offset_ns = inner, offset_ns

    def __getattr__(self, name: str) -> object:  # driver extras (world, true_calibration, ...)
        return _inner_attr(self, name)

    def grab(self, timeout_s: float) -> StereoFrame:
        self.require_active("grab")
        p = self.inner.grab(timeout_s)
        return StereoFrame(
            dataclasses.replace(p.left, t_ns=p.left.t_ns - self.offset_ns, time_source=FrameTime.EXPOSURE),
            dataclasses.replace(p.right, t_ns=p.right.t_ns - self.offset_ns, time_source=FrameTime.EXPOSURE))

    @property
    def frame_rate_hz(self) -> float:
        return self.inner.frame_rate_hz

    @property
    def exposure_us(self) -> float:
        return self.inner.exposure_us

    @property
    def image_size(self) -> tuple[int, int]:
        return self.inner.image_size

    @property
    def calibration(self) -> StereoCalibration | None:
        """The inner camera's stereo calibration (None when it knows none), never a default."""
        return self.inner.calibration


class TimeAlignedRobot(_Delegating, Robot):
    """A robot whose states are stamped ``offset_ns`` earlier (the time the pose was the arm's).
    Motion commands go to the inner driver unchanged (the base class checks limits on both)."""

    inner: Robot

    def __init__(self, inner: Robot, offset_ns: int) -> None:
        super().__init__(inner.name, inner.limits, T_flange_from_tcp=inner.T_flange_from_tcp)
        self.inner, self.offset_ns = inner, offset_ns

    def __getattr__(self, name: str) -> object:  # driver extras (world, q_at, ...)
        return _inner_attr(self, name)

    @property
    def control_rate_hz(self) -> float:
        return self.inner.control_rate_hz

    @property
    def following_model(self) -> FollowingModel:
        """The inner robot's."""
        return self.inner.following_model

    @property
    def T_flange_from_tcp(self) -> RigidTransform:
        """The inner robot's TCP in the flange frame (mm), never a default of its own."""
        return self.inner.T_flange_from_tcp

    def _move_linear(self, T_robot_from_tcp: RigidTransform, speed_mm_s: float, accel_mm_s2: float,
                     blocking: bool) -> None:
        self.inner.move_linear(T_robot_from_tcp, speed_mm_s, accel_mm_s2, blocking=blocking)

    def _servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None:
        self.inner.servo(T_robot_from_tcp, period_s)

    def _stop(self, decel_mm_s2: float) -> None:
        self.inner.stop(decel_mm_s2)

    def _state_now(self) -> RobotState:
        s = self.inner.state_now()
        return dataclasses.replace(s, t_ns=s.t_ns - self.offset_ns)

    def recover(self) -> None:
        self.inner.recover()


class TimeAlignedTracker(_Delegating, PoseTracker):
    """A tracker whose samples are stamped ``offset_ns`` earlier."""

    inner: PoseTracker

    def __init__(self, inner: PoseTracker, offset_ns: int) -> None:
        super().__init__(inner.name)
        self.inner, self.offset_ns = inner, offset_ns

    def __getattr__(self, name: str) -> object:
        return _inner_attr(self, name)

    def latest(self) -> dict[str, TrackerSample]:
        self.require_active("latest")
        return {k: dataclasses.replace(s, t_ns=s.t_ns - self.offset_ns)
                for k, s in self.inner.latest().items()}

    @property
    def sensors(self) -> tuple[str, ...]:
        return self.inner.sensors


def time_aligned(camera: StereoCamera, robot: Robot, tracker: PoseTracker | None,
                 rig: RigCalibration) -> tuple[StereoCamera, Robot, PoseTracker | None]:
    """The devices wrapped with the rig calibration's offsets (a device without an offset in the
    file is returned as it is), opened or not."""
    cam: StereoCamera = camera
    rob: Robot = robot
    trk = tracker
    if "camera" in rig.time_offsets:
        cam = TimeAlignedCamera(camera, rig.offset_ns("camera"))
    if "robot" in rig.time_offsets:
        rob = TimeAlignedRobot(robot, rig.offset_ns("robot"))
    if tracker is not None and "tracker" in rig.time_offsets:
        trk = TimeAlignedTracker(tracker, rig.offset_ns("tracker"))
    return cam, rob, trk
