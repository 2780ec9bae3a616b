"""Config models of the real stereo-camera drivers.

Each model is one ``[camera]`` section of a setup file (``driver = "aravis" | "v4l2" | "replay"``).
A leaf of its package: it imports no driver module; the factories live in
:mod:`drivers.camera.plugin`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

TriggerMode = Literal["software", "hardware", "free_run"]
PairingRule = Literal["auto", "trigger_id", "frame_id", "device_time", "host_time"]
PixelFormatName = Literal[
    "Mono8", "Mono10", "Mono12", "Mono16", "BayerGR8", "BayerRG8", "BayerGB8", "BayerBG8", "RGB8", "BGR8"
]


class AravisCameraConfig(BaseModel):
    """Two GigE Vision / USB3 Vision cameras through Aravis, used as one stereo source.

    Attributes:
        left_device_id / right_device_id: what ``arv-tool-0.8`` lists: the device id
            (``Vendor-Model-Serial``), the serial number or the IP address.
        trigger: ``software`` (the host sends one TriggerSoftware to each camera per pair),
            ``hardware`` (both cameras on one trigger line, ``trigger_line``) or ``free_run``.
        pairing: ``auto`` = trigger id for software trigger, frame id for hardware trigger,
            device time when ``device_clocks_synchronised`` (PTP) else host time for free run.
        pixel_format: the format asked of the cameras; frames are always delivered as Mono8.
        packet_size_bytes: GigE packet size (None: Aravis negotiates).
        enable_fake_interface: also enumerate Aravis' in-process ``Fake`` interface (tests).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    driver: Literal["aravis"]
    left_device_id: str = Field(min_length=1)
    right_device_id: str = Field(min_length=1)
    width_px: int = Field(default=1920, gt=0)
    height_px: int = Field(default=1080, gt=0)
    offset_x_px: int = Field(default=0, ge=0)
    offset_y_px: int = Field(default=0, ge=0)
    frame_rate_hz: float = Field(default=30.0, gt=0.0, le=1000.0)
    exposure_us: float = Field(default=5000.0, gt=0.0)
    gain_db: float | None = None
    pixel_format: PixelFormatName = "Mono8"
    trigger: TriggerMode = "software"
    trigger_line: str = "Line0"
    pairing: PairingRule = "auto"
    device_clocks_synchronised: bool = False
    n_buffers: int = Field(default=8, ge=2, le=64)
    packet_size_bytes: int | None = Field(default=None, gt=0)
    enable_fake_interface: bool = False

    @model_validator(mode="after")
    def _check(self) -> AravisCameraConfig:
        if self.left_device_id == self.right_device_id:
            raise ValueError("left_device_id and right_device_id name the same camera")
        if self.pairing == "trigger_id" and self.trigger != "software":
            raise ValueError("pairing = 'trigger_id' needs trigger = 'software'")
        if self.pairing == "frame_id" and self.trigger == "free_run":
            raise ValueError("pairing = 'frame_id' needs a trigger (free-running counters are not aligned)")
        return self


class V4l2CameraConfig(BaseModel):
    """V4L2 (UVC) stereo through OpenCV's CAP_V4L2 backend.

    Either two devices (``left_device`` and ``right_device``), or one side-by-side device
    (``side_by_side_device``) whose frames hold the left image in the left half.

    Attributes:
        *_device: ``/dev/videoN`` path or index N; in tests also a video file path with
            ``source = "file"``.
        width_px / height_px: the size of ONE camera's image (a side-by-side device delivers
            twice the width).
        fourcc: requested pixel format (``MJPG``, ``YUYV``); None leaves the device default.
        buffer_count: V4L2 buffers asked of the driver (CAP_PROP_BUFFERSIZE); 1 = freshest.
        drain_grabs_max: at most this many queued frames are dropped per grab so the pair
            returned is fresh (grab until a grab returns without waiting).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    driver: Literal["v4l2"]
    left_device: str | None = None
    right_device: str | None = None
    side_by_side_device: str | None = None
    source: Literal["device", "file"] = "device"
    width_px: int = Field(default=1280, gt=0)
    height_px: int = Field(default=720, gt=0)
    frame_rate_hz: float = Field(default=30.0, gt=0.0, le=1000.0)
    exposure_us: float | None = Field(default=None, gt=0.0)
    fourcc: str | None = Field(default=None, min_length=4, max_length=4)
    buffer_count: int = Field(default=1, ge=1, le=32)
    drain_grabs_max: int = Field(default=4, ge=0, le=64)
    pairing: Literal["auto", "host_time"] = "auto"

    @model_validator(mode="after")
    def _check(self) -> V4l2CameraConfig:
        pair = self.left_device is not None or self.right_device is not None
        if pair and self.side_by_side_device is not None:
            raise ValueError("give either left_device + right_device or side_by_side_device, not both")
        if not pair and self.side_by_side_device is None:
            raise ValueError("give left_device + right_device, or side_by_side_device")
        if pair and (self.left_device is None or self.right_device is None):
            raise ValueError("left_device and right_device go together")
        if pair and self.left_device == self.right_device:
            raise ValueError("left_device and right_device name the same device")
        return self


class ReplayCameraConfig(BaseModel):
    """A recorded stereo session (``tools``/``hil`` recorder output) played back as a camera.

    Attributes:
        recording_dir: the directory holding ``timestamps.csv`` and the frames (relative paths
            are resolved against the setup file's directory).
        speed: 1.0 replays at the recorded timing, 2.0 twice as fast; 0 = as fast as grabbed.
        loop: start again at the first pair after the last one (else DisconnectedError).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    driver: Literal["replay"]
    recording_dir: Path
    speed: float = Field(default=1.0, ge=0.0)
    loop: bool = False
