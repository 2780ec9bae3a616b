"""Stereo camera interface: synchronised left/right frames with timestamps."""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

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


#: What a :class:`PairFeed` hands over (the core's located pair; this interface does not know it).
PairT_co = TypeVar("PairT_co", covariant=True)


class PairFeed(Protocol[PairT_co]):
    """Stereo pairs already located elsewhere (a perception process running the camera): what the
    controller takes instead of grabbing the camera, with the consumer contract of its frame
    prefetcher (:class:`hil.controller.prefetch.FramePrefetcher`). ``PairT_co`` is the located
    pair (:class:`hil.controller.prefetch.Prefetched`; the driver interfaces import no core
    module, so they leave it open).

    Attributes:
        produced: pairs taken or skipped so far.
        overwritten: pairs replaced by a newer one before they were taken (the latest wins).
    """

    produced: int
    overwritten: int

    def ready(self) -> bool:
        """Whether :meth:`take` would return at once. Never blocks."""
        ...

    def take(self, timeout_s: float, wake: Callable[[], bool] | None = None) -> PairT_co | None:
        """The newest pair not taken yet, waiting up to ``timeout_s`` (blocking); None once
        ``wake`` returns True while waiting. Raises the camera's DriverError (DeviceTimeoutError
        when none came in time, DisconnectedError when the producer is gone)."""
        ...

    def stop(self, timeout_s: float | None = None) -> None:
        """Stop producing (up to ``timeout_s``; None: as long as it takes)."""
        ...


class StereoCamera(Device):
    """A calibrated stereo source. A sensor: it has no command that moves anything.

    Every driver says whether it knows its stereo calibration (:attr:`calibration`); one that
    does not needs the setup's ``[calibration] stereo`` file. A camera whose pairs are located
    elsewhere says so with :attr:`perception_feed`.
    """

    kind = "camera"

    #: The camera this one wraps (a fault-injection or time-alignment wrapper sets it; None for
    #: a device itself). :attr:`perception_feed` follows it unless a class says otherwise.
    inner: StereoCamera | None = None

    @property
    def perception_feed(self) -> PairFeed[Any] | None:
        """Where this camera's pairs come from already located (the perception process that runs
        the camera: the controller takes from it and never grabs), or None for a camera the
        controller grabs (every device driver). A wrapper returns its :attr:`inner` camera's (the
        default here). Never blocks, never raises, available in every lifecycle state."""
        return self.inner.perception_feed if self.inner is not None else None

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
