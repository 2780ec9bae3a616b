"""NDI Aurora / Polaris serial API ("combined API"): pure functions, bytes in, records out.

The wire format of ``reference/device-protocols.md`` section A2 (NDICAPI ``ndicapi.cxx``,
``ndicapi.h``; SAW ``mtsNDISerial.cpp``); no I/O. Used by the driver
(:mod:`drivers.tracker_serial.aurora`) and its probe; the encoders (``frame_reply``, ``format_tx``,
``format_bx``, ``parse_command``) serve the driver's own round-trip tests. The emulator does NOT use
this module: it has its own device-side encoder, and both are checked against the reference's test
vectors (tests/trackers/test_wire_vectors.py).

Framing (A2.2): a command is ``NAME:params`` + 4 upper-case hex CRC-16 over everything before
it + ``\\r`` (or ``NAME params\\r`` without CRC). An ASCII reply is ``text`` + CRC + ``\\r``.
A binary reply (BX) is ``C4 A5``, u16 LE body length, u16 LE header CRC (over those 4 bytes),
the body, u16 LE body CRC. The CRC is NDI's CRC-16 (x^16+x^15+x^2+1, reflected 0xA001,
init 0, no final XOR; = CRC-16/ARC, check value 0xBB3D for ``123456789``).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntFlag

import numpy as np

from hil.geometry.transform import RigidTransform, quaternion_to_matrix

BX_START = b"\xc4\xa5"
RESET_REPLY = b"RESETBE6F\r"
OKAY = "OKAY"

#: COMM baud digit (NDICAPI ``ndiCOMMHelper``; PLUS formats 230400 as ``A``).
COMM_BAUD_CODES: dict[int, str] = {
    9600: "0", 14400: "1", 19200: "2", 38400: "3", 57600: "4", 115200: "5", 921600: "6",
    1228739: "7", 230400: "A",
}
BAUD_FROM_CODE: dict[str, int] = {v: k for k, v in COMM_BAUD_CODES.items()}
#: Every rate the API can switch to (ascending); a session always starts at 9600 after a reset.
BAUD_RATES: tuple[int, ...] = tuple(sorted(COMM_BAUD_CODES))
RESET_BAUD = 9600

ERROR_TEXT: dict[int, str] = {
    0x01: "invalid command", 0x02: "command too long", 0x03: "command too short",
    0x04: "bad CRC in command", 0x05: "internal timeout", 0x06: "COMM fail (new parameters failed)",
    0x07: "wrong number of parameters", 0x08: "invalid port", 0x09: "invalid mode",
    0x0A: "invalid LED", 0x0B: "invalid LED state", 0x0C: "command invalid in current mode",
    0x0D: "no tool", 0x0E: "port not initialized", 0x0F: "port not enabled",
    0x10: "system not initialized", 0x11: "TSTOP fail", 0x12: "TSTART fail", 0x13: "PINIT fail",
    0x14: "invalid PS/FG characterization parameters", 0x15: "INIT fail", 0x16: "DSTART fail",
    0x17: "DSTOP fail", 0x19: "firmware version read fail", 0x1A: "internal error",
    0x1C: "IRED fail", 0x1E: "SROM read fail", 0x1F: "SROM write fail", 0x21: "port current test",
    0x22: "wavelength", 0x23: "parameter range", 0x24: "volume", 0x25: "features",
    0x28: "too many tools", 0x2A: "heap full", 0x2B: "handle not allocated", 0x2C: "handle empty",
    0x2D: "handles full", 0x2F: "invalid port description", 0x30: "port already has a handle",
    0x32: "invalid operation", 0x33: "no feature", 0x39: "permission denied",
    0x3B: "file not found", 0x3C: "file write", 0x3D: "file read", 0x42: "device not present",
    0xF1: "too much environmental IR", 0xF4: "flash erase", 0xF5: "flash write", 0xF6: "flash read",
}


def error_text(code: int) -> str:
    """Plain words for an ``ERRORnn`` code."""
    return ERROR_TEXT.get(code, f"unknown error {code:#04x}")


class NdiDecodeError(ValueError):
    """Bytes that are not a valid reply (framing, CRC, field syntax)."""


class NdiReplyError(Exception):
    """The device answered ``ERRORnn``. ``code`` is the device code (A2.3)."""

    def __init__(self, code: int) -> None:
        self.code = code
        super().__init__(f"ERROR{code:02X}: {error_text(code)}")


# --- CRC ------------------------------------------------------------------------------------------
def _make_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0xA001 if c & 1 else c >> 1
        table.append(c)
    return tuple(table)


_CRC_TABLE = _make_table()


def crc16(data: bytes | bytearray | str, crc: int = 0) -> int:
    """NDI CRC-16 (= CRC-16/ARC): reflected poly 0xA001, init 0, no final XOR; check 0xBB3D."""
    raw = data.encode("ascii") if isinstance(data, str) else data
    for b in raw:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ b) & 0xFF]
    return crc


def frame_command(command: str, *, with_crc: bool = True) -> bytes:
    """``'INIT:'`` -> ``b'INIT:E3A5\\r'``. A command without ``:`` (space form) gets no CRC.

    Raises:
        ValueError: non-ASCII or a CR inside the command.
    """
    if "\r" in command or not command.isascii():
        raise ValueError(f"command {command!r} must be ASCII without CR")
    if with_crc and ":" in command:
        return f"{command}{crc16(command):04X}\r".encode("ascii")
    return f"{command}\r".encode("ascii")


def frame_reply(text: str | bytes) -> bytes:
    """An ASCII reply with its CRC and CR: ``'OKAY'`` -> ``b'OKAYA896\\r'``."""
    raw = text.encode("ascii") if isinstance(text, str) else text
    return raw + f"{crc16(raw):04X}".encode("ascii") + b"\r"


@dataclass(frozen=True)
class ParsedCommand:
    """A command the device received. ``crc_ok`` is None for the space form (no CRC)."""

    name: str
    params: str
    crc_ok: bool | None


def parse_command(line: bytes) -> ParsedCommand:
    """Parse one command line (without the ``\\r``), as a device would (round-trip tests).

    Raises:
        NdiDecodeError: no name, or a ``:`` form shorter than its CRC.
    """
    text = line.decode("ascii", errors="replace")
    for i, ch in enumerate(text):
        if ch in ": " and i == 0:
            raise NdiDecodeError(f"command {text!r} has no name")
        if ch == ":":
            body, crc_text = text[:-4], text[-4:]
            if len(body) <= i:
                raise NdiDecodeError(f"command {text!r} is too short to hold a CRC")
            try:
                ok = int(crc_text, 16) == crc16(body)
            except ValueError:
                ok = False
            return ParsedCommand(text[:i].upper(), body[i + 1:], ok)
        if ch == " ":
            return ParsedCommand(text[:i].upper(), text[i + 1:], None)
        if not ch.isalnum():
            break
    if text.isalnum() and text:
        return ParsedCommand(text.upper(), "", None)
    raise NdiDecodeError(f"not a command: {text!r}")


def check_reply(line: bytes) -> str:
    """Check and strip an ASCII reply line (``\\r`` already removed): returns the text.

    Raises:
        NdiDecodeError: shorter than a CRC, non-hex or wrong CRC.
        NdiReplyError: the reply is ``ERRORnn``.
    """
    if len(line) < 4:
        raise NdiDecodeError(f"reply {line!r} is shorter than its CRC")
    body, crc_text = line[:-4], line[-4:]
    try:
        crc = int(crc_text, 16)
    except ValueError as exc:
        raise NdiDecodeError(f"reply CRC {crc_text!r} is not hex") from exc
    if crc != crc16(body):
        raise NdiDecodeError(f"reply CRC {crc:04X} != computed {crc16(body):04X}")
    text = body.decode("ascii", errors="replace")
    if text.startswith("ERROR") and len(text) == 7:
        try:
            code = int(text[5:], 16)
        except ValueError as exc:
            raise NdiDecodeError(f"bad error reply {text!r}") from exc
        raise NdiReplyError(code)
    return text


# --- COMM -----------------------------------------------------------------------------------------
def comm_command(baud: int) -> str:
    """``COMM:<b>0000``: 8 data bits, no parity, 1 stop bit, no handshake.

    Raises:
        ValueError: a baud rate the API has no code for.
    """
    if baud not in COMM_BAUD_CODES:
        raise ValueError(f"baud {baud} not in {sorted(COMM_BAUD_CODES)}")
    return f"COMM:{COMM_BAUD_CODES[baud]}0000"


# --- PHSR -----------------------------------------------------------------------------------------
def parse_phsr(text: str) -> list[tuple[int, int]]:
    """``NN`` then NN x (``HH`` handle + ``SSS`` status) -> [(handle, status)].

    Raises:
        NdiDecodeError: wrong length or non-hex.
    """
    try:
        n = int(text[:2], 16)
        if len(text) != 2 + 5 * n:
            raise NdiDecodeError(f"PHSR reply {text!r}: {n} handles need {2 + 5 * n} chars")
        return [(int(text[2 + 5 * i:4 + 5 * i], 16), int(text[4 + 5 * i:7 + 5 * i], 16)) for i in range(n)]
    except ValueError as exc:
        raise NdiDecodeError(f"PHSR reply {text!r} is not hex") from exc


def format_phsr(entries: list[tuple[int, int]]) -> str:
    return f"{len(entries):02X}" + "".join(f"{h:02X}{s:03X}" for h, s in entries)


# --- tracking data --------------------------------------------------------------------------------
class PortStatus(IntFlag):
    """TX/BX port status bits (A2.5)."""

    TOOL_IN_PORT = 0x01
    SWITCH_1 = 0x02
    SWITCH_2 = 0x04
    SWITCH_3 = 0x08
    INITIALIZED = 0x10
    ENABLED = 0x20
    OUT_OF_VOLUME = 0x40
    PARTIALLY_IN_VOLUME = 0x80


SYSTEM_STATUS_TEXT: dict[int, str] = {
    0x01: "comm_sync_error", 0x02: "too_much_ir", 0x04: "comm_crc_error", 0x08: "recoverable_comm_error",
    0x10: "hardware_failure", 0x20: "hardware_change", 0x40: "port_occupied", 0x80: "port_unoccupied",
}

TX_MODE_TRANSFORMS = 0x0001
TX_MODE_OUT_OF_VOLUME = 0x0800


@dataclass(frozen=True)
class HandleRecord:
    """One port handle's entry in a TX/BX reply.

    Attributes:
        state: ``valid``, ``missing``, ``disabled`` or ``unoccupied``.
        q_wxyz, t_mm, error_rms: the transform (valid only).
        port_status: the 32-bit port status (0 when the entry has none).
        frame: the device frame number (None when the entry has none).
    """

    handle: int
    state: str
    q_wxyz: tuple[float, float, float, float] | None = None
    t_mm: tuple[float, float, float] | None = None
    error_rms: float | None = None
    port_status: int = 0
    frame: int | None = None

    @property
    def flags(self) -> tuple[str, ...]:
        out = []
        if self.port_status & PortStatus.OUT_OF_VOLUME:
            out.append("out_of_volume")
        if self.port_status & PortStatus.PARTIALLY_IN_VOLUME:
            out.append("partially_out")
        if self.state != "valid":
            out.append(self.state)
        return tuple(out)

    def transform(self) -> RigidTransform | None:
        """The pose ``T_tracker_from_sensor`` (mm), or None without a valid transform."""
        if self.state != "valid" or self.q_wxyz is None or self.t_mm is None:
            return None
        return RigidTransform(quaternion_to_matrix(self.q_wxyz), np.asarray(self.t_mm, dtype=np.float64))


@dataclass(frozen=True)
class TrackingReply:
    """A decoded TX or BX reply."""

    handles: tuple[HandleRecord, ...]
    system_status: int


def _fixed(field_text: str, scale: float) -> float:
    if len(field_text) < 2 or field_text[0] not in "+-" or not field_text[1:].isdigit():
        raise NdiDecodeError(f"bad fixed-point field {field_text!r}")
    return int(field_text) * scale


def _hex(field_text: str, what: str) -> int:
    try:
        return int(field_text, 16)
    except ValueError as exc:
        raise NdiDecodeError(f"bad {what} {field_text!r}") from exc


def format_tx(reply: TrackingReply) -> str:
    """Text of a TX:0801 reply (without the CRC and CR), as a device sends it (round-trip tests)."""
    parts = [f"{len(reply.handles):02X}"]
    for h in reply.handles:
        s = f"{h.handle:02X}"
        if h.state == "valid":
            assert h.q_wxyz is not None
            assert h.t_mm is not None
            assert h.error_rms is not None
            s += "".join(f"{_clamp(round(v * 10000), 99999):+06d}" for v in h.q_wxyz)
            s += "".join(f"{_clamp(round(v * 100), 999999):+07d}" for v in h.t_mm)
            s += f"{_clamp(round(h.error_rms * 10000), 99999):+06d}"
        elif h.state == "missing":
            s += "MISSING"
        elif h.state == "disabled":
            parts.append(s + "DISABLED\n")
            continue
        else:
            parts.append(s + "UNOCCUPIED\n")
            continue
        s += f"{h.port_status:08X}{(h.frame or 0) & 0xFFFFFFFF:08X}\n"
        parts.append(s)
    parts.append(f"{reply.system_status:04X}")
    return "".join(parts)


def _clamp(v: int, limit: int) -> int:
    return max(-limit, min(limit, v))


def parse_tx(text: str) -> TrackingReply:
    """Parse the text of a ``TX:0801`` reply (CRC already checked and stripped).

    Raises:
        NdiDecodeError: any field out of syntax or the wrong length.
    """
    try:
        n = int(text[:2], 16)
    except ValueError as exc:
        raise NdiDecodeError(f"TX reply {text[:20]!r}: bad handle count") from exc
    pos = 2
    handles: list[HandleRecord] = []
    for _ in range(n):
        handle = _hex(text[pos:pos + 2], "handle")
        pos += 2
        if text.startswith("UNOCCUPIED", pos):
            handles.append(HandleRecord(handle, "unoccupied"))
            pos += 10
        elif text.startswith("DISABLED", pos):
            handles.append(HandleRecord(handle, "disabled"))
            pos += 8
        elif text.startswith("MISSING", pos):
            pos += 7
            status = _hex(text[pos:pos + 8], "port status")
            frame = _hex(text[pos + 8:pos + 16], "frame number")
            pos += 16
            handles.append(HandleRecord(handle, "missing", port_status=status, frame=frame))
        else:
            f = text[pos:pos + 51]
            if len(f) != 51:
                raise NdiDecodeError(f"TX reply truncated in handle {handle:02X}")
            q = tuple(_fixed(f[6 * i:6 * i + 6], 1e-4) for i in range(4))
            t = tuple(_fixed(f[24 + 7 * i:31 + 7 * i], 1e-2) for i in range(3))
            err = _fixed(f[45:51], 1e-4)
            pos += 51
            status = _hex(text[pos:pos + 8], "port status")
            frame = _hex(text[pos + 8:pos + 16], "frame number")
            pos += 16
            _check_quaternion(q, handle)
            handles.append(HandleRecord(handle, "valid", (q[0], q[1], q[2], q[3]), (t[0], t[1], t[2]), err,
                                        status, frame))
        if text[pos:pos + 1] != "\n":
            raise NdiDecodeError(f"TX reply: no line feed after handle {handle:02X}")
        pos += 1
    if len(text) - pos != 4:
        raise NdiDecodeError(f"TX reply: {len(text) - pos} chars where the 4-digit system status belongs")
    return TrackingReply(tuple(handles), _hex(text[pos:], "system status"))


def _check_quaternion(q: tuple[float, ...], handle: int) -> None:
    norm = math.sqrt(sum(v * v for v in q))
    if not 0.98 <= norm <= 1.02:
        raise NdiDecodeError(f"handle {handle:02X}: quaternion norm {norm:.4f} is not 1")


_BX_VALID, _BX_MISSING, _BX_DISABLED = 0x01, 0x02, 0x04


def bx_header(body_length: int) -> bytes:
    head = BX_START + struct.pack("<H", body_length)
    return head + struct.pack("<H", crc16(head))


def format_bx(reply: TrackingReply) -> bytes:
    """A whole BX:0801 reply (header, body, body CRC), as a device sends it (round-trip tests)."""
    body = bytearray([len(reply.handles)])
    for h in reply.handles:
        state = {"valid": _BX_VALID, "missing": _BX_MISSING}.get(h.state, _BX_DISABLED)
        body += bytes([h.handle, state])
        if state == _BX_DISABLED:
            continue
        if state == _BX_VALID:
            assert h.q_wxyz is not None
            assert h.t_mm is not None
            assert h.error_rms is not None
            body += struct.pack("<8f", *h.q_wxyz, *h.t_mm, h.error_rms)
        body += struct.pack("<II", h.port_status, (h.frame or 0) & 0xFFFFFFFF)
    body += struct.pack("<H", reply.system_status)
    return bx_header(len(body)) + bytes(body) + struct.pack("<H", crc16(body))


def parse_bx_header(head: bytes) -> int:
    """Check a 6-byte BX header; returns the body length.

    Raises:
        NdiDecodeError: wrong start bytes or header CRC.
    """
    if len(head) != 6 or head[:2] != BX_START:
        raise NdiDecodeError(f"BX header {head.hex()} does not start with c4a5")
    (length, crc) = struct.unpack("<HH", head[2:])
    if crc != crc16(head[:4]):
        raise NdiDecodeError(f"BX header CRC {crc:04X} != computed {crc16(head[:4]):04X}")
    return int(length)


def parse_bx_body(body_and_crc: bytes) -> TrackingReply:
    """Check the body CRC and parse a BX:0801 body.

    Raises:
        NdiDecodeError: CRC mismatch, truncation, NaN, a non-unit quaternion.
    """
    if len(body_and_crc) < 3:
        raise NdiDecodeError("BX body too short")
    body, (crc,) = body_and_crc[:-2], struct.unpack("<H", body_and_crc[-2:])
    if crc != crc16(body):
        raise NdiDecodeError(f"BX body CRC {crc:04X} != computed {crc16(body):04X}")
    try:
        n = body[0]
        pos = 1
        handles: list[HandleRecord] = []
        for _ in range(n):
            handle, state = body[pos], body[pos + 1]
            pos += 2
            if state & _BX_DISABLED:
                handles.append(HandleRecord(handle, "disabled"))
                continue
            if state & _BX_MISSING:
                status, frame = struct.unpack_from("<II", body, pos)
                pos += 8
                handles.append(HandleRecord(handle, "missing", port_status=status, frame=frame))
                continue
            vals = struct.unpack_from("<8f", body, pos)
            pos += 32
            status, frame = struct.unpack_from("<II", body, pos)
            pos += 8
            if not all(math.isfinite(v) for v in vals):
                raise NdiDecodeError(f"BX handle {handle:02X}: non-finite value")
            _check_quaternion(vals[:4], handle)
            handles.append(HandleRecord(handle, "valid", (vals[0], vals[1], vals[2], vals[3]),
                                        (vals[4], vals[5], vals[6]), vals[7], status, frame))
        (system_status,) = struct.unpack_from("<H", body, pos)
        pos += 2
    except (IndexError, struct.error) as exc:
        raise NdiDecodeError("BX body truncated") from exc
    if pos != len(body):
        raise NdiDecodeError(f"BX body has {len(body) - pos} unexpected trailing bytes")
    return TrackingReply(tuple(handles), int(system_status))
