"""Ascension Flock of Birds RS-232 protocol: pure functions, bytes in, records out.

Everything here is the wire format of FOB-MAN (Flock of Birds Installation and Operation
Guide, P/N 910141 Rev B) as summarised in ``reference/device-protocols.md`` section A1; no I/O.
Used by the driver (:mod:`drivers.tracker_serial.fob`) and its probe. The emulator does NOT use
it: it has its own device-side encoder, and both are checked against the manual's worked example
(tests/trackers/test_wire_vectors.py).

Wire format (FOB-MAN p.39-41):
    A record is N 16-bit words, each carrying its 14 most significant bits, sent as two bytes,
    LSbyte first: ``LS = phase | ((w >> 2) & 0x7F)``, ``MS = (w >> 9) & 0x7F``. The phasing bit
    (bit 7) is 1 in the first byte of a record and 0 in every other byte. After the words come,
    in this order: the BUTTON byte (BUTTON MODE 1), the METAL byte (not used here), and the
    GROUP MODE address byte (group mode on).

Orientation convention (FOB-MAN p.77, p.90-92; VESS and VRJ confirm it): the angles are
azimuth (about Z), elevation (about Y), roll (about X) and the sensor's orientation in the
transmitter frame is ``R_tracker_from_sensor = Rz(A) Ry(E) Rx(R)`` (seed 000 eq 14 order). The
MATRIX record holds the *transpose* of it (it maps transmitter axes into sensor axes), sent
column-major M(1,1), M(2,1), M(3,1), M(1,2) ...; the QUATERNION record holds the *conjugate*
of the quaternion of ``R_tracker_from_sensor``, scalar first.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np

from hil.geometry.transform import FloatArray, RigidTransform, matrix_to_quaternion, quaternion_to_matrix

MM_PER_INCH = 25.4
PHASE_BIT = 0x80

#: The RS-232 rates the Bird's baud dip switches 1-2-3 select (FOB-MAN p.29); the host must match.
BAUD_RATES: tuple[int, ...] = (2400, 4800, 9600, 19200, 38400, 57600, 115200)
#: How the model id (EXAMINE VALUE 15: 10 ASCII bytes, space-padded) of each Ascension unit starts
#: (FOB-MAN p.109-110 parameter table).
MODEL_ID_ERC = "6DERC"  # an Extended Range Controller: positions at 144" full scale (A1.5)
MODEL_IDS: tuple[str, ...] = ("6DFOB", MODEL_ID_ERC, "6DBOF", "PCBIRD", "SPACEPAD", "MOTIONSTAR", "WIRELESS")

# --- command bytes (FOB-MAN ch.7) ---------------------------------------------------------------
CMD_POINT = 0x42  # 'B'
CMD_STREAM = 0x40  # '@'
CMD_STREAM_STOP = 0x3F  # '?'
CMD_EXAMINE = 0x4F  # 'O'
CMD_CHANGE = 0x50  # 'P'
CMD_BUTTON_MODE = 0x4D  # 'M'
CMD_BUTTON_READ = 0x4E  # 'N'
CMD_RUN = 0x46  # 'F'
CMD_SLEEP = 0x47  # 'G'
CMD_HEMISPHERE = 0x4C  # 'L'
CMD_FBB_RESET = 0x2F  # '/'
CMD_REPORT_RATE_1 = 0x51  # 'Q': every measurement cycle
CMD_REPORT_RATE_2 = 0x52
CMD_REPORT_RATE_8 = 0x53
CMD_REPORT_RATE_32 = 0x54
CMD_XON = 0x11
CMD_XOFF = 0x13

# --- EXAMINE/CHANGE VALUE parameters (FOB-MAN p.109-110) -----------------------------------------
PARAM_BIRD_STATUS = 0x00
PARAM_SOFTWARE_REVISION = 0x01
PARAM_POSITION_SCALING = 0x03
PARAM_MEASUREMENT_RATE = 0x07
PARAM_ERROR_CODE = 0x0A
PARAM_MODEL_ID = 0x0F
PARAM_EXPANDED_ERROR_CODE = 0x10
PARAM_ADDRESSING_MODE = 0x13
PARAM_FBB_ADDRESS = 0x15
PARAM_GROUP_MODE = 0x23
PARAM_FLOCK_STATUS = 0x24
PARAM_AUTO_CONFIG = 0x32

#: Bytes returned by EXAMINE VALUE for the parameters a driver reads (FOB-MAN table).
EXAMINE_REPLY_BYTES: dict[int, int] = {
    PARAM_BIRD_STATUS: 2,
    PARAM_SOFTWARE_REVISION: 2,
    0x02: 2,  # crystal speed
    PARAM_POSITION_SCALING: 2,
    0x04: 2,  # filter on/off
    PARAM_MEASUREMENT_RATE: 2,
    PARAM_ERROR_CODE: 1,
    PARAM_MODEL_ID: 10,
    PARAM_EXPANDED_ERROR_CODE: 2,
    PARAM_ADDRESSING_MODE: 1,
    PARAM_FBB_ADDRESS: 1,
    PARAM_GROUP_MODE: 1,
    PARAM_FLOCK_STATUS: 14,  # normal addressing
    PARAM_AUTO_CONFIG: 5,  # normal addressing
}

#: Data bytes after ``P <param>`` for the parameters a driver changes (FOB-MAN "CHANGE bytes" - 2).
CHANGE_DATA_BYTES: dict[int, int] = {
    PARAM_POSITION_SCALING: 2,
    0x04: 2,
    PARAM_MEASUREMENT_RATE: 2,
    0x0B: 1,  # error detect mask
    PARAM_GROUP_MODE: 1,
    PARAM_AUTO_CONFIG: 1,
}

BUTTON_VALUES: frozenset[int] = frozenset({0x00, 0x10, 0x30, 0x70})

#: Bits of a flock system status byte (EXAMINE 36, one byte per FBB address; FOB-MAN p.129).
FLOCK_ACCESSIBLE = 0x80
FLOCK_RUNNING = 0x40
FLOCK_HAS_SENSOR = 0x20


class FobFormat(Enum):
    """Record formats: (command byte, words per record, status-word format code)."""

    POSITION = (0x56, 3, 1)
    ANGLES = (0x57, 3, 2)
    MATRIX = (0x58, 9, 3)
    POSITION_ANGLES = (0x59, 6, 4)
    POSITION_MATRIX = (0x5A, 12, 5)
    QUATERNION = (0x5C, 4, 7)
    POSITION_QUATERNION = (0x5D, 7, 8)

    @property
    def command(self) -> int:
        return self.value[0]

    @property
    def words(self) -> int:
        return self.value[1]

    @property
    def status_code(self) -> int:
        return self.value[2]

    @property
    def has_position(self) -> bool:
        return self in (FobFormat.POSITION, FobFormat.POSITION_ANGLES, FobFormat.POSITION_MATRIX,
                        FobFormat.POSITION_QUATERNION)

    @classmethod
    def from_command(cls, command: int) -> FobFormat | None:
        for fmt in cls:
            if fmt.command == command:
                return fmt
        return None


# --- error codes (FOB-MAN ch.9) -------------------------------------------------------------------
FATAL_ERROR_CODES: frozenset[int] = frozenset({1, 2, 15, 16, *range(20, 28)})
ERROR_TEXT: dict[int, str] = {
    1: "system RAM failure", 2: "non-volatile storage write failure",
    3: "PCB configuration data corrupt",
    4: "transmitter calibration/configuration data corrupt or not connected",
    5: "sensor calibration/configuration data corrupt or not connected", 6: "invalid RS232 command",
    7: "not an FBB master", 8: "no birds accessible in device list", 9: "bird is not initialized",
    10: "FBB receive error - intra bird bus", 11: "RS232 receive overrun or framing error",
    12: "FBB receive error - FBB host bus", 13: "no FBB command response", 14: "invalid FBB host command",
    15: "FBB run time error", 16: "invalid CPU speed", 17: "no FBB data", 18: "illegal baud rate",
    19: "slave acknowledge error", 20: "CPU error: INT4 overflow", 21: "CPU error: INT5 bounds",
    22: "CPU error: INT6 unused opcode", 23: "CPU error: INT7 ESC opcode", 24: "CPU error: INT9 reserved",
    25: "CPU error: INT10 reserved", 26: "CPU error: INT11 reserved", 27: "CPU error: INT16 numeric",
    28: "CRT synchronization error", 29: "transmitter not accessible",
    30: "extended range transmitter not attached", 31: "CPU time overflow", 32: "sensor saturated",
    33: "slave configuration error", 34: "watchdog error", 35: "over temperature",
}


def error_text(code: int) -> str:
    """Plain words for a FOB error code (EXAMINE VALUE 10); ``unknown error N`` otherwise."""
    return ERROR_TEXT.get(code, f"unknown error {code}")


class FobDecodeError(ValueError):
    """Bytes that are not a valid record (phasing, length, trailer or implausible content)."""


# --- words ----------------------------------------------------------------------------------------
def encode_words(words: Sequence[int]) -> bytes:
    """Pack signed 16-bit words as a record: 2 bytes each, LSbyte first, phasing bit on byte 0.

    The two least significant bits of each word are lost (14-bit resolution).

    Raises:
        ValueError: a word outside int16.
    """
    out = bytearray()
    for i, w in enumerate(words):
        if not -32768 <= w <= 32767:
            raise ValueError(f"word {i} = {w} is outside int16")
        u = w & 0xFFFF
        out.append((PHASE_BIT if i == 0 else 0) | ((u >> 2) & 0x7F))
        out.append((u >> 9) & 0x7F)
    return bytes(out)


def decode_words(data: bytes | bytearray) -> list[int]:
    """Inverse of :func:`encode_words` (FOB-MAN p.40): ``int16(((MS & 0x7F) << 9) | ((LS & 0x7F) << 2))``.

    Raises:
        FobDecodeError: odd length, no phasing bit on byte 0, or a phasing bit on any other byte.
    """
    if len(data) % 2:
        raise FobDecodeError(f"record of {len(data)} bytes is not whole words")
    if not data or not data[0] & PHASE_BIT:
        raise FobDecodeError("first byte lacks the phasing bit")
    for i in range(1, len(data)):
        if data[i] & PHASE_BIT:
            raise FobDecodeError(f"phasing bit set in byte {i}")
    words = []
    for i in range(0, len(data), 2):
        u = ((data[i + 1] & 0x7F) << 9) | ((data[i] & 0x7F) << 2)
        words.append(u - 0x10000 if u & 0x8000 else u)
    return words


def encode_data_words(words: Sequence[int]) -> bytes:
    """Command data words: int16, LSbyte first, 2's complement, no phasing (FOB-MAN p.110)."""
    return b"".join(int(w).to_bytes(2, "little", signed=True) for w in words)


