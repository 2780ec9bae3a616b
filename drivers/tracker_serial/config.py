"""Configs of the serial magnetic-tracker drivers (``[tracker]`` in a setup).

A leaf of its package: it imports the wire facts it validates against (the baud tables of
:mod:`~drivers.tracker_serial.fob_protocol` and :mod:`~drivers.tracker_serial.aurora_protocol`)
and no driver module; the factories live in :mod:`drivers.tracker_serial.plugin`.

Flock of Birds::

    [tracker]
    driver = "fob"
    port = "/dev/ttyUSB0"
    baud_rate = 115200                 # must match the Bird's dip switches
    sensors = { stylus = 1, reference = 2 }   # name -> FBB address (0 = a standalone bird)

NDI Aurora::

    [tracker]
    driver = "aurora"
    port = "/dev/ttyUSB0"
    baud_rate = 115200                 # switched to with COMM after the reset at 9600
    sensors = { needle = "0A", reference = "0B" }   # name -> port handle (2 hex digits)
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from drivers.tracker_serial.aurora_protocol import BAUD_RATES as AURORA_BAUD_RATES
from drivers.tracker_serial.fob_protocol import BAUD_RATES as FOB_BAUD_RATES


class FlockOfBirdsConfig(BaseModel):
    """Ascension Flock of Birds on RS-232 (FOB-MAN). Times in seconds, rates in Hz.

    Attributes:
        sensors: sensor name -> FBB address. A single bird with address 0 is a standalone unit;
            addresses 1..14 are birds of a flock (auto-configured to the highest address and read
            in group mode).
        record_format: the record each bird sends (all birds alike).
        mode: ``stream`` (STREAM, the Bird paces) or ``point`` (POINT at ``poll_rate_hz``).
        position_scale_in: full-scale position, 36" or 72" (CHANGE VALUE 3); 144" for an ERC is
            detected from the model id.
        measurement_rate_hz: CHANGE VALUE 7 (20-144); None leaves the Bird's setting.
        timeout_s: ``latest()`` raises DeviceTimeoutError when no valid record came for this long.
        response_timeout_s: wait for the answer to one command.
        reset_hold_s, reset_settle_s: RTS high time and the wait after it (GOBBI: 1 s, 2 s).
        max_consecutive_damaged: damaged records in a row that count as unrecoverable corruption
            (``latest()`` raises ProtocolError until a valid record arrives).
        max_step_mm: the Flock's records carry no checksum, so a record that jumps farther than
            this from the sensor's previous one is held back until the next record confirms it
            (None: no gate). Catches most records forged by line noise that passed the framing
            checks; costs one record of delay after a genuine jump.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    driver: Literal["fob"]
    port: str = Field(min_length=1)
    baud_rate: int = 115200
    sensors: dict[str, int] = Field(min_length=1)
    record_format: Literal["position_angles", "position_matrix",
                           "position_quaternion"] = "position_quaternion"
    mode: Literal["stream", "point"] = "stream"
    position_scale_in: Literal[36, 72] = 36
    measurement_rate_hz: float | None = Field(default=None, ge=20.0, le=144.0)
    poll_rate_hz: float = Field(default=50.0, gt=0.0, le=200.0)
    timeout_s: float = Field(default=0.5, gt=0.0)
    response_timeout_s: float = Field(default=1.0, gt=0.0)
    reset_on_open: bool = True
    reset_hold_s: float = Field(default=1.0, ge=0.0)
    reset_settle_s: float = Field(default=2.0, ge=0.0)
    auto_config_wait_s: float = Field(default=0.6, ge=0.0)
    max_consecutive_damaged: int = Field(default=20, ge=1)
    max_step_mm: float | None = Field(default=25.0, gt=0.0)

    @field_validator("baud_rate")
    @classmethod
    def _baud(cls, v: int) -> int:
        if v not in FOB_BAUD_RATES:
            raise ValueError(f"baud_rate {v} is not a Flock dip-switch rate {FOB_BAUD_RATES}")
        return v

    @model_validator(mode="after")
    def _addresses(self) -> FlockOfBirdsConfig:
        addrs = list(self.sensors.values())
        if len(set(addrs)) != len(addrs):
            raise ValueError("sensors: two sensors share an FBB address")
        if any(not 0 <= a <= 14 for a in addrs):
            raise ValueError("sensors: FBB addresses are 1..14 (0 for a standalone bird)")
        if 0 in addrs and len(addrs) > 1:
            raise ValueError("sensors: address 0 (standalone bird) cannot be combined with others")
        return self

    @property
    def standalone(self) -> bool:
        return list(self.sensors.values()) == [0]


class AuroraConfig(BaseModel):
    """NDI Aurora over its serial port (NDI combined API). Times in seconds, rates in Hz.

    Attributes:
        sensors: sensor name -> port handle, two hex digits as the device reports it in PHSR.
        reply_format: ``bx`` (binary, CRC-checked header and body) or ``tx`` (ASCII).
        poll_rate_hz: how often the driver asks for a frame (TX/BX are polled).
        frame_rate_hz: the device's frame counter rate, used to turn frame numbers into host
            times (Aurora's exact figure is not in the sources read; 40 Hz by default).
        break_as_nul: also send a NUL byte with the break (what a UART reads for a break); needed
            for the emulator on a pseudo-terminal, which carries no break.
        reinit_after_s: after a device reset mid-tracking (no answer for this long, or tracking
            refused with ERROR0C/ERROR10), run the start-up again, retried every this many
            seconds; None: do not (the error then stays until the driver is reopened).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    driver: Literal["aurora"]
    port: str = Field(min_length=1)
    baud_rate: int = 115200
    sensors: dict[str, str] = Field(min_length=1)
    reply_format: Literal["bx", "tx"] = "bx"
    poll_rate_hz: float = Field(default=40.0, gt=0.0, le=400.0)
    frame_rate_hz: float = Field(default=40.0, gt=0.0)
    timeout_s: float = Field(default=0.5, gt=0.0)
    response_timeout_s: float = Field(default=1.0, gt=0.0)
    reset_on_open: bool = True
    reset_timeout_s: float = Field(default=7.0, gt=0.0)
    break_duration_s: float = Field(default=0.25, gt=0.0)
    break_as_nul: bool = False
    max_consecutive_damaged: int = Field(default=20, ge=1)
    reinit_after_s: float | None = Field(default=1.0, gt=0.0)

    @field_validator("baud_rate")
    @classmethod
    def _baud(cls, v: int) -> int:
        if v not in AURORA_BAUD_RATES:
            raise ValueError(f"baud_rate {v} has no COMM code; use one of {AURORA_BAUD_RATES}")
        return v

    @field_validator("sensors", mode="before")
    @classmethod
    def _handles(cls, v: object) -> object:
        if not isinstance(v, dict):
            return v
        out: dict[str, str] = {}
        for name, h in v.items():
            text = f"{h:02X}" if isinstance(h, int) and not isinstance(h, bool) else str(h).upper()
            if len(text) != 2 or any(c not in "0123456789ABCDEF" for c in text):
                raise ValueError(f"sensors.{name}: port handle {h!r} is not two hex digits")
            out[str(name)] = text
        if len(set(out.values())) != len(out):
            raise ValueError("sensors: two sensors share a port handle")
        return out


#: Aliases with the names of the brief.
FobTrackerConfig = FlockOfBirdsConfig
AuroraTrackerConfig = AuroraConfig
