"""Serial-port checks and just enough of the two tracker protocols to identify a device and find
the baud rate it answers at (pyserial; every read bounded).

Flock of Birds (FOB-MAN): STREAM STOP ``?`` (0x3F), EXAMINE VALUE ``O <param>`` (0x4F); param 15
= model id (10 ASCII bytes, ``6DFOB`` ...), 1 = software revision (2 bytes), 10 = error code
(1 byte), 36 = flock status (14 bytes, one per FBB address: bit 7 accessible, bit 6 running,
bit 5 has a receiver). The baud rate is set by dip switches: a host at another rate reads noise.

NDI Aurora (combined API): commands ``NAME:params`` + CRC-16 (4 hex digits) + CR; replies text +
CRC-16 + CR, ``ERRORnn`` on failure. CRC-16/ARC (reflected 0xA001, init 0; check value 0xBB3D).
A serial break resets the device to 9600 baud (reply ``RESET`` + CRC); ``COMM:<code>0000``
switches the rate (OKAY at the old rate, then the new one); ``VER:4`` names the firmware;
``PHSR:00`` lists the port handles (``NN`` + NN x ``HH`` handle + ``SSS`` status).

The drivers own the full protocols (``drivers.tracker_serial``); the core may not import them, so
the few constants a diagnosis needs are restated here.
"""

from __future__ import annotations

import contextlib
import glob
import os
import stat
import time
from pathlib import Path

import serial

from hil.probe.runner import WireProblem

FOB_BAUD_RATES = (115200, 57600, 38400, 19200, 9600, 4800, 2400)
AURORA_BAUD_RATES = (9600, 19200, 38400, 57600, 115200, 230400, 921600, 14400, 1228739)
FOB_MODEL_IDS = ("6DFOB", "6DERC", "6DBOF", "PCBIRD", "SPACEPAD", "MOTIONSTAR", "WIRELESS")
AURORA_COMM_CODES = {9600: "0", 14400: "1", 19200: "2", 38400: "3", 57600: "4", 115200: "5",
                     921600: "6", 1228739: "7", 230400: "A"}
FOB_ERRORS = {6: "invalid RS232 command", 9: "bird is not initialized",
              11: "RS232 receive overrun or framing error (host at the wrong baud rate)",
              13: "no FBB command response", 29: "transmitter not accessible",
              30: "extended range transmitter not attached", 32: "sensor saturated"}

_STREAM_STOP = b"\x3f"
_EXAMINE = 0x4F
FOB_PARAM_REVISION = 0x01
FOB_PARAM_ERROR = 0x0A
FOB_PARAM_MODEL = 0x0F
FOB_PARAM_FLOCK_STATUS = 0x24


class WireTimeoutError(WireProblem):
    """Fewer bytes than expected before the deadline."""


# --------------------------------------------------------------------------------- the port itself
def is_url(port: str) -> bool:
    """pyserial URL (``socket://``, ``rfc2217://``, ``loop://``): no device node to check."""
    return "://" in port


def candidate_ports() -> list[str]:
    """Serial devices that exist here (for "did you mean ..." hints)."""
    found: list[str] = []
    for pattern in ("/dev/serial/by-id/*", "/dev/ttyUSB*", "/dev/ttyACM*", "/dev/ttyS[0-3]"):
        found += sorted(glob.glob(pattern))
    return found


def describe_node(path: str) -> str:
    """``crw-rw---- root:dialout`` style description of a device node."""
    st = os.stat(path)
    try:
        import grp
        import pwd

        owner = f"{pwd.getpwuid(st.st_uid).pw_name}:{grp.getgrgid(st.st_gid).gr_name}"
    except (KeyError, ImportError):
        owner = f"{st.st_uid}:{st.st_gid}"
    return f"{stat.filemode(st.st_mode)} {owner}"


def node_kind(path: str) -> str:
    """``char`` / ``file`` / ``dir`` / ``other`` (follows symlinks). Raises OSError."""
    mode = os.stat(path).st_mode
    if stat.S_ISCHR(mode):
        return "char"
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISDIR(mode):
        return "dir"
    return "other"


def resolved(path: str) -> str:
    return str(Path(path).resolve())


def open_port(port: str, baud: int) -> serial.Serial:
    """Open 8N1, no flow control, 50 ms read timeout, exclusive (fails if another program holds
    it with an exclusive lock). Raises serial.SerialException / OSError / ValueError."""
    if is_url(port):
        return serial.serial_for_url(port, baudrate=baud, timeout=0.05)
    return serial.Serial(port, baud, bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                         stopbits=serial.STOPBITS_ONE, timeout=0.05, xonxoff=False, rtscts=False,
                         dsrdtr=False, exclusive=True)


def read_exact(ser: serial.Serial, n: int, timeout_s: float) -> bytes:
    deadline = time.monotonic() + timeout_s
    buf = bytearray()
    while len(buf) < n:
        if time.monotonic() > deadline:
            raise WireTimeoutError(f"got {len(buf)} of {n} bytes within {timeout_s:g} s")
        buf += ser.read(n - len(buf))
    return bytes(buf)


def flush(ser: serial.Serial, quiet_s: float = 0.0) -> None:
    if quiet_s > 0:
        time.sleep(quiet_s)
    with contextlib.suppress(serial.SerialException, OSError):
        ser.reset_input_buffer()