def decode_data_word(data: bytes | bytearray) -> int:
    """One EXAMINE VALUE word: int16, LSbyte first."""
    return int.from_bytes(bytes(data[:2]), "little", signed=True)


# --- scaling (FOB-MAN p.63, p.88, p.92, p.113) ----------------------------------------------------
def position_full_scale_mm(scaling_param: int, *, extended_range: bool = False) -> float:
    """Full-scale position in mm: 36" (param 3 = 0), 72" (param 3 = 1), 144" with an ERC/ERT."""
    if extended_range:
        return 144.0 * MM_PER_INCH
    if scaling_param not in (0, 1):
        raise ValueError(f"position scaling parameter must be 0 or 1, got {scaling_param}")
    return (72.0 if scaling_param else 36.0) * MM_PER_INCH


def _clamp16(v: float) -> int:
    return max(-32768, min(32767, round(v)))


def position_to_word(value_mm: float, full_scale_mm: float) -> int:
    """``int16 = mm * 32768 / full_scale``, saturating (0x7FFF = +full scale)."""
    return _clamp16(value_mm * 32768.0 / full_scale_mm)


def word_to_position_mm(word: int, full_scale_mm: float) -> float:
    return word * full_scale_mm / 32768.0


def angle_to_word(angle_rad: float) -> int:
    """``int16 = deg * 32768 / 180``; +180 deg wraps to -180 (0x8000)."""
    deg = math.degrees(angle_rad)
    w = round(deg * 32768.0 / 180.0)
    if w >= 32768:
        w -= 65536
    return _clamp16(w)


