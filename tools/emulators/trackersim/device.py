"""What both emulated trackers share: the pty loop, time, the baud check, faults on output."""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable

from emulators.trackersim.faults import Faults
from emulators.trackersim.poses import PoseSource
from emulators.trackersim.pty_link import PtyLink


class EmulatedDevice(ABC):
    """A device on the emulator side of a :class:`PtyLink`.

    Wrong baud: a pty moves bytes whatever the speed, so the device compares the speed the host
    set on its side of the pty with its own. On a mismatch it reads the host's bytes as framing
    errors (ignored) and what it sends arrives as garbage, as on a real line.
    """

    def __init__(self, link: PtyLink, poses: PoseSource, faults: Faults, *, baud: int,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.link = link
        self.poses = poses
        self.faults = faults
        self.baud = baud
        self._clock = clock
        self._t0 = clock()
        self.lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def now_s(self) -> float:
        """Seconds since the emulator started."""
        return self._clock() - self._t0

    def device_baud(self) -> int:
        """The speed the device actually runs at (the wrong_baud fault overrides it)."""
        return self.faults.wrong_baud or self.baud

    def baud_matches(self) -> bool:
        host = self.link.host_baud()
        return host is None or host == self.device_baud()

    def send(self, data: bytes) -> None:
        """Send to the host, through the silence and baud-mismatch effects."""
        if not data or self.faults.silent(self.now_s()):
            return
        if not self.baud_matches():
            host = self.link.host_baud() or self.device_baud()
            n = max(1, min(4 * len(data), round(len(data) * host / self.device_baud())))
            data = self.faults.random_bytes(n)
        self.link.write(data)

    def handle_input(self, data: bytes) -> None:
        if not self.baud_matches():
            self.on_framing_error(data)
            return
        self.on_bytes(data)

    @abstractmethod
    def on_bytes(self, data: bytes) -> None:
        """Bytes the host sent at the right speed."""

    def on_framing_error(self, data: bytes) -> None:  # noqa: B027 - optional hook
        """Bytes the host sent at the wrong speed (default: lost)."""

    @abstractmethod
    def tick(self) -> float:
        """Periodic work (streaming, frame counter). Returns seconds until it is due again."""

    @abstractmethod
    def reset(self) -> None:
        """Power cycle: back to the power-up state."""

    # --- loop -------------------------------------------------------------------------------------
    def serve_forever(self) -> None:
        """Run until :meth:`stop` (in the calling thread)."""
        wait_s = 0.0
        while not self._stop.is_set():
            data = self.link.read(min(max(wait_s, 0.0005), 0.02))
            with self.lock:
                if data:
                    self.handle_input(data)
                wait_s = self.tick()

    def start(self) -> None:
        """Serve in a daemon thread."""
        self._thread = threading.Thread(target=self.serve_forever, name=type(self).__name__, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.link.close()
