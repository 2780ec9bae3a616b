"""Ascension Flock of Birds over RS-232 (pyserial): :class:`FlockOfBirdsTracker`.

Start-up (FOB-MAN p.29, p.35-37; GOBBI ``fbReset``): RTS high for ``reset_hold_s`` then low
and a ``reset_settle_s`` wait (a pseudo-terminal has no RTS: the driver logs it and goes on), a
STREAM STOP and a flush, then the model id (EXAMINE 15; anything that is not a Bird's id means
the baud rate or the cable is wrong), the software revision and the error register (EXAMINE 1,
10). A flock is auto-configured to its highest sensor address (CHANGE 50) and read in group
mode (CHANGE 35); each bird gets the record format, BUTTON MODE 0 and the position scaling
(CHANGE 3) through RS232 TO FBB. Then STREAM, or POINT at ``poll_rate_hz``.

The Bird has no clock: a sample's ``t_ns`` is the host (context clock) time at which the
record's last byte was read, ``seq`` a per-sensor host counter. Records go through
:class:`~drivers.tracker_serial.fob_protocol.RecordSynchronizer`, so a pose is only built from a
record whose framing and content checks passed.
"""

from __future__ import annotations

import contextlib
import time
from collections import deque

import numpy as np
import serial

from drivers.interfaces.errors import DeviceFaultError, ProtocolError
from drivers.interfaces.tracker import TrackerSample
from drivers.tracker_serial import fob_protocol as fp
from drivers.tracker_serial.base import SerialFactory, SerialPoseTracker
from drivers.tracker_serial.config import FlockOfBirdsConfig
from hil.clock import Clock

_FORMATS = {
    "position_angles": fp.FobFormat.POSITION_ANGLES,
    "position_matrix": fp.FobFormat.POSITION_MATRIX,
    "position_quaternion": fp.FobFormat.POSITION_QUATERNION,
}
_BUTTONS = {0x10: "button_left", 0x30: "button_middle", 0x70: "button_right"}


