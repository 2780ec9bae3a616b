"""Replay of a recorded stereo session (see :mod:`drivers.camera.recording`) as a StereoCamera.

Timing: with ``speed > 0`` pair *k* is delivered no earlier than
``open_time + (t_k - t_0) / speed`` on the controller clock (``clock.sleep`` waits, so a
ManualClock replays instantly in tests); ``speed = 0`` delivers as fast as grabbed.
``Frame.t_ns`` is the delivery time on the controller clock, keeping the recorded left/right skew;
``seq`` and ``device_t_ns`` are the recorded ones. At the end: with ``loop`` the recording starts
again, otherwise ``grab`` raises DisconnectedError.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from drivers.camera.recording import PairRow, RecordingInfo, read_info, read_png, read_timestamps
from drivers.interfaces.camera import Frame, StereoCamera, StereoFrame
from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError
from hil.clock import Clock
from hil.errors import InputFileError
from hil.log import get_logger

if TYPE_CHECKING:
    from hil.vision.camera_model import StereoCalibration

log = get_logger(__name__)


class ReplayStereoCamera(StereoCamera):
    """Plays a recording directory back. Bad recordings raise InputFileError at ``open()``."""

    def __init__(self, name: str, directory: Path, clock: Clock, *, speed: float = 1.0,
                 loop: bool = False) -> None:
        super().__init__(name)
        if speed < 0 or not math.isfinite(speed):
            raise ValueError(f"speed must be >= 0, got {speed}")
        self.directory = Path(directory)
        self.speed = speed
        self.loop = loop
        self._clock = clock
        self._info: RecordingInfo | None = None
        self._rows: list[PairRow] = []
        self._caps: dict[str, cv2.VideoCapture] = {}
        self._next = 0
        self._laps = 0
        self._start_clock_ns = 0
        self._lap_offset_ns = 0

    @property
    def info(self) -> RecordingInfo:
        if self._info is None:
            self._info = read_info(self.directory)
        return self._info

    def describe(self) -> dict[str, str]:
        """The recording's format (``hil probe``): codec, image size, rate and pairs."""
        if self._info is None:
            return {}
        i = self._info
        return {"codec": str(i.codec), "image": f"{i.image_size[0]}x{i.image_size[1]}",
                "rate": f"{i.frame_rate_hz:g} Hz", "pairs": str(i.pairs)}

    @property
    def frame_rate_hz(self) -> float:
        return self.info.frame_rate_hz

    @property
    def calibration(self) -> StereoCalibration | None:
        """None: a recording holds no stereo calibration: the setup's ``[calibration] stereo`` gives it."""
        return None

    @property
    def exposure_us(self) -> float:
        return self.info.exposure_us

    @property
    def image_size(self) -> tuple[int, int]:
        return self.info.image_size

    def _open(self) -> None:
        info = self.info
        self._rows = read_timestamps(self.directory)
        if len(self._rows) != info.pairs:
            raise InputFileError(str(self.directory / "timestamps.csv"),
                                 f"{len(self._rows)} rows but recording.json says {info.pairs} pairs")
        if not self._rows:
            raise InputFileError(str(self.directory), "the recording holds no pairs")
        self._rewind()
        self._start_clock_ns = self._clock.now_ns()
        log.info("replay_opened", device=self.name, directory=str(self.directory), pairs=info.pairs,
                 codec=info.codec, speed=self.speed, loop=self.loop)

    def _rewind(self) -> None:
        self._release()
        self._next = 0
        if self.info.codec == "ffv1":
            for side in ("left", "right"):
                path = self.directory / f"{side}.mkv"
                if not path.exists():
                    raise InputFileError(str(path), "missing")
                cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
                if not cap.isOpened():
                    raise InputFileError(str(path), "not a readable video")
                self._caps[side] = cap

    def _release(self) -> None:
        for cap in self._caps.values():
            cap.release()
        self._caps.clear()

    def _close(self) -> None:
        self._release()

    def grab(self, timeout_s: float) -> StereoFrame:
        """The next recorded pair, at the recorded pace / ``speed``.

        Raises:
            LifecycleError: not active.
            DeviceTimeoutError: the next pair is due later than ``timeout_s`` from now (the clock
                has then waited ``timeout_s``).
            DisconnectedError: the recording ended (and ``loop`` is off).
        """
        self.require_active("grab")
        if self._next >= len(self._rows):
            if not self.loop:
                raise DisconnectedError(self.name, f"recording {self.directory} ended after "
                                                   f"{len(self._rows)} pairs")
            rows = self._rows
            lap_ns = rows[-1].left_t_ns - rows[0].left_t_ns + round(1e9 / self.info.frame_rate_hz)
            self._lap_offset_ns += lap_ns
            self._laps += 1
            self._rewind()
        row = self._rows[self._next]
        first = self._rows[0]
        t0 = (first.left_t_ns + first.right_t_ns) // 2
        rec_t_ns = (row.left_t_ns + row.right_t_ns) // 2
        if self.speed > 0:
            due_ns = self._start_clock_ns + round((rec_t_ns - t0 + self._lap_offset_ns) / self.speed)
            wait_s = (due_ns - self._clock.now_ns()) / 1e9
            if wait_s > timeout_s:
                self._clock.sleep(timeout_s)
                raise DeviceTimeoutError(self.name, f"next recorded pair is due in {wait_s:.3f} s, "
                                                    f"more than the {timeout_s:g} s timeout")
            if wait_s > 0:
                self._clock.sleep(wait_s)
        left_img, right_img = self._images(self._next)
        now_ns = self._clock.now_ns()
        scale = self.speed if self.speed > 0 else 1.0
        pair = StereoFrame(
            Frame(left_img, now_ns + round((row.left_t_ns - rec_t_ns) / scale), row.left_seq,
                  row.left_device_t_ns),
            Frame(right_img, now_ns + round((row.right_t_ns - rec_t_ns) / scale), row.right_seq,
                  row.right_device_t_ns),
        )
        self._next += 1
        return pair

    def _images(self, index: int) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        out: list[NDArray[np.uint8]] = []
        for side in ("left", "right"):
            image: NDArray[np.uint8]
            if self.info.codec == "png":
                image = read_png(self.directory / side / f"{index:06d}.png")
            else:
                ok, raw = self._caps[side].read()
                if not ok or raw is None:
                    raise InputFileError(str(self.directory / f"{side}.mkv"),
                                         f"has no frame {index} (timestamps.csv lists {len(self._rows)})")
                grey = cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY) if raw.ndim == 3 else raw
                image = np.ascontiguousarray(grey, dtype=np.uint8)
            out.append(image)
        return out[0], out[1]