def word_to_angle_rad(word: int) -> float:
    return math.radians(word * 180.0 / 32768.0)


def unit_to_word(value: float) -> int:
    """Matrix/quaternion element: ``int16 = value * 32768`` (+0.99996 = 0x7FFF, -1 = 0x8000)."""
    return _clamp16(value * 32768.0)


def word_to_unit(word: int) -> float:
    return word / 32768.0


# --- records --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RecordLayout:
    """What a record looks like on the wire for one bird."""

    fmt: FobFormat = FobFormat.POSITION_ANGLES
    button_mode: bool = False
    group_mode: bool = False

    @property
    def length(self) -> int:
        """Bytes per record: 2 x words + button byte + group address byte (GOBBI, FOB-MAN p.39)."""
        return 2 * self.fmt.words + int(self.button_mode) + int(self.group_mode)


@dataclass(frozen=True)
class FobRecord:
    """One decoded record.

    Attributes:
        T_tracker_from_sensor: the pose (mm); the translation is zero for orientation-only formats
            and the rotation identity for POSITION.
        button: BUTTON byte (0x00 none, 0x10 left, 0x30 middle, 0x70 right) or None.
        address: FBB address from the group-mode byte, or None outside group mode.
        words: the raw words, for diagnostics.
        end_offset: from :class:`RecordSynchronizer`: stream offset just past the record's last
            byte (bytes fed since creation), so a caller can time-stamp it by when it arrived.
    """

    T_tracker_from_sensor: RigidTransform
    button: int | None
    address: int | None
    words: tuple[int, ...] = field(default=())
    end_offset: int = -1