class FlockOfBirdsTracker(SerialPoseTracker):
    """A standalone Bird or a flock on one serial port (host on the master).

    Args:
        config: the validated config.
        name: device name used in errors (the setup role).
        clock: the context clock for time stamps and the timeout (default: monotonic).
        serial_factory: ``serial.Serial`` or a stand-in with its signature (tests).
    """

    def __init__(self, config: FlockOfBirdsConfig, *, name: str = "tracker", clock: Clock | None = None,
                 serial_factory: SerialFactory | None = None) -> None:
        super().__init__(name, tuple(config.sensors), port=config.port, baud_rate=config.baud_rate,
                         timeout_s=config.timeout_s, max_consecutive_damaged=config.max_consecutive_damaged,
                         clock=clock, serial_factory=serial_factory)
        self.config = config
        self._by_address = {addr: sensor for sensor, addr in config.sensors.items()}
        self._seq: dict[str, int] = dict.fromkeys(config.sensors, 0)
        self._n_birds = 1 if config.standalone else max(config.sensors.values())
        self._layout = fp.RecordLayout(_FORMATS[config.record_format], button_mode=False,
                                       group_mode=not config.standalone)
        self._full_scale_mm = fp.position_full_scale_mm(0 if config.position_scale_in == 36 else 1)
        self._sync: fp.RecordSynchronizer | None = None
        self._last_pos: dict[str, np.ndarray] = {}
        self._jump: dict[str, np.ndarray] = {}
        self.gated_records = 0

    # --- commands -----------------------------------------------------------------------------------
    def _examine(self, param: int, n_bytes: int, *, address: int | None = None) -> bytes:
        self._flush_input()
        self._write(fp.examine(param, address=address))
        return self._read_exact(n_bytes, self.config.response_timeout_s, f"EXAMINE VALUE {param}")

    def _check_error_register(self, when: str) -> int:
        code = self._examine(fp.PARAM_ERROR_CODE, 1)[0]
        if code and code in fp.FATAL_ERROR_CODES:
            raise DeviceFaultError(self.name, f"{when}: Flock error {code} ({fp.error_text(code)}), fatal")
        return code

    def _reset(self) -> None:
        cfg = self.config
        try:
            self.ser.rts = True
            time.sleep(cfg.reset_hold_s)
            self.ser.rts = False
            time.sleep(cfg.reset_settle_s)
            self.info["reset"] = "rts"
        except (OSError, serial.SerialException) as exc:
            # A pseudo-terminal (the emulator) or a USB adapter without modem lines.
            self.log.warning("rts_reset_unavailable", device=self.name, port=cfg.port, error=str(exc))
            self.info["reset"] = "none (no RTS line)"
        self._write(bytes([fp.CMD_STREAM_STOP]))
        self._flush_input(quiet_s=0.02)  # FOB-MAN p.100: discard input >= 10 ms after stopping

    def _start_device(self) -> None:
        cfg = self.config
        if cfg.reset_on_open:
            self._reset()
        else:
            self._write(bytes([fp.CMD_STREAM_STOP]))
            self._flush_input(quiet_s=0.02)
        model_raw = self._examine(fp.PARAM_MODEL_ID, 10)
        model = model_raw.decode("ascii", errors="replace").strip()
        if not model.startswith(fp.MODEL_IDS):
            raise ProtocolError(self.name, f"model id {model_raw!r} is not a Bird's; is baud_rate "
                                           f"{cfg.baud_rate} what the dip switches say?")
        if model.startswith(fp.MODEL_ID_ERC):
            self._full_scale_mm = fp.position_full_scale_mm(0, extended_range=True)
        rev = self._examine(fp.PARAM_SOFTWARE_REVISION, 2)
        self.info.update(model=model, firmware=f"{rev[0]}.{rev[1]}", baud_rate=str(cfg.baud_rate))
        self._check_error_register("at start-up")
        fmt_cmd = bytes([self._layout.fmt.command])
        scaling = (0 if cfg.position_scale_in == 36 else 1).to_bytes(2, "little")
        if cfg.standalone:
            self._write(fmt_cmd + bytes([fp.CMD_BUTTON_MODE, 0]))
            self._write(fp.change(fp.PARAM_POSITION_SCALING, scaling))
        else:
            self._write(fp.change(fp.PARAM_AUTO_CONFIG, bytes([self._n_birds])))
            time.sleep(cfg.auto_config_wait_s)
            for addr in range(1, self._n_birds + 1):
                prefix = fp.rs232_to_fbb(addr)
                self._write(prefix + fmt_cmd + prefix + bytes([fp.CMD_BUTTON_MODE, 0]))
                self._write(fp.change(fp.PARAM_POSITION_SCALING, scaling, address=addr))
            self._write(fp.change(fp.PARAM_GROUP_MODE, b"\x01"))
        if cfg.measurement_rate_hz is not None:
            self._write(fp.change(fp.PARAM_MEASUREMENT_RATE,
                                  round(cfg.measurement_rate_hz * 256).to_bytes(2, "little")))
        code = self._check_error_register("after configuration")
        if code:
            raise DeviceFaultError(self.name,
                                   f"configuration refused: Flock error {code} ({fp.error_text(code)})")
        status = fp.BirdStatus.from_bytes(self._examine(fp.PARAM_BIRD_STATUS, 2))
        if status.fmt is not self._layout.fmt:
            raise ProtocolError(self.name,
                                f"bird status says format {status.fmt}, expected {self._layout.fmt}")
        addresses = None if cfg.standalone else range(1, self._n_birds + 1)
        self._sync = fp.RecordSynchronizer(self._layout, full_scale_mm=self._full_scale_mm,
                                           addresses=addresses)
        if cfg.mode == "stream":
            self._write(bytes([fp.CMD_STREAM]))

    def _stop_device(self) -> None:
        if self._ser is None:
            return
        self._write(bytes([fp.CMD_STREAM_STOP]))
        self._write(bytes([fp.CMD_SLEEP]))
        with contextlib.suppress(OSError, serial.SerialException):
            self.ser.rts = True  # standby (GOBBI fbClose)

    # --- reading ------------------------------------------------------------------------------------
    def _samples(self, records: list[fp.FobRecord], t_ns_of: dict[int, int] | None, t_now_ns: int) -> list[
            TrackerSample]:
        out = []
        for rec in records:
            addr = 0 if self.config.standalone else rec.address
            sensor = self._by_address.get(addr) if addr is not None else None
            if sensor is None:
                continue  # a bird of the flock nobody asked for
            if not self._passes_step_gate(sensor, rec.T_tracker_from_sensor.t):
                continue
            self._seq[sensor] += 1
            t_ns = t_ns_of.get(rec.end_offset, t_now_ns) if t_ns_of else t_now_ns
            flags = (_BUTTONS[rec.button],) if rec.button in _BUTTONS else ()
            out.append(TrackerSample(sensor, rec.T_tracker_from_sensor, None, t_ns, self._seq[sensor],
                                     flags=flags))
        return out

    def _passes_step_gate(self, sensor: str, pos: np.ndarray) -> bool:
        gate = self.config.max_step_mm
        prev = self._last_pos.get(sensor)
        if gate is not None and prev is not None and float(np.linalg.norm(pos - prev)) > gate:
            cand = self._jump.get(sensor)
            if cand is None or float(np.linalg.norm(pos - cand)) > gate:
                self._jump[sensor] = pos
                self.gated_records += 1
                self.log.debug("record_gated", device=self.name, sensor=sensor,
                               step_mm=float(np.linalg.norm(pos - prev)))
                return False
        self._jump.pop(sensor, None)
        self._last_pos[sensor] = pos
        return True

    def _reader_loop(self) -> None:
        if self.config.mode == "stream":
            self._stream_loop()
        else:
            self._point_loop()

    def _stream_loop(self) -> None:
        sync = self._sync
        assert sync is not None
        rx_total = 0
        chunks: deque[tuple[int, int]] = deque(maxlen=256)  # (stream offset at chunk end, t_ns)
        while not self._stop.is_set():
            data = self._read(0)
            if not data:
                continue
            now = self.clock.now_ns()
            rx_total += len(data)
            chunks.append((rx_total, now))
            damaged_before = sync.stats.damaged
            records = sync.feed(data)
            times = {r.end_offset: _arrival(chunks, r.end_offset, now) for r in records}
            self._publish(self._samples(records, times, now))
            if sync.stats.damaged > damaged_before:
                self._record_damage(sync.consecutive_damaged, "framing/phasing or implausible content")

    def _point_loop(self) -> None:
        sync = self._sync
        assert sync is not None
        n_records = self._n_birds if self._layout.group_mode else 1
        n_bytes = n_records * self._layout.length
        period_s = 1.0 / self.config.poll_rate_hz
        char_s = 10.0 / self.config.baud_rate
        next_s = time.monotonic()
        while not self._stop.is_set():
            self._flush_input()
            sync.reset()
            self._write(bytes([fp.CMD_POINT]))
            damaged_before = sync.stats.damaged
            data = bytearray()
            deadline = time.monotonic() + self.config.response_timeout_s
            while len(data) < n_bytes and time.monotonic() < deadline and not self._stop.is_set():
                data += self._read(n_bytes - len(data))
            now = self.clock.now_ns()
            if data:
                time.sleep(3 * char_s + 0.002)  # the line must be quiet after a whole reply
                extra = self._read(0) if self._waiting() else b""
                records = sync.feed(bytes(data) + extra) + sync.end_of_reply()
                if extra or len(data) < n_bytes:
                    records = []  # the reply was longer or shorter than asked: trust none of it
                    sync.stats.damaged += 1
                    sync.consecutive_damaged += 1
                self._publish(self._samples(records, None, now))
                if sync.stats.damaged > damaged_before:
                    self._record_damage(sync.consecutive_damaged, "POINT reply damaged")
            next_s += period_s
            delay = next_s - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_s = time.monotonic()


def _arrival(chunks: deque[tuple[int, int]], end_offset: int, default_ns: int) -> int:
    """Host time of the chunk that brought the byte just before ``end_offset``."""
    for offset, t_ns in chunks:
        if offset >= end_offset:
            return t_ns
    return default_ns
