"""V4L2 stereo camera through OpenCV's CAP_V4L2 backend: two devices, or one side-by-side device.

Freshness: OpenCV's V4L2 backend keeps a queue of driver buffers; read naively, a frame can be
~100 ms old. The driver asks for ``buffer_count`` buffers (CAP_PROP_BUFFERSIZE, 1 by default) and,
before each pair, drains queued frames: it ``grab()``s while a grab returns without waiting
(faster than ``drain_fraction`` of a frame period), at most ``drain_grabs_max`` times; the first
grab that had to wait holds a fresh frame and is kept (else one more grab is made). Frames are
retrieved (decoded) only after both sides are grabbed (grab/retrieve split).

Timestamps: after ``grab()``, CAP_PROP_POS_MSEC on CAP_V4L2 is the kernel buffer timestamp
(``v4l2_buffer.timestamp``, CLOCK_MONOTONIC for UVC, ms). ``Frame.device_t_ns`` carries it in
ns; ``Frame.t_ns`` is it moved onto the controller clock by the frame's age. Two devices are
paired by these timestamps: when the left and right timestamps differ by more than half a frame
period, the older side is grabbed again (until the deadline). A side-by-side device gives one
buffer: both halves share timestamp and sequence. The kernel stamps a buffer when the driver
fills it (for UVC, at the start or end of the transfer, after the exposure): frames say
``time_source = reception``, and ``hil rig-calibrate --temporal`` measures the offset to the
exposure.

Sources: ``source = "device"`` opens ``/dev/videoN`` (or index N) with CAP_V4L2;
``source = "file"`` opens a recorded video with the same code (CAP_FFMPEG; POS_MSEC is then the
media time and is mapped onto the clock from the first frame). The capture opener can be
injected (tests use scripted captures).
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from drivers.camera.config import V4l2CameraConfig
from drivers.interfaces.camera import Frame, FrameTime, StereoCamera, StereoFrame
from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError, DriverError
from hil.clock import Clock
from hil.log import get_logger

if TYPE_CHECKING:
    from hil.vision.camera_model import StereoCalibration

log = get_logger(__name__)


class VideoCaptureLike(Protocol):
    """The part of ``cv2.VideoCapture`` the driver uses."""

    def isOpened(self) -> bool: ...
    def grab(self) -> bool: ...
    def retrieve(self) -> tuple[bool, Any]: ...
    def get(self, prop_id: int) -> float: ...
    def set(self, prop_id: int, value: float) -> bool: ...
    def release(self) -> None: ...


#: (source, api_preference) -> capture. ``source`` is a path, or a device index as int.
CaptureOpener = Callable[[str | int, int], VideoCaptureLike]


def opencv_opener(source: str | int, api_preference: int) -> VideoCaptureLike:
    cap: VideoCaptureLike = cv2.VideoCapture(source, api_preference)
    return cap


def parse_device(spec: str) -> str | int:
    """``"2"`` -> 2 (index), ``"/dev/video2"`` and file paths unchanged."""
    return int(spec) if re.fullmatch(r"\d+", spec) else spec


@dataclass
class _Stream:
    label: str  # "left", "right" or "side_by_side"
    spec: str
    cap: VideoCaptureLike
    grabbed: int = 0  # frames taken from the device (including drained ones)
    last_ts_ns: int = 0
    first_media_ns: int | None = None
    first_clock_ns: int = 0


class V4l2StereoCamera(StereoCamera):
    """Stereo from V4L2 devices (or recorded files through the same path).

    Args:
        name: role name used in errors.
        config: the validated ``[camera]`` section.
        clock: controller clock; ``Frame.t_ns`` is on it.
        opener: builds a capture; default ``cv2.VideoCapture``.
        monotonic_ns: the kernel's CLOCK_MONOTONIC (V4L2 timestamps' clock; also times the
            drain grabs), injectable.
    """

    drain_fraction = 0.3

    def __init__(
        self,
        name: str,
        config: V4l2CameraConfig,
        clock: Clock,
        *,
        opener: CaptureOpener = opencv_opener,
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        super().__init__(name)
        self.config = config
        self._clock = clock
        self._opener = opener
        self._monotonic_ns = monotonic_ns
        self._period_ns = round(1e9 / config.frame_rate_hz)
        self._streams: list[_Stream] = []

    @property
    def frame_rate_hz(self) -> float:
        return self.config.frame_rate_hz

    @property
    def calibration(self) -> StereoCalibration | None:
        """None: two UVC cameras know no stereo calibration: the setup's ``[calibration] stereo`` gives it."""
        return None

    @property
    def exposure_us(self) -> float:
        """The configured exposure, us; NaN when left to the device (auto exposure)."""
        return self.config.exposure_us if self.config.exposure_us is not None else float("nan")

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.config.width_px, self.config.height_px)

    @property
    def side_by_side(self) -> bool:
        return self.config.side_by_side_device is not None

    # -- lifecycle --------------------------------------------------------------------------
    def _open(self) -> None:
        cfg = self.config
        specs: list[tuple[str, str]]
        if cfg.side_by_side_device is not None:
            specs = [("side_by_side", cfg.side_by_side_device)]
        else:
            assert cfg.left_device is not None
            assert cfg.right_device is not None
            specs = [("left", cfg.left_device), ("right", cfg.right_device)]
        try:
            for label, spec in specs:
                self._streams.append(self._open_one(label, spec))
        except BaseException:
            self._release_all()
            raise
        log.info("v4l2_stereo_opened", device=self.name, sources=[s.spec for s in self._streams],
                 source=cfg.source, width_px=cfg.width_px, height_px=cfg.height_px,
                 frame_rate_hz=cfg.frame_rate_hz, buffer_count=cfg.buffer_count)

    def _open_one(self, label: str, spec: str) -> _Stream:
        cfg = self.config
        target = parse_device(spec)
        if isinstance(target, str) and not os.path.exists(target):
            what = "V4L2 device" if cfg.source == "device" else "video file"
            raise DisconnectedError(self.name, f"{label} {what} {spec!r} does not exist")
        api = cv2.CAP_V4L2 if cfg.source == "device" else cv2.CAP_FFMPEG
        cap = self._opener(target, api)
        if not cap.isOpened():
            cap.release()
            what = "V4L2 device" if cfg.source == "device" else "video file"
            raise DisconnectedError(self.name, f"{label} {what} {spec!r} could not be opened "
                                               "(busy, no permission, or not a capture device)")
        stream = _Stream(label=label, spec=spec, cap=cap)
        width_px = cfg.width_px * (2 if label == "side_by_side" else 1)
        if cfg.source == "device":
            if cfg.fourcc is not None:
                cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*cfg.fourcc))
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, width_px)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, cfg.height_px)
            cap.set(cv2.CAP_PROP_FPS, cfg.frame_rate_hz)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, cfg.buffer_count)
            if cfg.exposure_us is not None:
                cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2 "manual" mode
                cap.set(cv2.CAP_PROP_EXPOSURE, cfg.exposure_us / 100.0)  # V4L2 unit: 100 us
        got = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        if got != (width_px, cfg.height_px):
            cap.release()
            raise DriverError(self.name, f"{label} source {spec!r} delivers {got[0]}x{got[1]}, "
                                         f"config asks {width_px}x{cfg.height_px}")
        return stream

    def _close(self) -> None:
        grabbed = {s.label: s.grabbed for s in self._streams}
        self._release_all()
        log.info("v4l2_stereo_closed", device=self.name, frames_grabbed=grabbed)

    def _release_all(self) -> None:
        for s in self._streams:
            s.cap.release()
        self._streams.clear()

    # -- acquisition ------------------------------------------------------------------------
    def grab(self, timeout_s: float) -> StereoFrame:
        """Block until a fresh pair (see the module doc for draining and pairing).

        Raises:
            LifecycleError: not active.
            DeviceTimeoutError: no pair within ``timeout_s``.
            DisconnectedError: a device stopped delivering (unplugged) or a file ended.
        """
        self.require_active("grab")
        deadline = time.monotonic() + timeout_s
        fresh = [self._drain(s) for s in self._streams]
        for s, is_fresh in zip(self._streams, fresh, strict=True):
            if not is_fresh:
                self._grab_one(s, deadline, timeout_s)
        if len(self._streams) == 2:
            left, right = self._streams
            while abs(left.last_ts_ns - right.last_ts_ns) > self._period_ns // 2:
                if time.monotonic() >= deadline:
                    raise DeviceTimeoutError(
                        self.name, f"no left/right pair within {timeout_s:g} s: timestamps "
                        f"{left.last_ts_ns} and {right.last_ts_ns} ns differ by more than half a period")
                older = left if left.last_ts_ns < right.last_ts_ns else right
                self._grab_one(older, deadline, timeout_s)
            pair = StereoFrame(self._retrieve(left), self._retrieve(right))
        else:
            (s,) = self._streams
            frame = self._retrieve(s)
            half = frame.image.shape[1] // 2
            pair = StereoFrame(
                Frame(np.ascontiguousarray(frame.image[:, :half]), frame.t_ns, frame.seq, frame.device_t_ns,
                      frame.time_source),
                Frame(np.ascontiguousarray(frame.image[:, half:]), frame.t_ns, frame.seq, frame.device_t_ns,
                      frame.time_source),
            )
        return pair

    def _drain(self, s: _Stream) -> bool:
        """Drop frames that were already queued: grab while a grab does not wait.

        Returns True when the last grab waited for the device (its frame is fresh and is used).
        """
        limit_ns = int(self._period_ns * self.drain_fraction)
        for _ in range(self.config.drain_grabs_max):
            t0 = self._monotonic_ns()
            if not s.cap.grab():
                self._lost(s)
            s.grabbed += 1
            s.last_ts_ns = self._timestamp_ns(s)
            if self._monotonic_ns() - t0 > limit_ns:
                return True  # that one waited for the device: it is fresh
        return False

    def _grab_one(self, s: _Stream, deadline: float, timeout_s: float) -> None:
        if not s.cap.grab():
            if time.monotonic() >= deadline:
                raise DeviceTimeoutError(self.name, f"{s.label} source {s.spec!r}: no frame within "
                                                    f"{timeout_s:g} s")
            self._lost(s)
        s.grabbed += 1
        s.last_ts_ns = self._timestamp_ns(s)

    def _lost(self, s: _Stream) -> None:
        if self.config.source == "file":
            raise DisconnectedError(self.name, f"{s.label} video file {s.spec!r} ended after "
                                               f"{s.grabbed} frames")
        raise DisconnectedError(self.name, f"{s.label} V4L2 device {s.spec!r} stopped delivering frames "
                                           "(unplugged?)")

    def _timestamp_ns(self, s: _Stream) -> int:
        return round(s.cap.get(cv2.CAP_PROP_POS_MSEC) * 1e6)

    def _retrieve(self, s: _Stream) -> Frame:
        ok, image = s.cap.retrieve()
        if not ok or image is None:
            self._lost(s)
        mono = _to_mono(np.asarray(image))
        ts_ns = s.last_ts_ns
        if self.config.source == "device":
            t_ns = self._clock.now_ns() - max(0, self._monotonic_ns() - ts_ns)
        else:
            if s.first_media_ns is None:
                s.first_media_ns, s.first_clock_ns = ts_ns, self._clock.now_ns()
            t_ns = s.first_clock_ns + (ts_ns - s.first_media_ns)
        # V4L2 buffer timestamps are the driver's (when the buffer was filled): a reception time
        return Frame(image=mono, t_ns=t_ns, seq=s.grabbed - 1, device_t_ns=ts_ns,
                     time_source=FrameTime.RECEPTION)


def _to_mono(image: NDArray[Any]) -> NDArray[np.uint8]:
    if image.ndim == 2:
        return np.ascontiguousarray(image, dtype=np.uint8)
    if image.ndim == 3 and image.shape[2] == 1:
        return np.ascontiguousarray(image[:, :, 0], dtype=np.uint8)
    return np.ascontiguousarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
