"""The device side of the NDI combined API, as the emulated Aurora speaks it.

Written from the manual facts of reference/device-protocols.md section A2, NOT from the driver's
codec (``drivers.tracker_serial.aurora_protocol``): with one codec on both ends a framing bug would
pass every test. Both are checked against the reference's test vectors (tests/trackers/
test_wire_vectors.py).

- CRC (A2.2): polynomial x^16+x^15+x^2+1, reflected (0xA001), initial value 0, no final XOR;
  computed here bit by bit.
- Command (A2.2): ``NAME:params`` + 4 upper-case hex digits of the CRC of everything before them
  + CR, or ``NAME params`` + CR without a CRC.
- ASCII reply: text + 4 hex CRC digits + CR. ``ERROR`` + 2 hex digits on failure.
- Binary reply (A2.2, A2.6): ``C4 A5``, u16 LE body length, u16 LE CRC of those 4 bytes, the
  body, u16 LE CRC of the body.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntFlag

RESET_BAUD = 9600
RESET = "RESET"  # sent (with its CRC) after a serial break
OKAY = "OKAY"
#: The baud digit of ``COMM:<b>0000`` (A2.4 COMM row) -> bits/s.
COMM_BAUD: dict[str, int] = {"0": 9600, "1": 14400, "2": 19200, "3": 38400, "4": 57600, "5": 115200,
                             "6": 921600, "7": 1228739, "A": 230400}
#: TX/BX reply option bits the emulator produces: transformations, and out-of-volume tools reported.
REPLY_TRANSFORMS = 0x0001
REPLY_OUT_OF_VOLUME = 0x0800

_BX_START = bytes([0xC4, 0xA5])
_BX_VALID = 0x01
_BX_MISSING = 0x02
_HEX = frozenset("0123456789ABCDEFabcdef")


class Port(IntFlag):
    """Port status bits (A2.5 table)."""

    TOOL_IN_PORT = 0x01
    INITIALIZED = 0x10
    ENABLED = 0x20
    OUT_OF_VOLUME = 0x40
    PARTIALLY_IN_VOLUME = 0x80


def crc16(data: bytes) -> int:
    """The NDI CRC-16 of ``data``, bit by bit (check value of ``123456789``: 0xBB3D)."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def reply(text: str) -> bytes:
    """An ASCII reply line: ``OKAY`` -> ``OKAYA896\\r``."""
    raw = text.encode("ascii")
    return raw + b"%04X\r" % crc16(raw)


def reset_reply() -> bytes:
    """What the device sends after a serial break: ``RESETBE6F\\r``."""
    return reply(RESET)


@dataclass(frozen=True)
class Command:
    """A command line the device received. ``crc_ok`` is None for the space form (no CRC)."""

    name: str
    params: str
    crc_ok: bool | None


def read_command(line: bytes) -> Command | None:
    """One command line (without its CR), or None when it is not a command (no name, a ``:``
    form too short to hold its CRC, or a character that is not part of a name before the
    separator)."""
    text = line.decode("ascii", errors="replace")
    name_end = 0
    while name_end < len(text) and text[name_end].isalnum():
        name_end += 1
    name, sep = text[:name_end].upper(), text[name_end:name_end + 1]
    if not name:
        return None
    if sep == "":
        return Command(name, "", None)
    if sep == " ":
        return Command(name, text[name_end + 1:], None)
    if sep != ":" or len(text) < name_end + 1 + 4:
        return None
    body, digits = text[:-4], text[-4:]
    crc_ok = all(c in _HEX for c in digits) and int(digits, 16) == crc16(body.encode("ascii", "replace"))
    return Command(name, body[name_end + 1:], crc_ok)


def phsr_text(entries: list[tuple[int, int]]) -> str:
    """PHSR reply text: 2 hex digits count, then per handle 2 hex digits handle + 3 hex status."""
    return f"{len(entries):02X}" + "".join(f"{handle:02X}{status:03X}" for handle, status in entries)


@dataclass(frozen=True)
class ToolFrame:
    """One enabled handle in a TX/BX reply: ``pose`` is None for a MISSING tool, else
    (q0, qx, qy, qz, tx_mm, ty_mm, tz_mm, rms_error)."""

    handle: int
    pose: tuple[float, float, float, float, float, float, float, float] | None
    port_status: int
    frame: int


def _signed(value: float, scale: float, digits: int) -> str:
    """``sign`` + ``digits`` decimal digits of ``value * scale``, saturating."""
    limit = 10 ** digits - 1
    n = max(-limit, min(limit, round(value * scale)))
    return ("-" if n < 0 else "+") + str(abs(n)).rjust(digits, "0")


def tx_text(tools: list[ToolFrame], system_status: int) -> str:
    """TX reply text (option 0x0001, A2.5): per handle 2 hex handle, then the transform as
    4 x (sign + 5 digits, x 1e-4), 3 x (sign + 6 digits, x 0.01 mm), error (sign + 5 digits,
    x 1e-4) -- or ``MISSING`` --, 8 hex port status, 8 hex frame number, LF; then 4 hex system
    status."""
    out = [f"{len(tools):02X}"]
    for tool in tools:
        out.append(f"{tool.handle:02X}")
        if tool.pose is None:
            out.append("MISSING")
        else:
            q0, qx, qy, qz, tx, ty, tz, err = tool.pose
            out += [_signed(v, 1e4, 5) for v in (q0, qx, qy, qz)]
            out += [_signed(v, 1e2, 6) for v in (tx, ty, tz)]
            out.append(_signed(err, 1e4, 5))
        out.append(f"{tool.port_status & 0xFFFFFFFF:08X}{tool.frame & 0xFFFFFFFF:08X}\n")
    out.append(f"{system_status:04X}")
    return "".join(out)


def bx_reply(tools: list[ToolFrame], system_status: int) -> bytes:
    """A whole BX reply (option 0x0001, A2.6): header, body, body CRC."""
    body = bytearray([len(tools)])
    for tool in tools:
        body += bytes([tool.handle, _BX_MISSING if tool.pose is None else _BX_VALID])
        if tool.pose is not None:
            body += struct.pack("<8f", *tool.pose)
        body += struct.pack("<II", tool.port_status & 0xFFFFFFFF, tool.frame & 0xFFFFFFFF)
    body += struct.pack("<H", system_status)
    head = _BX_START + struct.pack("<H", len(body))
    return head + struct.pack("<H", crc16(head)) + bytes(body) + struct.pack("<H", crc16(bytes(body)))