# ------------------------------------------------------------------------------------ Flock of Birds
def fob_examine(ser: serial.Serial, param: int, n_bytes: int, timeout_s: float,
                address: int | None = None) -> bytes:
    """EXAMINE VALUE ``param``; with ``address`` (1..14) through RS232 TO FBB (0xF0 + address)."""
    flush(ser)
    prefix = bytes([0xF0 + address]) if address else b""
    ser.write(prefix + bytes([_EXAMINE, param]))
    return read_exact(ser, n_bytes, timeout_s)


def fob_model_id(ser: serial.Serial, timeout_s: float) -> str | None:
    """Stop any stream, ask the model id; the id when it is a Bird's, None for silence or noise."""
    ser.write(_STREAM_STOP)
    flush(ser, quiet_s=0.02)
    try:
        raw = fob_examine(ser, FOB_PARAM_MODEL, 10, timeout_s)
    except WireTimeoutError:
        return None
    text = raw.decode("ascii", errors="replace").strip().strip("\x00")
    return text if text.startswith(FOB_MODEL_IDS) else None


def fob_error_text(code: int) -> str:
    return FOB_ERRORS.get(code, f"see the FOB manual's error table, code {code}")


# ------------------------------------------------------------------------------------------ Aurora
def _crc_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0xA001 if c & 1 else c >> 1
        table.append(c)
    return tuple(table)


_CRC = _crc_table()


def ndi_crc16(data: bytes) -> int:
    """CRC-16/ARC as NDI uses it (check value of b"123456789": 0xBB3D)."""
    crc = 0
    for b in data:
        crc = (crc >> 8) ^ _CRC[(crc ^ b) & 0xFF]
    return crc


class NdiError(WireProblem):
    """The Aurora answered ERRORnn (``code``) or a reply failed its CRC (``code`` None)."""

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        self.code = code


def ndi_read_line(ser: serial.Serial, timeout_s: float) -> bytes:
    """One reply line without its CR. Raises WireTimeoutError."""
    deadline = time.monotonic() + timeout_s
    buf = bytearray()
    while not buf.endswith(b"\r"):
        if time.monotonic() > deadline:
            raise WireTimeoutError(f"no complete reply within {timeout_s:g} s (got {bytes(buf[:40])!r})")
        buf += ser.read_until(b"\r")
    return bytes(buf[:-1])


def ndi_check(line: bytes) -> str:
    """The reply text after its CRC was checked. Raises NdiError."""
    body, crc_text = line[:-4], line[-4:]
    try:
        ok = len(line) >= 4 and int(crc_text, 16) == ndi_crc16(body)
    except ValueError:
        ok = False
    if not ok:
        raise NdiError(f"reply {line[:40]!r} fails its CRC check")
    text = body.decode("ascii", errors="replace")
    if text.startswith("ERROR") and len(text) == 7:
        code = int(text[5:], 16) if all(c in "0123456789ABCDEFabcdef" for c in text[5:]) else -1
        raise NdiError(text, code)
    return text


def ndi_command(ser: serial.Serial, command: str, timeout_s: float) -> str:
    """Send ``NAME:params`` with its CRC; the checked reply text. Raises WireTimeoutError, NdiError."""
    flush(ser)
    ser.write(f"{command}{ndi_crc16(command.encode('ascii')):04X}\r".encode("ascii"))
    return ndi_check(ndi_read_line(ser, timeout_s))


def ndi_reset(ser: serial.Serial, *, break_s: float, break_as_nul: bool, timeout_s: float) -> bool:
    """Serial break at 9600 baud, then wait for ``RESET``; True when it came."""
    ser.baudrate = 9600
    flush(ser)
    with contextlib.suppress(OSError, serial.SerialException):
        ser.send_break(break_s)
    if break_as_nul:
        ser.write(b"\x00")
    reset = b"RESET" + f"{ndi_crc16(b'RESET'):04X}".encode("ascii")
    deadline = time.monotonic() + timeout_s
    seen = bytearray()
    while time.monotonic() < deadline:
        seen += ser.read_until(b"\r")
        if reset in seen:
            return True
        del seen[:-64]
    return False


def ndi_answers(ser: serial.Serial, baud: int, timeout_s: float) -> str | None:
    """Switch the host to ``baud`` and send ``VER:4``: the first firmware line when a CRC-valid
    reply comes (an ERROR reply also proves the link), else None."""
    ser.baudrate = baud
    flush(ser, quiet_s=0.02)
    try:
        return ndi_command(ser, "VER:4", timeout_s).strip().splitlines()[0]
    except NdiError as exc:
        return None if exc.code is None else f"(answers {exc})"
    except (WireTimeoutError, IndexError):
        return None


def parse_phsr(text: str) -> list[tuple[int, int]]:
    """``NN`` then NN x (``HH`` handle, ``SSS`` status). Raises ValueError."""
    n = int(text[:2], 16)
    if len(text) != 2 + 5 * n:
        raise ValueError(f"PHSR reply {text!r}: {n} handles need {2 + 5 * n} characters")
    return [(int(text[2 + 5 * i:4 + 5 * i], 16), int(text[4 + 5 * i:7 + 5 * i], 16)) for i in range(n)]
