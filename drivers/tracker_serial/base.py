"""What the serial tracker drivers share: the port, the reader thread, ``latest()``.

Threading model: after ``open()`` one background thread per driver owns the port (it streams
or polls) and publishes the newest valid sample per sensor under a lock; ``latest()`` never
blocks on I/O. The thread records a condition instead of raising: a dead port
(DisconnectedError), a device error (DeviceFaultError), or a run of damaged records
(ProtocolError); ``latest()`` raises it. Staleness is checked in ``latest()`` on the context
clock: no valid record for longer than ``timeout_s`` raises DeviceTimeoutError. A sample is
only ever built from a record that passed every framing and checksum test.
"""

from __future__ import annotations

import contextlib
import threading
import time
from abc import abstractmethod
from collections.abc import Callable

import serial

from drivers.interfaces.errors import (
    DeviceTimeoutError,
    DisconnectedError,
    DriverError,
    ProtocolError,
)
from drivers.interfaces.tracker import PoseTracker, TrackerSample
from hil.clock import Clock, MonotonicClock
from hil.log import get_logger

SerialFactory = Callable[..., serial.Serial]


class TruncatedReplyError(DeviceTimeoutError):
    """Part of a reply came, then the line went quiet: a damaged reply rather than silence."""


class SerialPoseTracker(PoseTracker):
    """Base of :class:`FlockOfBirdsTracker` and :class:`AuroraTracker`."""

    def __init__(self, name: str, sensor_names: tuple[str, ...], *, port: str, baud_rate: int,
                 timeout_s: float, max_consecutive_damaged: int, clock: Clock | None,
                 serial_factory: SerialFactory | None) -> None:
        super().__init__(name)
        self._sensor_names = sensor_names
        self._port_name = port
        self._open_baud = baud_rate
        self._timeout_ns = round(timeout_s * 1e9)
        self._max_damaged = max_consecutive_damaged
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self._serial_factory: SerialFactory = serial_factory or serial.Serial
        self._ser: serial.Serial | None = None
        self._lock = threading.Lock()
        self._latest: dict[str, TrackerSample] = {}
        self._last_valid_ns: int | None = None
        self._condition: DriverError | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.damaged_records = 0
        self.info: dict[str, str] = {}
        self._listeners: list[Callable[[TrackerSample], None]] = []
        self.log = get_logger(f"drivers.tracker_serial.{type(self).__name__}")

    @property
    def sensors(self) -> tuple[str, ...]:
        return self._sensor_names

    # --- port -------------------------------------------------------------------------------------
    @property
    def ser(self) -> serial.Serial:
        if self._ser is None:
            raise DisconnectedError(self.name, "serial port not open")
        return self._ser

    def _open_port(self, baud_rate: int) -> None:
        try:
            self._ser = self._serial_factory(
                self._port_name, baud_rate, bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE, timeout=0.05, xonxoff=False, rtscts=False, dsrdtr=False)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DisconnectedError(self.name, f"cannot open serial port {self._port_name}: {exc}") from exc

    def _read_exact(self, n: int, timeout_s: float, what: str) -> bytes:
        """Read exactly ``n`` bytes or raise DeviceTimeoutError naming ``what``."""
        deadline = time.monotonic() + timeout_s
        buf = bytearray()
        while len(buf) < n:
            if time.monotonic() > deadline:
                raise (TruncatedReplyError if buf else DeviceTimeoutError)(
                    self.name, f"{what}: got {len(buf)} of {n} bytes within {timeout_s:g} s on "
                               f"{self._port_name} (power, cable, baud rate?)")
            buf += self._read(n - len(buf))
        return bytes(buf)

    def _read(self, n: int) -> bytes:
        """Up to ``n`` bytes (``n`` <= 0: what is waiting, at least 1), within the port timeout."""
        try:
            if n <= 0:
                n = max(1, self.ser.in_waiting)
            return bytes(self.ser.read(n))
        except (serial.SerialException, OSError) as exc:
            raise DisconnectedError(self.name, f"serial port {self._port_name}: {exc}") from exc

    def _read_until_cr(self) -> bytes:
        try:
            return bytes(self.ser.read_until(b"\r"))
        except (serial.SerialException, OSError) as exc:
            raise DisconnectedError(self.name, f"serial port {self._port_name}: {exc}") from exc

    def _waiting(self) -> int:
        try:
            return int(self.ser.in_waiting)
        except (serial.SerialException, OSError) as exc:
            raise DisconnectedError(self.name, f"serial port {self._port_name}: {exc}") from exc

    def _write(self, data: bytes) -> None:
        try:
            self.ser.write(data)
        except (serial.SerialException, OSError) as exc:
            raise DisconnectedError(self.name, f"serial port {self._port_name}: {exc}") from exc

    def _flush_input(self, quiet_s: float = 0.0) -> None:
        """Discard input; with ``quiet_s`` first wait that long so a reply in flight is dropped too."""
        if quiet_s > 0:
            time.sleep(quiet_s)
        with contextlib.suppress(serial.SerialException, OSError):
            self.ser.reset_input_buffer()

    # --- lifecycle ----------------------------------------------------------------------------------
    def _open(self) -> None:
        self._open_port(self._open_baud)
        try:
            self._start_device()
        except BaseException:
            self._close_port()
            raise
        self._stop.clear()
        self._last_valid_ns = self.clock.now_ns()  # the timeout runs from the start of streaming
        self._thread = threading.Thread(target=self._run_reader, name=f"{self.name}-reader", daemon=True)
        self._thread.start()
        self.log.info("tracker_opened", device=self.name, port=self._port_name, **self.info)

    def _close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        try:
            self._stop_device()
        except (DriverError, serial.SerialException, OSError) as exc:
            self.log.warning("tracker_stop_failed", device=self.name, error=str(exc))
        self._close_port()

    def _close_port(self) -> None:
        if self._ser is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                self._ser.close()
            self._ser = None

    def _run_reader(self) -> None:
        try:
            self._reader_loop()
        except DriverError as exc:
            self._set_condition(exc)
        except (serial.SerialException, OSError) as exc:
            self._set_condition(DisconnectedError(self.name, f"serial port {self._port_name}: {exc}"))

    @abstractmethod
    def _start_device(self) -> None:
        """Reset, identify and configure the device, and start it streaming (port is open)."""

    @abstractmethod
    def _stop_device(self) -> None:
        """Stop streaming and leave the device in its idle state (best effort)."""

    @abstractmethod
    def _reader_loop(self) -> None:
        """Runs in the reader thread until ``self._stop`` is set."""

    # --- publishing ---------------------------------------------------------------------------------
    def add_listener(self, listener: Callable[[TrackerSample], None]) -> None:
        """Call ``listener(sample)`` for every sample published (in the reader thread; keep it short).

        For recording every sample; ``latest()`` only keeps the newest per sensor.
        """
        self._listeners.append(listener)

    def _publish(self, samples: list[TrackerSample]) -> None:
        for listener in self._listeners:
            for s in samples:
                listener(s)
        with self._lock:
            for s in samples:
                self._latest[s.sensor] = s
            if samples:
                self._last_valid_ns = max(s.t_ns for s in samples)
                if isinstance(self._condition, ProtocolError):
                    self._condition = None

    def _record_damage(self, consecutive: int, detail: str) -> None:
        self.damaged_records += 1
        self.log.debug("record_damaged", device=self.name, consecutive=consecutive, detail=detail)
        if consecutive >= self._max_damaged:
            self._set_condition(ProtocolError(
                self.name, f"{consecutive} damaged records in a row from {self._port_name} "
                           f"(last: {detail}); wrong baud rate or a noisy line?"))

    def _set_condition(self, exc: DriverError) -> None:
        with self._lock:
            if self._condition is None or not isinstance(self._condition, DisconnectedError):
                self._condition = exc
        self.log.warning("tracker_condition", device=self.name, error=str(exc))

    def latest(self) -> dict[str, TrackerSample]:
        """The newest valid sample per sensor (a sensor with none yet is absent). Never blocks on I/O.

        Raises:
            LifecycleError: not active.
            DisconnectedError: the port failed.
            DeviceFaultError: the device reported an error it does not recover from.
            ProtocolError: ``max_consecutive_damaged`` damaged records in a row, until a valid one.
            DeviceTimeoutError: no valid record for longer than ``timeout_s`` (context clock).
        """
        self.require_active("latest")
        with self._lock:
            if self._condition is not None:
                raise self._condition
            now = self.clock.now_ns()
            if self._last_valid_ns is not None and now - self._last_valid_ns > self._timeout_ns:
                raise DeviceTimeoutError(
                    self.name, f"no valid record from {self._port_name} for "
                               f"{(now - self._last_valid_ns) * 1e-9:.2f} s "
                               f"(timeout {self._timeout_ns * 1e-9:g} s)")
            return dict(self._latest)
