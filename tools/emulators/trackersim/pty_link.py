"""The emulator's end of a pseudo-terminal: raw mode, non-blocking writes, the host's baud rate.

A pty carries no modem lines and no break; it does carry the termios settings the host
program (pyserial) makes on its side, so the emulator reads the host's baud rate with
``tcgetattr`` and can refuse to understand a host at the wrong speed.
"""

from __future__ import annotations

import contextlib
import os
import select
import termios
import tty

_SPEEDS: dict[int, int] = {
    getattr(termios, f"B{b}"): b
    for b in (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
    if hasattr(termios, f"B{b}")
}


class PtyLink:
    """A pty pair; ``path`` is the device the host opens. The emulator keeps the slave open too,
    so the host may close and reopen the port without the emulator seeing a hang-up."""

    def __init__(self) -> None:
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd)
        tty.setraw(self.master_fd)
        os.set_blocking(self.master_fd, False)
        self.path = os.ttyname(self.slave_fd)
        self._closed = False

    def host_baud(self) -> int | None:
        """The input speed the host configured on its side, or None if unknown."""
        try:
            attrs = termios.tcgetattr(self.slave_fd)
        except termios.error:
            return None
        return _SPEEDS.get(attrs[5])

    def read(self, timeout_s: float) -> bytes:
        """Bytes the host wrote, waiting at most ``timeout_s``; b"" when none."""
        if self._closed:
            return b""
        ready, _, _ = select.select([self.master_fd], [], [], max(0.0, timeout_s))
        if not ready:
            return b""
        try:
            return os.read(self.master_fd, 4096)
        except (BlockingIOError, OSError):
            return b""

    def write(self, data: bytes) -> int:
        """Write what the pty accepts now; drop the rest (like a line nobody listens to)."""
        if self._closed or not data:
            return 0
        try:
            return os.write(self.master_fd, data)
        except (BlockingIOError, OSError):
            return 0

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for fd in (self.master_fd, self.slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)