_UNIT_TOLERANCE = 0.02  # 14-bit elements are good to ~1e-4; corruption is far beyond this


def _euler_to_R(az: float, el: float, roll: float) -> FloatArray:
    return RigidTransform.from_euler_zyx(az, el, roll).R


def encode_record(T_tracker_from_sensor: RigidTransform, layout: RecordLayout, *, full_scale_mm: float,
                  button: int = 0, address: int = 0) -> bytes:
    """The bytes a bird sends for a pose (the driver's round-trip tests).

    Raises:
        ValueError: a trailer value out of range.
    """
    fmt = layout.fmt
    words: list[int] = []
    if fmt.has_position:
        words += [position_to_word(float(v), full_scale_mm) for v in T_tracker_from_sensor.t]
    R = T_tracker_from_sensor.R
    if fmt in (FobFormat.ANGLES, FobFormat.POSITION_ANGLES):
        az, el, roll = T_tracker_from_sensor.as_euler_zyx()
        words += [angle_to_word(az), angle_to_word(el), angle_to_word(roll)]
    elif fmt in (FobFormat.MATRIX, FobFormat.POSITION_MATRIX):
        M = R.T  # the Bird's matrix maps transmitter axes into sensor axes
        words += [unit_to_word(float(M[row, col])) for col in range(3) for row in range(3)]
    elif fmt in (FobFormat.QUATERNION, FobFormat.POSITION_QUATERNION):
        q = matrix_to_quaternion(R)
        words += [unit_to_word(float(v)) for v in (q[0], -q[1], -q[2], -q[3])]
    out = bytearray(encode_words(words))
    if layout.button_mode:
        if button not in BUTTON_VALUES:
            raise ValueError(f"button byte {button:#x} is not one of 0x00/0x10/0x30/0x70")
        out.append(button)
    if layout.group_mode:
        if not 0 <= address <= 0x7F:
            raise ValueError(f"group address {address} outside 0..127")
        out.append(address)
    return bytes(out)


def decode_record(data: bytes | bytearray, layout: RecordLayout, *, full_scale_mm: float) -> FobRecord:
    """Decode one record of ``layout``; checks framing, trailer bytes and plausibility.

    Plausibility (a corrupt record usually fails it): elevation within +-90 deg, matrix
    orthonormal and quaternion of unit norm within 0.02.

    Raises:
        FobDecodeError: wrong length, phasing, trailer value or implausible content.
    """
    if len(data) != layout.length:
        raise FobDecodeError(f"record has {len(data)} bytes, layout needs {layout.length}")
    n_word_bytes = 2 * layout.fmt.words
    words = decode_words(data[:n_word_bytes])
    pos = n_word_bytes
    button: int | None = None
    address: int | None = None
    if layout.button_mode:
        button = data[pos]
        pos += 1
        if button not in BUTTON_VALUES:
            raise FobDecodeError(f"button byte {button:#04x} is not a button value")
    if layout.group_mode:
        address = data[pos]
        if address & PHASE_BIT:
            raise FobDecodeError("group address byte has the phasing bit")
    fmt = layout.fmt
    i = 0
    t = np.zeros(3)
    if fmt.has_position:
        t = np.array([word_to_position_mm(w, full_scale_mm) for w in words[0:3]])
        i = 3
    R = np.eye(3)
    if fmt in (FobFormat.ANGLES, FobFormat.POSITION_ANGLES):
        az, el, roll = (word_to_angle_rad(w) for w in words[i:i + 3])
        if abs(el) > math.pi / 2 + 1e-3:
            raise FobDecodeError(f"elevation {math.degrees(el):.2f} deg is outside +-90 deg")
        R = _euler_to_R(az, el, roll)
    elif fmt in (FobFormat.MATRIX, FobFormat.POSITION_MATRIX):
        vals = [word_to_unit(w) for w in words[i:i + 9]]
        M = np.array(vals).reshape(3, 3).T  # column-major on the wire
        if not np.allclose(M @ M.T, np.eye(3), atol=_UNIT_TOLERANCE) or np.linalg.det(M) < 0:
            raise FobDecodeError("matrix record is not a rotation")
        R = _orthonormalise(M.T)
    elif fmt in (FobFormat.QUATERNION, FobFormat.POSITION_QUATERNION):
        q0, q1, q2, q3 = (word_to_unit(w) for w in words[i:i + 4])
        norm = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        if abs(norm - 1.0) > _UNIT_TOLERANCE:
            raise FobDecodeError(f"quaternion norm {norm:.4f} is not 1")
        R = quaternion_to_matrix([q0, -q1, -q2, -q3])
    return FobRecord(RigidTransform(R, t), button, address, tuple(words))


