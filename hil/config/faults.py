"""The shape of a fault schedule (``[[faults]]``). The wrappers that play it live in
``drivers.faults`` (the core knows the schedule, not the wrappers).

Each fault has a kind (which fixes the device it applies to), a time window on the controller's
clock measured from the moment the device was opened, and the few parameters its kind uses.

Robot faults with ``transport`` set are not simulated in the wrapper: at their scheduled time
they are sent to the fault-control channel of the UR controller emulator (``tools/ursim``) named by
the setup's ``[fault_channel]`` (:class:`FaultChannelConfig`), so they reach the real driver over
the real protocol (docs/ursim.md). The kind stays the symptom the controller sees; ``transport``
names the emulator command that causes it (``true``: the kind's first command in
:data:`TRANSPORT_COMMANDS`). A setup without ``[fault_channel]`` (a real controller has none)
refuses transport faults.
"""

from __future__ import annotations

import ipaddress
from enum import StrEnum
from typing import Literal

from pydantic import BaseModel, Field, field_validator, model_validator

from hil.config.types import STRICT


class FaultKind(StrEnum):
    # camera
    FRAME_DROP = "frame_drop"            # pairs are lost; grab times out if nothing arrives
    FROZEN_FRAME = "frozen_frame"        # the same images again, with new timestamps and seq
    STALE_TIMESTAMP = "stale_timestamp"  # frames carry timestamps age_ms in the past
    LR_DESYNC = "lr_desync"              # the right image is the previous pair's (skew = 1 frame)
    OCCLUSION = "occlusion"              # a region is painted over (markers hidden)
    GLARE = "glare"                      # bright ring blobs that look like markers (stereo-consistent)
    # tracker
    TRACKER_TIMEOUT = "tracker_timeout"  # latest() raises DeviceTimeoutError
    CORRUPT_RECORD = "corrupt_record"    # latest() raises ProtocolError
    BAD_QUALITY = "bad_quality"          # samples flagged bad_quality with the given quality figure
    SENSOR_MISSING = "sensor_missing"    # samples reported missing (no pose)
    # robot
    ROBOT_DISCONNECT = "robot_disconnect"  # every call raises DisconnectedError
    PROTECTIVE_STOP = "protective_stop"    # the arm stops; safety = protective_stop until recover()
    MOTION_REJECTED = "motion_rejected"    # move/servo raise DeviceFaultError
    MOTION_LAG = "motion_lag"              # commands reach the arm lag_ms late


FAULT_DEVICE: dict[FaultKind, Literal["camera", "tracker", "robot"]] = {
    FaultKind.FRAME_DROP: "camera", FaultKind.FROZEN_FRAME: "camera",
    FaultKind.STALE_TIMESTAMP: "camera", FaultKind.LR_DESYNC: "camera",
    FaultKind.OCCLUSION: "camera", FaultKind.GLARE: "camera",
    FaultKind.TRACKER_TIMEOUT: "tracker", FaultKind.CORRUPT_RECORD: "tracker",
    FaultKind.BAD_QUALITY: "tracker", FaultKind.SENSOR_MISSING: "tracker",
    FaultKind.ROBOT_DISCONNECT: "robot", FaultKind.PROTECTIVE_STOP: "robot",
    FaultKind.MOTION_REJECTED: "robot", FaultKind.MOTION_LAG: "robot",
}

#: An emulator fault-channel command (docs/ursim.md) a robot fault can be sent as.
TransportCommand = Literal["protective_stop", "estop", "drop_connection", "stop_program", "stall",
                           "slow_responses"]

#: The emulator commands each robot kind may be sent as with ``transport`` (the first one for
#: ``transport = true``), and what happens on the emulator:
#: protective_stop -> ``protective_stop`` at the start (``recover()`` is refused until the window
#: ends) or ``estop`` at the start and ``release`` (the button) at the end; robot_disconnect ->
#: ``drop_connection duration_s`` (a network outage as long as the window); motion_rejected ->
#: ``stop_program`` at the start (motion is refused until ``recover()`` restarts the script);
#: motion_lag -> ``slow_responses lag_ms`` / ``slow_responses 0``, or ``stall on`` / ``stall off``.
TRANSPORT_COMMANDS: dict[FaultKind, tuple[TransportCommand, ...]] = {
    FaultKind.PROTECTIVE_STOP: ("protective_stop", "estop"),
    FaultKind.ROBOT_DISCONNECT: ("drop_connection",),
    FaultKind.MOTION_REJECTED: ("stop_program",),
    FaultKind.MOTION_LAG: ("slow_responses", "stall"),
}

#: The UR emulator's default fault-control port (tools/ursim ``--control-port``).
DEFAULT_FAULT_CHANNEL_PORT = 30200


