"""The shape of a fault schedule (``[[faults]]``). The wrappers that play it live in
``drivers.faults`` (the core knows the schedule, not the wrappers).

Each fault has a kind (which fixes the device it applies to), a time window on the controller's
clock measured from the moment the device was opened, and the few parameters its kind uses.

Patient faults (``device`` ``"patient"``: a cough, the patient shifting on the table, a skin
marker lost or moved) happen to the body, not to a device: the simulated world plays them
(``drivers.sim.patient_faults``; its window counts from the world's start, when the devices are
built), so a setup without a simulated device refuses them.

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
import math
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
    # patient (the simulated body; issue 41)
    COUGH = "cough"                        # a non-rigid jolt of the body peaking at offset_mm
    PATIENT_SHIFT = "patient_shift"        # the body moves offset_mm over the window and stays
    MARKER_LOST = "marker_lost"            # skin markers `markers` not seen (come off, covered)
    MARKER_MOVED = "marker_moved"          # skin markers `markers` slide offset_mm and stay (peeling)

#: The devices a fault can apply to ("patient": the simulated body, module doc).
FaultDevice = Literal["camera", "tracker", "robot", "patient"]


FAULT_DEVICE: dict[FaultKind, FaultDevice] = {
    FaultKind.FRAME_DROP: "camera", FaultKind.FROZEN_FRAME: "camera",
    FaultKind.STALE_TIMESTAMP: "camera", FaultKind.LR_DESYNC: "camera",
    FaultKind.OCCLUSION: "camera", FaultKind.GLARE: "camera",
    FaultKind.TRACKER_TIMEOUT: "tracker", FaultKind.CORRUPT_RECORD: "tracker",
    FaultKind.BAD_QUALITY: "tracker", FaultKind.SENSOR_MISSING: "tracker",
    FaultKind.ROBOT_DISCONNECT: "robot", FaultKind.PROTECTIVE_STOP: "robot",
    FaultKind.MOTION_REJECTED: "robot", FaultKind.MOTION_LAG: "robot",
    FaultKind.COUGH: "patient", FaultKind.PATIENT_SHIFT: "patient",
    FaultKind.MARKER_LOST: "patient", FaultKind.MARKER_MOVED: "patient",
}

#: Each patient kind's default ``offset_mm`` (image frame: x lateral, y superior, z anterior, mm).
PATIENT_DEFAULT_OFFSET_MM: dict[FaultKind, tuple[float, float, float]] = {
    FaultKind.COUGH: (0.0, 4.0, 6.0),
    FaultKind.PATIENT_SHIFT: (5.0, 3.0, 0.0),
    FaultKind.MARKER_MOVED: (12.0, 0.0, 0.0),
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
    FaultKind.COUGH: frozenset({"offset_mm"}),
    FaultKind.PATIENT_SHIFT: frozenset({"offset_mm"}),
    FaultKind.MARKER_LOST: frozenset({"markers"}),
    FaultKind.MARKER_MOVED: frozenset({"markers", "offset_mm"}),
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
    offset_mm: tuple[float, float, float] | None = Field(
        None, description="cough: the jolt's peak; patient_shift: the body's final offset; marker_moved: "
                          "the markers' final displacement (image frame, mm; None: the kind's default)")
    markers: tuple[int, ...] = Field(
        (0,), min_length=1, description="marker_lost/marker_moved: skin marker indices (CT fiducial order)")
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
        if any(i < 0 for i in self.markers):
            raise ValueError(f"markers {list(self.markers)}: indices are >= 0 (CT fiducial order)")
        off = self.offset_mm
        if off is not None and not all(math.isfinite(v) and abs(v) <= 100.0 for v in off):
            raise ValueError(f"offset_mm {self.offset_mm}: finite and within 100 mm per axis")
        x0, y0, x1, y1 = self.region_px
        if x1 <= x0 or y1 <= y0:
            raise ValueError(f"region_px {self.region_px} must be x0 < x1, y0 < y1")
        return self

    @property
    def device(self) -> FaultDevice:
        return FAULT_DEVICE[self.kind]

    @property
    def patient_offset_mm(self) -> tuple[float, float, float]:
        """A patient fault's offset (mm, image frame): the configured one or the kind's default
        (zero for kinds without one)."""
        if self.offset_mm is not None:
            return self.offset_mm
        return PATIENT_DEFAULT_OFFSET_MM.get(self.kind, (0.0, 0.0, 0.0))

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
