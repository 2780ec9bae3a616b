"""The device side of the Ascension Flock of Birds RS-232 protocol, as the emulated Bird speaks it.

Written from the manual facts of reference/device-protocols.md section A1 (FOB-MAN), NOT from
the driver's codec (``drivers.tracker_serial.fob_protocol``): with one codec on both ends a
framing bug would pass every test. Both are checked against the manual's worked example and the
reference's record example (tests/trackers/test_wire_vectors.py).

- Words (A1.4, FOB-MAN p.40): each 16-bit word keeps its 14 most significant bits and goes out as
  two bytes, least significant first: ``phase | bits 8..2`` then ``bits 15..9``; the phasing bit
  (0x80) is set in the first byte of a record only.
- Trailer (A1.4): the BUTTON byte (BUTTON MODE on), then the FBB address byte (GROUP MODE on).
- Scaling (A1.5): position ``int16 = inches * 32768 / full scale`` (36" or 72"); angles
  ``int16 = degrees * 32768 / 180`` (+180 deg is sent as -180); matrix and quaternion elements
  ``int16 = value * 32768``; all saturating.
- Orientation (A1.4): angles are azimuth (z), elevation (y), roll (x) of the sensor in the
  transmitter frame; the MATRIX record holds the transpose of that rotation, column by column;
  the QUATERNION record holds the conjugate of its quaternion, scalar first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from hil.geometry.transform import RigidTransform, matrix_to_quaternion

INCH_MM = 25.4
PHASE = 0x80

# --- command bytes (A1.3) ------------------------------------------------------------------------
POINT = 0x42
STREAM = 0x40
STREAM_STOP = 0x3F
EXAMINE = 0x4F
CHANGE = 0x50
BUTTON_MODE = 0x4D
BUTTON_READ = 0x4E
RUN = 0x46
SLEEP = 0x47
XON = 0x11
XOFF = 0x13
METAL_ERROR = 0x74

# --- EXAMINE / CHANGE VALUE parameters (A1.7) ----------------------------------------------------
BIRD_STATUS = 0x00
SOFTWARE_REVISION = 0x01
CRYSTAL_SPEED = 0x02
POSITION_SCALING = 0x03
FILTER = 0x04
MEASUREMENT_RATE = 0x07
ERROR_CODE = 0x0A
ERROR_DETECT_MASK = 0x0B
MODEL_ID = 0x0F
EXPANDED_ERROR_CODE = 0x10
ADDRESSING_MODE = 0x13
FBB_ADDRESS = 0x15
GROUP_MODE = 0x23
FLOCK_STATUS = 0x24
AUTO_CONFIG = 0x32

#: Bytes EXAMINE VALUE answers with, for the parameters the emulator has no special value for.
EXAMINE_BYTES: dict[int, int] = {BIRD_STATUS: 2, SOFTWARE_REVISION: 2, CRYSTAL_SPEED: 2, POSITION_SCALING: 2,
                                 FILTER: 2, MEASUREMENT_RATE: 2, ERROR_CODE: 1, MODEL_ID: 10,
                                 EXPANDED_ERROR_CODE: 2, ADDRESSING_MODE: 1, FBB_ADDRESS: 1, GROUP_MODE: 1,
                                 FLOCK_STATUS: 14, AUTO_CONFIG: 5}
#: Data bytes after ``P <param>`` ("CHANGE bytes" of the A1.7 table minus the 2 command bytes).
CHANGE_BYTES: dict[int, int] = {POSITION_SCALING: 2, FILTER: 2, MEASUREMENT_RATE: 2, ERROR_DETECT_MASK: 1,
                                GROUP_MODE: 1, AUTO_CONFIG: 1}

#: Flock system status byte (EXAMINE 36, one per FBB address; A1.7 note).
FLOCK_ACCESSIBLE = 0x80
FLOCK_RUNNING = 0x40
FLOCK_HAS_SENSOR = 0x20
FLOCK_TRANSMITTER = 0x01  # a standard transmitter (or ERT #0) is attached to this bird


class Format(Enum):
    """The record formats (A1.3 format commands, A1.4 record sizes, A1.7 bird status codes):
    ``(command byte, words, status code)``."""

    POSITION = (0x56, 3, 1)
    ANGLES = (0x57, 3, 2)
    MATRIX = (0x58, 9, 3)
    POSITION_ANGLES = (0x59, 6, 4)
    POSITION_MATRIX = (0x5A, 12, 5)
    QUATERNION = (0x5C, 4, 7)
    POSITION_QUATERNION = (0x5D, 7, 8)

    @classmethod
    def for_command(cls, command: int) -> Format | None:
        return next((f for f in cls if f.value[0] == command), None)


def _saturate(value: float) -> int:
    return int(max(-32768, min(32767, round(value))))


def pack_words(words: list[int]) -> bytes:
    """The bytes of a record's words (FOB-MAN p.40 worked example: 0x1122, 0x3344, 0x5566 ->
    ``C8 08 51 19 59 2A``)."""
    out = bytearray()
    for i, word in enumerate(words):
        u = word & 0xFFFF
        out += bytes([(PHASE if i == 0 else 0) | (u >> 2) & 0x7F, (u >> 9) & 0x7F])
    return bytes(out)


def _angle_word(rad: float) -> int:
    word = round(math.degrees(rad) * 32768 / 180)
    return -32768 if word >= 32768 else _saturate(word)


def record(T_tracker_from_sensor: RigidTransform, fmt: Format, *, full_scale_in: float,
           button: int | None = None, address: int | None = None) -> bytes:
    """The record a bird sends for a pose, with the BUTTON byte (``button`` not None) and the
    GROUP MODE address byte (``address`` not None) after the words."""
    T = T_tracker_from_sensor
    words: list[int] = []
    if fmt in (Format.POSITION, Format.POSITION_ANGLES, Format.POSITION_MATRIX, Format.POSITION_QUATERNION):
        words += [_saturate(float(mm) / INCH_MM * 32768 / full_scale_in) for mm in T.t]
    if fmt in (Format.ANGLES, Format.POSITION_ANGLES):
        words += [_angle_word(a) for a in T.as_euler_zyx()]  # azimuth, elevation, roll
    elif fmt in (Format.MATRIX, Format.POSITION_MATRIX):
        M = T.R.T
        words += [_saturate(float(M[r, c]) * 32768) for c in range(3) for r in range(3)]
    elif fmt in (Format.QUATERNION, Format.POSITION_QUATERNION):
        q = matrix_to_quaternion(T.R)
        words += [_saturate(float(v) * 32768) for v in (q[0], -q[1], -q[2], -q[3])]
    out = pack_words(words)
    if button is not None:
        out += bytes([button])
    if address is not None:
        out += bytes([address & 0x7F])
    return out


@dataclass(frozen=True)
class BirdState:
    """What the bird status word (EXAMINE 0, A1.7: FOB-MAN p.111-112) reports."""

    master: bool
    initialized: bool
    error: bool
    running: bool
    sleeping: bool
    stream: bool
    fmt: Format

    def word(self) -> bytes:
        """The two status bytes, least significant first: bit 15 master, 14 initialised, 13
        error, 12 running, 5 sleeping, 4..1 the format code, 0 stream."""
        w = (self.master << 15) | (self.initialized << 14) | (self.error << 13) | (self.running << 12)
        w |= (self.sleeping << 5) | (self.fmt.value[2] << 1) | int(self.stream)
        return w.to_bytes(2, "little")