def _orthonormalise(M: FloatArray) -> FloatArray:
    U, _, Vt = np.linalg.svd(M)
    R: FloatArray = U @ Vt
    return R


# --- stream resynchroniser ------------------------------------------------------------------------
@dataclass
class SyncStats:
    """Counters of the resynchroniser (cumulative)."""

    records: int = 0
    damaged: int = 0
    discarded_bytes: int = 0


class RecordSynchronizer:
    """Cuts a byte stream into records, dropping damaged ones and resynchronising on phasing bits.

    A candidate record is a byte with the phasing bit followed by ``length - 1`` bytes without it.
    It is *accepted* only once the byte after it is known to start the next record (phasing bit
    set) — or, for a POINT reply, when the caller says the reply is over (:meth:`end_of_reply`).
    Bytes inserted inside a record lengthen it, so the next phasing byte does not follow it and
    it is dropped; bytes lost from a record make the next phasing byte fall inside it, so it is
    dropped and the search restarts at that byte. Framing alone cannot tell bytes inserted at the
    end of a record from bytes inserted just after it, so a record followed by anything other
    than a phasing byte counts as damaged: the loss is bounded to the record(s) that touch the
    damaged bytes, and every record whose own bytes and following boundary are intact is
    returned. Accepted candidates are also decoded (:func:`decode_record`); one that fails the
    decode checks is dropped.

    Args:
        layout: the record layout (all birds of a group share it).
        full_scale_mm: position scaling.
        addresses: in group mode, the FBB addresses that may appear in the address byte.
    """

    def __init__(self, layout: RecordLayout, *, full_scale_mm: float,
                 addresses: Iterable[int] | None = None) -> None:
        self.layout = layout
        self.full_scale_mm = full_scale_mm
        self.addresses = frozenset(addresses) if addresses is not None else None
        self.stats = SyncStats()
        self._buf = bytearray()
        self._consumed = 0
        self.consecutive_damaged = 0

    def reset(self) -> None:
        """Forget buffered bytes (after a flush of the port); they count as consumed."""
        self._consumed += len(self._buf)
        self._buf.clear()

    def feed(self, data: bytes | bytearray) -> list[FobRecord]:
        """Add bytes; return the records now known to be whole and valid, in order."""
        self._buf += data
        return self._scan(final=False)

    def end_of_reply(self) -> list[FobRecord]:
        """The line went quiet after a POINT reply: accept a complete candidate at the very end."""
        return self._scan(final=True)

    def _scan(self, *, final: bool) -> list[FobRecord]:
        out: list[FobRecord] = []
        buf = self._buf
        n = self.layout.length
        while True:
            start = _find_phase(buf, 0)
            if start < 0:
                self._drop(len(buf))
                break
            if start:
                self._drop(start)
            nxt = _find_phase(buf, 1)
            if nxt < 0:
                if len(buf) > n:
                    # n bytes + clear bytes after: inserted bytes at the end of this record, or lost
                    # phasing of the next one. Either way this candidate is unusable.
                    self._damaged(len(buf))
                    continue
                if final and len(buf) == n:
                    self._accept(bytes(buf), out)
                    del buf[:n]
                elif final and buf:
                    self._damaged(len(buf))
                break
            if nxt == n:
                self._accept(bytes(buf[:n]), out)
                del buf[:n]
            else:
                self._damaged(nxt)  # too short (bytes lost) or too long (bytes inserted)
        return out

    def _drop(self, count: int) -> None:
        self.stats.discarded_bytes += count
        self._consumed += count
        del self._buf[:count]

    def _damaged(self, count: int) -> None:
        self.stats.damaged += 1
        self.consecutive_damaged += 1
        self._drop(count)

    def _accept(self, raw: bytes, out: list[FobRecord]) -> None:
        """Decode a framed candidate (the caller removes its bytes from the buffer)."""
        self._consumed += len(raw)
        try:
            rec = decode_record(raw, self.layout, full_scale_mm=self.full_scale_mm)
        except FobDecodeError:
            self.stats.damaged += 1
            self.consecutive_damaged += 1
            self.stats.discarded_bytes += len(raw)
            return
        if self.addresses is not None and rec.address not in self.addresses:
            self.stats.damaged += 1
            self.consecutive_damaged += 1
            self.stats.discarded_bytes += len(raw)
            return
        self.stats.records += 1
        self.consecutive_damaged = 0
        out.append(replace(rec, end_offset=self._consumed))