class FaultChannelConfig(BaseModel):
    """``[fault_channel]``: the UR controller emulator's fault-control channel (``tools/ursim``),
    where ``[[faults]]`` with ``transport`` are sent. Test rigs only: a real controller has no such
    channel, so the address must be a loopback one."""

    model_config = STRICT

    host: str = Field("127.0.0.1", min_length=1,
                      description="the emulator's address (loopback: 127.0.0.0/8, ::1 or localhost)")
    port: int = Field(DEFAULT_FAULT_CHANNEL_PORT, ge=1, le=65535, description="its fault-control TCP port")

    @field_validator("host")
    @classmethod
    def _loopback(cls, v: str) -> str:
        try:
            loopback = v == "localhost" or ipaddress.ip_address(v).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise ValueError(f"{v!r} is not a loopback address: the fault channel is the emulator's, on "
                             "this machine (a real controller has none)")
        return v


# Parameters each kind accepts (beyond kind, start_s, duration_s).
_PARAMS: dict[FaultKind, frozenset[str]] = {
    FaultKind.FRAME_DROP: frozenset({"probability"}),
    FaultKind.FROZEN_FRAME: frozenset(),
    FaultKind.STALE_TIMESTAMP: frozenset({"age_ms"}),
    FaultKind.LR_DESYNC: frozenset(),
    FaultKind.OCCLUSION: frozenset({"region_px", "eye"}),
    FaultKind.GLARE: frozenset({"count", "radius_px", "disparity_px"}),
    FaultKind.TRACKER_TIMEOUT: frozenset(),
    FaultKind.CORRUPT_RECORD: frozenset(),
    FaultKind.BAD_QUALITY: frozenset({"quality", "sensors"}),
    FaultKind.SENSOR_MISSING: frozenset({"sensors"}),
    FaultKind.ROBOT_DISCONNECT: frozenset({"transport"}),
    FaultKind.PROTECTIVE_STOP: frozenset({"transport"}),
    FaultKind.MOTION_REJECTED: frozenset({"transport"}),
    FaultKind.MOTION_LAG: frozenset({"lag_ms", "transport"}),
}
_BASE = frozenset({"kind", "start_s", "duration_s"})


class FaultSpec(BaseModel):
    """One scheduled fault: active while ``start_s <= t - t_open < start_s + duration_s``."""

    model_config = STRICT

    kind: FaultKind
    start_s: float = Field(ge=0, description="window start, s after the device was opened")
    duration_s: float = Field(gt=0, description="window length, s")
    probability: float = Field(1.0, gt=0, le=1, description="frame_drop: fraction of pairs lost")
    age_ms: float = Field(500.0, gt=0, description="stale_timestamp: how old the timestamps are, ms")
    region_px: tuple[int, int, int, int] = Field(
        (760, 340, 1160, 740), description="occlusion: x0, y0, x1, y1 painted over, px")
    eye: Literal["left", "right", "both"] = Field("both", description="occlusion: which image")
    count: int = Field(2, ge=1, le=50, description="glare: blobs per image")
    radius_px: float = Field(4.9, gt=0, description="glare: blob outer radius, px (7 mm at 1 m, f 1394 px)")
    disparity_px: float = Field(167.0, ge=0, description="glare: right blob = left blob - this in x, px")
    quality: float = Field(5.0, ge=0, description="bad_quality: the quality figure reported")
    sensors: tuple[str, ...] = Field(
        (), description="bad_quality/sensor_missing: sensors hit (all when empty)")
    lag_ms: float = Field(200.0, gt=0, description="motion_lag: command delay, ms")
    transport: bool | TransportCommand = Field(
        False, description="robot faults: send to the UR emulator's fault channel as this command "
                           "(true: the kind's default) instead of simulating in the wrapper")

    @model_validator(mode="after")
    def _params_fit_kind(self) -> FaultSpec:
        extra = set(self.model_fields_set) - _BASE - _PARAMS[self.kind]
        if extra:
            raise ValueError(f"{sorted(extra)} do not apply to a {self.kind.value} fault "
                             f"(it takes {sorted(_PARAMS[self.kind]) or 'no parameters'})")
        if isinstance(self.transport, str) and self.transport not in TRANSPORT_COMMANDS[self.kind]:
            raise ValueError(f"transport = {self.transport!r} does not cause a {self.kind.value} "
                             f"(it takes {list(TRANSPORT_COMMANDS[self.kind])} or true)")
        x0, y0, x1, y1 = self.region_px
        if x1 <= x0 or y1 <= y0:
            raise ValueError(f"region_px {self.region_px} must be x0 < x1, y0 < y1")
        return self

    @property
    def device(self) -> Literal["camera", "tracker", "robot"]:
        return FAULT_DEVICE[self.kind]

    @property
    def transport_command(self) -> TransportCommand | None:
        """The emulator command this fault is sent as, or None when the wrapper simulates it."""
        if self.transport is False:
            return None
        if self.transport is True:
            return TRANSPORT_COMMANDS[self.kind][0]
        return self.transport

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.end_s
