"""The serial-port steps any serial device's probe starts with, and bounded reads (pyserial).

:func:`open_port_steps` checks that the port exists (and is a character device), that the user may
read and write it, and opens it 8N1 with an exclusive lock: three steps, ``port_exists``,
``port_permissions`` and ``port_opens`` (the first two are skipped for a pyserial URL such as
``socket://``). A driver's probe (registered through ``hil_register_probes``) then speaks its own
protocol on the open port with :func:`read_exact` and :func:`flush`, and closes it with
:func:`close_port`. Nothing here knows a device protocol.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import os
import stat
import time
from pathlib import Path

import serial

from hil.probe.runner import Checklist, Finding, Outcome, WireProblem

DIALOUT_HINT = ("add your user to the group owning the port (usually dialout): "
                "sudo usermod -aG dialout $USER, then log out and in")
#: Read timeout of the opened port (s): a read returns at least this often.
READ_TIMEOUT_S = 0.05


class WireTimeoutError(WireProblem):
    """Fewer bytes than expected before the deadline."""


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


def open_port(port: str, baud: int) -> serial.Serial:
    """Open 8N1, no flow control, :data:`READ_TIMEOUT_S` read timeout, exclusive (fails if another
    program holds it with an exclusive lock). Raises serial.SerialException / OSError / ValueError."""
    if is_url(port):
        return serial.serial_for_url(port, baudrate=baud, timeout=READ_TIMEOUT_S)
    return serial.Serial(port, baud, bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                         stopbits=serial.STOPBITS_ONE, timeout=READ_TIMEOUT_S, xonxoff=False, rtscts=False,
                         dsrdtr=False, exclusive=True)


def close_port(ser: serial.Serial) -> None:
    """Close the port; an error here is not the user's problem."""
    with contextlib.suppress(serial.SerialException, OSError):
        ser.close()


def read_exact(ser: serial.Serial, n: int, timeout_s: float) -> bytes:
    """Exactly ``n`` bytes. Raises WireTimeoutError when fewer came within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    buf = bytearray()
    while len(buf) < n:
        if time.monotonic() > deadline:
            raise WireTimeoutError(f"got {len(buf)} of {n} bytes within {timeout_s:g} s")
        buf += ser.read(n - len(buf))
    return bytes(buf)


def read_line(ser: serial.Serial, end: bytes, timeout_s: float) -> bytes:
    """Bytes up to and without ``end``. Raises WireTimeoutError when no whole line came in time."""
    deadline = time.monotonic() + timeout_s
    buf = bytearray()
    while not buf.endswith(end):
        if time.monotonic() > deadline:
            raise WireTimeoutError(f"no complete reply within {timeout_s:g} s (got {bytes(buf[:40])!r})")
        buf += ser.read_until(end)
    return bytes(buf[:-len(end)])


def flush(ser: serial.Serial, quiet_s: float = 0.0) -> None:
    """Wait ``quiet_s`` (s), then drop what was received."""
    if quiet_s > 0:
        time.sleep(quiet_s)
    with contextlib.suppress(serial.SerialException, OSError):
        ser.reset_input_buffer()


def open_port_steps(cl: Checklist, port: str, baud: int, *, section: str = "") -> serial.Serial | None:
    """Steps ``port_exists``, ``port_permissions`` (not for a URL) and ``port_opens`` at ``baud``.

    Blocking, each step bounded by the checklist's timeout. ``section`` names the setup section in
    hints (default: the device's role). Returns the open port (the caller closes it with
    :func:`close_port`), or None when a step failed.
    """
    where = section or cl.report.role
    if not is_url(port):
        if cl.step("port_exists", lambda: _exists(port, where), what=f"looking for {port}") is None:
            return None
        if cl.step("port_permissions", lambda: _permissions(port)) is None:
            return None
    out = cl.step("port_opens", lambda: _opens(port, baud), what=f"opening {port}")
    return None if out is None else out.value


def _exists(port: str, where: str) -> Outcome:
    if not os.path.lexists(port):
        found = candidate_ports()
        raise Finding(f"serial port {port} does not exist",
                      "is the adapter plugged in and powered? serial ports here: "
                      + (", ".join(found) if found else "none found (ls /dev/ttyUSB* /dev/ttyACM*)")
                      + f"\nprefer a stable /dev/serial/by-id/... path in [{where}] port",
                      {"port": port, "candidates": found})
    if not os.path.exists(port):
        raise Finding(f"serial port {port} is a dangling link (to {os.readlink(port)})",
                      "the adapter was unplugged or renumbered; plug it in again")
    kind = node_kind(port)
    if kind != "char":
        raise Finding(f"{port} exists but is a {kind}, not a serial device",
                      f"point [{where}] port at the tty device (/dev/ttyUSB0, /dev/serial/by-id/...)")
    target = str(Path(port).resolve())
    via = f" (-> {target})" if target != port else ""
    return Outcome(f"serial port {port}{via} exists ({describe_node(port)})",
                   data={"port": port, "device": target})


def _permissions(port: str) -> Outcome:
    if not os.access(port, os.R_OK | os.W_OK):
        raise Finding(f"no read/write permission on {port} ({describe_node(port)})", DIALOUT_HINT)
    return Outcome(f"read/write permission on {port}")


def _opens(port: str, baud: int) -> Outcome:
    try:
        ser = open_port(port, baud)
    except (serial.SerialException, OSError, ValueError) as exc:
        err = getattr(exc, "errno", None)
        text = str(exc)
        if err == errno.EBUSY or "busy" in text.lower() or "lock" in text.lower():
            raise Finding(f"{port} is in use by another program ({text})",
                          "close the other program (another hil, a serial terminal, ModemManager: "
                          "sudo systemctl stop ModemManager); fuser -v " + port) from None
        if err in (errno.EACCES, errno.EPERM):
            raise Finding(f"permission denied opening {port}", DIALOUT_HINT) from None
        raise Finding(f"{port} does not open: {text}",
                      "unplug and replug the adapter; check dmesg for USB-serial errors") from None
    return Outcome(f"{port} opens at {baud} baud, 8N1", value=ser)