def _find_phase(buf: bytearray, start: int) -> int:
    for i in range(start, len(buf)):
        if buf[i] & PHASE_BIT:
            return i
    return -1


# --- commands -------------------------------------------------------------------------------------
def rs232_to_fbb(address: int) -> bytes:
    """The RS232 TO FBB prefix for a bird address (normal/expanded addressing, FOB-MAN p.97).

    Raises:
        ValueError: address outside 1..30.
    """
    if 1 <= address <= 15:
        return bytes([0xF0 + address])
    if 16 <= address <= 30:
        return bytes([0xE0 + address - 16])
    raise ValueError(f"FBB address {address} outside 1..30")


def examine(param: int, *, address: int | None = None) -> bytes:
    """``O <param>``, prefixed with RS232 TO FBB when ``address`` is given."""
    cmd = bytes([CMD_EXAMINE, param])
    return rs232_to_fbb(address) + cmd if address else cmd


def change(param: int, data: bytes, *, address: int | None = None) -> bytes:
    """``P <param> <data>``; checks the data length for the parameters in :data:`CHANGE_DATA_BYTES`.

    Raises:
        ValueError: wrong number of data bytes.
    """
    want = CHANGE_DATA_BYTES.get(param)
    if want is not None and len(data) != want:
        raise ValueError(f"CHANGE VALUE {param:#04x} takes {want} data bytes, got {len(data)}")
    cmd = bytes([CMD_CHANGE, param]) + data
    return rs232_to_fbb(address) + cmd if address else cmd


@dataclass(frozen=True)
class BirdStatus:
    """The bird status word (EXAMINE 0, FOB-MAN p.111-112)."""

    word: int

    @property
    def master(self) -> bool:
        return bool(self.word & 0x8000)

    @property
    def initialized(self) -> bool:
        return bool(self.word & 0x4000)

    @property
    def error(self) -> bool:
        return bool(self.word & 0x2000)

    @property
    def running(self) -> bool:
        return bool(self.word & 0x1000)

    @property
    def sleeping(self) -> bool:
        return bool(self.word & 0x0020)

    @property
    def stream(self) -> bool:
        """Bit 0: 1 = STREAM, 0 = POINT (FOB-MAN p.112)."""
        return bool(self.word & 0x0001)

    @property
    def fmt(self) -> FobFormat | None:
        code = (self.word >> 1) & 0x0F
        for f in FobFormat:
            if f.status_code == code:
                return f
        return None

    @classmethod
    def build(cls, *, master: bool, initialized: bool, error: bool, running: bool, sleeping: bool,
              stream: bool, fmt: FobFormat) -> BirdStatus:
        w = (0x8000 * master) | (0x4000 * initialized) | (0x2000 * error) | (0x1000 * running)
        w |= (0x0020 * sleeping) | (fmt.status_code << 1) | int(stream)
        return cls(w)

    def to_bytes(self) -> bytes:
        return (self.word & 0xFFFF).to_bytes(2, "little")

    @classmethod
    def from_bytes(cls, data: bytes | bytearray) -> BirdStatus:
        return cls(int.from_bytes(bytes(data[:2]), "little"))
