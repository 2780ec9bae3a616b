"""NDI Aurora over its serial port (pyserial): :class:`AuroraTracker`.

Start-up (NDICAPI, SKS ``_connect_aurora``): open at 9600 8N1; serial break and wait for
``RESET`` (``reset_timeout_s``); ``INIT:``; ``COMM:<b>0000`` — the OKAY comes at the old baud,
then (100 ms later) the host switches; ``VER:4`` checks the link at the new rate and names the
firmware; ``PHSR:02`` -> ``PINIT`` until no handle needs it, ``PHSR:03`` -> ``PENA:hhD``; every
configured handle must then be enabled; ``TSTART:``. Close: ``TSTOP:``, ``COMM:00000`` and the
host back to 9600 (PLUS).

Reading is a poll model: the reader thread sends ``BX:0801`` (or ``TX:0801``) at
``poll_rate_hz`` and parses the one reply; input is flushed before each poll, so a damaged
reply costs exactly that reply. A frame already published (polling faster than the device
measures) is not published again, so a device whose frame counter stalls times out.
Every reply is CRC-checked (ASCII CRC, or BX header and body
CRCs) before any field is used. A sample's ``seq`` is the device frame number and ``t_ns`` the
frame's time on the context clock: ``offset + frame / frame_rate_hz``, where ``offset`` is the
smallest ``receive time - frame time`` seen so far (the least-delayed reply).
Tool status: MISSING or out of volume -> ``missing`` (no pose); partially in volume -> a pose
with the ``partially_out`` flag.

Device reset mid-tracking (a power dip, a cable pulled and pushed back): the device is back at
9600 baud, not initialised, not tracking. At the host's COMM rate the polls then get no answer; at
9600 they get ``ERROR0C``/``ERROR10``. Either way ``latest()`` raises (``DeviceTimeoutError`` once
``timeout_s`` passed without a valid frame, ``DeviceFaultError`` on the refusal), and when nothing
was heard for ``reinit_after_s`` (or at once on the refusal) the reader thread runs the whole
start-up again (break, INIT, COMM, PINIT/PENA, TSTART), every ``reinit_after_s`` until it succeeds
or the driver is closed; a success clears the condition and samples flow again
(``tracker_reinitialised``). ``reinit_after_s = None`` turns this off: the condition then stays.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable

import serial

from drivers.interfaces.errors import DeviceFaultError, DeviceTimeoutError, DriverError, ProtocolError
from drivers.interfaces.tracker import TrackerSample
from drivers.tracker_serial import aurora_protocol as ap
from drivers.tracker_serial.base import SerialFactory, SerialPoseTracker, TruncatedReplyError
from drivers.tracker_serial.config import AuroraConfig
from hil.clock import Clock

_BX_MAX_BODY = 4096
#: Log events of the re-initialisation after a device reset (module doc).
EV_REINITIALISING = "tracker_reinitialising"
EV_REINIT_FAILED = "tracker_reinit_failed"
EV_REINITIALISED = "tracker_reinitialised"


class AuroraTracker(SerialPoseTracker):
    """An NDI Aurora with wired tools on port handles.

    Args:
        config: the validated config.
        name: device name used in errors (the setup role).
        clock: the context clock for time stamps and the timeout (default: monotonic).
        serial_factory: ``serial.Serial`` or a stand-in with its signature (tests).
    """

    def __init__(self, config: AuroraConfig, *, name: str = "tracker", clock: Clock | None = None,
                 serial_factory: SerialFactory | None = None) -> None:
        super().__init__(name, tuple(config.sensors), port=config.port, baud_rate=ap.RESET_BAUD,
                         timeout_s=config.timeout_s, max_consecutive_damaged=config.max_consecutive_damaged,
                         clock=clock, serial_factory=serial_factory)
        self.config = config
        self._by_handle = {int(h, 16): sensor for sensor, h in config.sensors.items()}
        self._frame_offset_ns: int | None = None
        self._frame_period_ns = 1e9 / config.frame_rate_hz
        self._last_frame: dict[str, int] = {}

    # --- commands -----------------------------------------------------------------------------------
    def _read_line(self, timeout_s: float, what: str) -> bytes:
        """One reply line without its ``\\r``."""
        deadline = time.monotonic() + timeout_s
        buf = bytearray()
        while not buf.endswith(b"\r"):
            if time.monotonic() > deadline:
                raise (TruncatedReplyError if buf else DeviceTimeoutError)(
                    self.name, f"{what}: no complete reply within {timeout_s:g} s "
                               f"on {self._port_name} (got {bytes(buf[:40])!r})")
            buf += self._read_until_cr()
        return bytes(buf[:-1])

    def command(self, command: str) -> str:
        """Send one command (``NAME:params``, CRC added) and return the checked reply text.

        Raises:
            DeviceTimeoutError: no reply in ``response_timeout_s``.
            ProtocolError: the reply fails its CRC.
            DeviceFaultError: the device answered ERRORnn.
        """
        self._flush_input()
        self._write(ap.frame_command(command))
        line = self._read_line(self.config.response_timeout_s, command)
        try:
            return ap.check_reply(line)
        except ap.NdiReplyError as exc:
            raise DeviceFaultError(self.name, f"{command}: {exc}") from exc
        except ap.NdiDecodeError as exc:
            raise ProtocolError(self.name, f"{command}: {exc}") from exc

    def _expect_okay(self, command: str) -> None:
        reply = self.command(command)
        if reply != ap.OKAY:
            raise ProtocolError(self.name, f"{command}: expected OKAY, got {reply!r}")

    def _reset(self, abort: Callable[[], bool] = lambda: False) -> None:
        """Serial break at 9600 baud and wait for ``RESET`` (``reset_timeout_s``, or until ``abort()``).

        Raises:
            DeviceTimeoutError: no RESET in time (or aborted).
        """
        cfg = self.config
        self.ser.baudrate = ap.RESET_BAUD
        self._flush_input()
        try:
            self.ser.send_break(cfg.break_duration_s)
        except (OSError, serial.SerialException) as exc:
            self.log.warning("serial_break_failed", device=self.name, error=str(exc))
        if cfg.break_as_nul:
            self._write(b"\x00")
        deadline = time.monotonic() + cfg.reset_timeout_s
        seen = bytearray()
        while time.monotonic() < deadline and not abort():
            seen += self._read_until_cr()
            if seen.endswith(ap.RESET_REPLY):
                return
            if len(seen) > 4096:
                del seen[:-64]
        raise DeviceTimeoutError(
            self.name, f"no RESET after a serial break within {cfg.reset_timeout_s:g} s on {self._port_name} "
                       f"(power, cable? got {bytes(seen[-40:])!r}; a pseudo-terminal needs break_as_nul)")

    def _start_device(self) -> None:
        if self.config.reset_on_open:
            self._reset()
        self._initialise()

    def _initialise(self) -> None:
        """From the reset state (9600 baud): INIT, COMM, VER, PINIT/PENA of every handle, TSTART."""
        cfg = self.config
        self._expect_okay("INIT:")
        if cfg.baud_rate != ap.RESET_BAUD:
            self._expect_okay(ap.comm_command(cfg.baud_rate))
            time.sleep(0.1)
            self.ser.baudrate = cfg.baud_rate
        try:
            version = self.command("VER:4")
        except (DeviceTimeoutError, ProtocolError) as exc:
            raise ProtocolError(self.name,
                                f"no valid reply at {cfg.baud_rate} baud after COMM: {exc}") from exc
        self.info.update(firmware=version.strip().splitlines()[0] if version.strip() else "?",
                         baud_rate=str(cfg.baud_rate))
        for _ in range(8):  # PINIT may reveal more handles (NDICAPI/SKS loop)
            pending = ap.parse_phsr(self.command("PHSR:02"))
            if not pending:
                break
            for handle, _status in pending:
                self._expect_okay(f"PINIT:{handle:02X}")
        for handle, _status in ap.parse_phsr(self.command("PHSR:03")):
            self._expect_okay(f"PENA:{handle:02X}D")
        enabled = {h for h, _ in ap.parse_phsr(self.command("PHSR:04"))}
        for sensor, handle_text in cfg.sensors.items():
            if int(handle_text, 16) not in enabled:
                raise DeviceFaultError(
                    self.name, f"sensor {sensor!r}: port handle {handle_text} is not enabled (tool not "
                               f"plugged in?); enabled handles: {sorted(f'{h:02X}' for h in enabled)}")
        self.info["handles"] = ",".join(f"{h:02X}" for h in sorted(enabled))
        self._expect_okay("TSTART:")
        self._frame_offset_ns = None
        self._last_frame.clear()

    def _stop_device(self) -> None:
        if self._ser is None:
            return
        with contextlib.suppress(DeviceTimeoutError, ProtocolError, DeviceFaultError):
            self._expect_okay("TSTOP:")
        if self.ser.baudrate != ap.RESET_BAUD:
            with contextlib.suppress(DeviceTimeoutError, ProtocolError, DeviceFaultError):
                self._expect_okay("COMM:00000")
                time.sleep(0.1)
            self.ser.baudrate = ap.RESET_BAUD

    # --- reading ------------------------------------------------------------------------------------
    def _poll_once(self) -> ap.TrackingReply:
        """One TX/BX exchange. Raises NdiDecodeError, NdiReplyError or DeviceTimeoutError."""
        timeout_s = self.config.response_timeout_s
        if self.config.reply_format == "tx":
            self._write(ap.frame_command("TX:0801"))
            return ap.parse_tx(ap.check_reply(self._read_line(timeout_s, "TX:0801")))
        self._write(ap.frame_command("BX:0801"))
        head = self._read_exact(2, timeout_s, "BX:0801")
        if head == b"ER":  # an ASCII ERROR reply
            rest = self._read_line(timeout_s, "BX:0801")
            ap.check_reply(head + rest)
            raise ap.NdiDecodeError(f"BX reply {head + rest!r} is neither binary nor an error")
        head += self._read_exact(4, timeout_s, "BX:0801 header")
        length = ap.parse_bx_header(head)
        if length > _BX_MAX_BODY:
            raise ap.NdiDecodeError(f"BX body length {length} is implausible")
        return ap.parse_bx_body(self._read_exact(length + 2, timeout_s, "BX:0801 body"))

    def _frame_time_ns(self, frame: int, rx_ns: int) -> int:
        frame_ns = round(frame * self._frame_period_ns)
        cand = rx_ns - frame_ns
        if self._frame_offset_ns is None or cand < self._frame_offset_ns:
            self._frame_offset_ns = cand
        return self._frame_offset_ns + frame_ns

    def _samples(self, reply: ap.TrackingReply, rx_ns: int) -> list[TrackerSample]:
        out = []
        for rec in reply.handles:
            sensor = self._by_handle.get(rec.handle)
            if sensor is None or rec.frame is None:
                continue
            last = self._last_frame.get(sensor)
            if last is not None and rec.frame == last:
                continue  # polled faster than the device measures: the same frame again
            if last is not None and rec.frame < last:
                self._frame_offset_ns = None  # the counter restarted (TSTART again)
            self._last_frame[sensor] = rec.frame
            t_ns = self._frame_time_ns(rec.frame, rx_ns)
            T = rec.transform()
            missing = T is None or bool(rec.port_status & ap.PortStatus.OUT_OF_VOLUME)
            out.append(TrackerSample(sensor, None if missing else T, rec.error_rms, t_ns, rec.frame,
                                     missing=missing, flags=rec.flags))
        return out

    def _reinitialise(self, why: str) -> bool:
        """Run the start-up again in the reader thread (module doc); True when tracking again.
        A failure is logged and leaves the condition as it is (the caller retries later)."""
        self.log.warning(EV_REINITIALISING, device=self.name, reason=why)
        try:
            self._reset(abort=self._stop.is_set)
            self._initialise()
        except DriverError as exc:
            self.log.warning(EV_REINIT_FAILED, device=self.name, error=str(exc))
            return False
        with self._lock:
            self._condition = None  # stale until the first new frame (latest()'s own timeout)
        self.log.warning(EV_REINITIALISED, device=self.name, **self.info)
        return True

    def _reader_loop(self) -> None:
        period_s = 1.0 / self.config.poll_rate_hz
        reinit_after_s = self.config.reinit_after_s
        next_s = time.monotonic()
        heard_s = next_s  # the last time the device answered anything (valid or damaged)
        consecutive = 0
        while not self._stop.is_set():
            self._flush_input()
            try:
                reply = self._poll_once()
            except ap.NdiReplyError as exc:
                heard_s = time.monotonic()
                if exc.code in (0x0C, 0x10):  # not tracking any more (device reset / power cycle)
                    self._set_condition(DeviceFaultError(self.name, f"tracking data request refused: {exc}"))
                    if reinit_after_s is None:
                        return
                    if not self._reinitialise(f"tracking data request refused: {exc}"):
                        self._stop.wait(reinit_after_s)
                    heard_s = next_s = time.monotonic()
                    consecutive = 0
                    continue
                consecutive += 1
                self._record_damage(consecutive, str(exc))
            except (ap.NdiDecodeError, TruncatedReplyError) as exc:
                heard_s = time.monotonic()
                consecutive += 1
                self._record_damage(consecutive, str(exc))
                self._flush_input(quiet_s=0.005)
            except DeviceTimeoutError as exc:
                self.log.debug("poll_timeout", device=self.name, error=str(exc))
                if reinit_after_s is not None and time.monotonic() - heard_s >= reinit_after_s:
                    self._reinitialise(f"no answer for {time.monotonic() - heard_s:.2f} s")
                    heard_s = next_s = time.monotonic()  # a failed attempt is retried after reinit_after_s
                    consecutive = 0
                    continue
            else:
                heard_s = time.monotonic()
                consecutive = 0
                self._publish(self._samples(reply, self.clock.now_ns()))
            next_s += period_s
            delay = next_s - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_s = time.monotonic()
