"""Stereo camera interface: synchronised left/right frames with timestamps."""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.lifecycle import Device

if TYPE_CHECKING:
    from hil.vision.camera_model import StereoCalibration


class FrameTime(StrEnum):
    """What a frame's ``t_ns`` marks."""

    EXPOSURE = "exposure"    # the exposure (a device timestamp mapped to the host clock, or a simulation)
    RECEPTION = "reception"  # when the host received the frame (the device gives nothing better)


@dataclass(frozen=True)
class Frame:
    """One image from one camera.

    Attributes:
        image: HxW uint8 (mono) or HxWx3 uint8 (BGR).
        t_ns: host monotonic time of the exposure (or of reception when the device gives
            nothing better), ns, on the clock the controller uses.
        seq: per-camera frame counter (device frame id where there is one).
        device_t_ns: the device's own timestamp, ns, when it has one; None otherwise.
        time_source: what ``t_ns`` marks (:class:`FrameTime`): the exposure, or the host
            reception (later than the exposure by the transfer; ``hil rig-calibrate --temporal``
            measures the difference).
    """

    image: NDArray[np.uint8]
    t_ns: int
    seq: int
    device_t_ns: int | None = None
    time_source: FrameTime = FrameTime.EXPOSURE


@dataclass(frozen=True)
class StereoFrame:
    """A left/right pair grabbed as one. ``skew_ns`` is right.t_ns - left.t_ns."""

    left: Frame
    right: Frame

    @property
    def skew_ns(self) -> int:
        return self.right.t_ns - self.left.t_ns

    @property
    def t_ns(self) -> int:
        """Pair time: the mean of left and right exposure times."""
        return (self.left.t_ns + self.right.t_ns) // 2


class StereoCamera(Device):
    """A calibrated stereo source. A sensor: it has no command that moves anything.

    Every driver says whether it knows its stereo calibration (:attr:`calibration`); one that
    does not needs the setup's ``[calibration] stereo`` file.
    """

    kind = "camera"

    @property
    @abstractmethod
    def calibration(self) -> StereoCalibration | None:
        """The stereo calibration the device itself knows (intrinsics, distortion, left-to-right
        pose, mm), or None when it knows none (a plain camera pair): the setup must then give
        ``[calibration] stereo``, and the controller's assembly raises a ConfigError naming that
        key when neither does. A wrapper returns its inner device's. Never blocks, never raises,
        available in every lifecycle state.
        """

    @abstractmethod
    def grab(self, timeout_s: float) -> StereoFrame:
        """Block until the next synchronised pair (newer than the last one returned).

        Raises:
            LifecycleError: not active.
            DeviceTimeoutError: no pair within ``timeout_s``.
            DisconnectedError: the stream is gone.
        """

    @property
    @abstractmethod
    def frame_rate_hz(self) -> float:
        """The configured frame rate, Hz."""

    @property
    @abstractmethod
    def exposure_us(self) -> float:
        """The configured exposure time, microseconds."""

    @property
    @abstractmethod
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels of each camera's image."""
