"""An Ascension Flock of Birds on RS-232, byte-exact (FOB-MAN; reference section A1).

The bytes come from the emulator's own encoder (:mod:`emulators.trackersim.fob_wire`), written
from the manual's facts and independent of the driver's codec.

One standalone bird (address 0) or a flock of N birds on FBB addresses 1..N with the host on
the master (address 1). Implemented: RS232 TO FBB prefixes, the format commands, POINT, STREAM,
STREAM STOP (``?``, and POINT/format commands stop a stream, p.100), BUTTON MODE/READ,
EXAMINE/CHANGE VALUE (status, revision, crystal, scaling, filter, rates, error code, model id,
expanded error, addressing mode, FBB address, group mode, flock status, auto-config), RUN,
SLEEP, HEMISPHERE, REPORT RATE, XON/XOFF, group mode; error codes 6 (invalid command), 9 (bird
not initialised), 11 (framing error: host at the wrong baud). Commands whose data a driver never
needs (angle align, reference frame, offset, sync, metal) are parsed and ignored.

A pty has no RTS line: :meth:`FobDevice.reset` (control interface ``reset``) is the power cycle.
"""

from __future__ import annotations

from dataclasses import dataclass

from emulators.trackersim import fob_wire as fw
from emulators.trackersim.device import EmulatedDevice
from emulators.trackersim.faults import Faults
from emulators.trackersim.poses import PoseSource
from emulators.trackersim.pty_link import PtyLink
from hil.geometry.transform import RigidTransform

# Data bytes after each command byte (FOB-MAN ch.7). EXAMINE/CHANGE are special-cased.
_DATA_BYTES: dict[int, int] = {
    0x4A: 12, 0x71: 6, 0x4D: 1, 0x4C: 2, 0x73: 2, 0x30: 1, 0x4B: 6, 0x48: 12, 0x72: 6, 0x41: 1,
}
_NO_DATA = frozenset({0x57, 0x75, 0x76, 0x4E, 0x58, 0x42, 0x56, 0x59, 0x5A, 0x5D, 0x5C, 0x51, 0x52, 0x53,
                      0x54, 0x46, 0x47, 0x40, 0x3F, 0x2F, 0x7A, 0x74, 0x11, 0x13})
_RATE_DIVISOR = {0x51: 1, 0x52: 2, 0x53: 8, 0x54: 32}
# A bird without a usable field (sleeping, or the pose source has none) reports zeros (p.63).
_ZERO_POSE = RigidTransform.identity()


@dataclass
class _Bird:
    address: int
    fmt: fw.Format = fw.Format.POSITION_ANGLES
    button_mode: bool = False
    scaling: int = 0
    running: bool = False
    sleeping: bool = False


class FobDevice(EmulatedDevice):
    """The emulated flock. ``n_birds`` = 1 is a standalone bird at address 0."""

    def __init__(self, link: PtyLink, poses: PoseSource, faults: Faults, *, baud: int = 115200,
                 n_birds: int = 1, rate_hz: float = 100.0) -> None:
        if not 1 <= n_birds <= 14:
            raise ValueError(f"n_birds must be 1..14, got {n_birds}")
        self.n_birds = n_birds
        self.power_up_rate_hz = rate_hz
        super().__init__(link, poses, faults, baud=baud)
        self.reset()

    # --- state ------------------------------------------------------------------------------------
    def reset(self) -> None:
        with self.lock:
            standalone = self.n_birds == 1
            addrs = [0] if standalone else list(range(1, self.n_birds + 1))
            self.birds = {a: _Bird(a, running=standalone) for a in addrs}
            self.master = addrs[0]
            self.group_mode = False
            self.auto_configured = standalone
            self.stream = False
            self._stream_target: int | None = None
            self.rate_hz = self.power_up_rate_hz
            self.report_divisor = 1
            self.error_code = 0
            self.error_info = 0
            self.xoff = False
            self._pending = bytearray()
            self._next_record_s = self.now_s()

    def sensor_id(self, bird: _Bird) -> str:
        return str(bird.address)

    def _set_error(self, code: int, info: int = 0) -> None:
        self.error_code, self.error_info = code, info

    # --- input ------------------------------------------------------------------------------------
    def on_framing_error(self, data: bytes) -> None:
        self._set_error(11)

    def on_bytes(self, data: bytes) -> None:
        self._pending += data
        while self._pending:
            used = self._parse_one(self._pending)
            if used == 0:
                return  # need more bytes
            del self._pending[:used]

    def _parse_one(self, buf: bytearray) -> int:
        """Execute the first command in ``buf``; returns bytes used (0 = incomplete)."""
        pos = 0
        target: int | None = None
        b = buf[0]
        if 0xF1 <= b <= 0xFE or 0xE0 <= b <= 0xEF:
            target = b - 0xF0 if b >= 0xF0 else b - 0xE0 + 16
            pos = 1
        elif b == 0xA0:
            if len(buf) < 2:
                return 0
            target, pos = buf[1], 2
        if len(buf) <= pos:
            return 0
        cmd = buf[pos]
        pos += 1
        if cmd == fw.EXAMINE:
            if len(buf) < pos + 1:
                return 0
            self._examine(buf[pos], target)
            return pos + 1
        if cmd == fw.CHANGE:
            if len(buf) < pos + 1:
                return 0
            param = buf[pos]
            n = fw.CHANGE_BYTES.get(param)
            if n is None:
                self._set_error(6)
                return pos + 1
            if len(buf) < pos + 1 + n:
                return 0
            self._change(param, bytes(buf[pos + 1:pos + 1 + n]), target)
            return pos + 1 + n
        if cmd in _DATA_BYTES:
            n = _DATA_BYTES[cmd]
            if len(buf) < pos + n:
                return 0
            self._command(cmd, bytes(buf[pos:pos + n]), target)
            return pos + n
        if cmd in _NO_DATA:
            self._command(cmd, b"", target)
            return pos
        self._set_error(6)  # invalid RS232 command
        return pos

    def _bird(self, target: int | None) -> _Bird | None:
        addr = self.master if target is None else target
        bird = self.birds.get(addr)
        if bird is None:
            self._set_error(13, addr)  # no FBB command response
        return bird

    def _command(self, cmd: int, data: bytes, target: int | None) -> None:
        fmt = fw.Format.for_command(cmd)
        if fmt is not None:
            bird = self._bird(target)
            if bird is not None:
                bird.fmt = fmt
            self.stream = False
            return
        if cmd == fw.POINT:
            self.stream = False
            self._send_records(target)
        elif cmd == fw.STREAM:
            self.stream = True
            self._stream_target = target
            self._next_record_s = self.now_s()
        elif cmd == fw.STREAM_STOP:
            self.stream = False
        elif cmd == fw.BUTTON_MODE:
            bird = self._bird(target)
            if bird is not None:
                bird.button_mode = bool(data[0])
        elif cmd == fw.BUTTON_READ:
            self.send(b"\x00")
        elif cmd == fw.SLEEP:
            for bird in self.birds.values():
                bird.sleeping = True
        elif cmd == fw.RUN:
            for bird in self.birds.values():
                bird.sleeping = False
        elif cmd in _RATE_DIVISOR:
            self.report_divisor = _RATE_DIVISOR[cmd]
        elif cmd == fw.XOFF:
            self.xoff = True
        elif cmd == fw.XON:
            self.xoff = False
        elif cmd == fw.METAL_ERROR:
            self.send(b"\x00")

    def _examine(self, param: int, target: int | None) -> None:
        bird = self._bird(target)
        if bird is None:
            return
        if param == fw.BIRD_STATUS:
            reply = fw.BirdState(master=bird.address == self.master, initialized=self.auto_configured,
                                 error=self.error_code != 0, running=bird.running, sleeping=bird.sleeping,
                                 stream=self.stream, fmt=bird.fmt).word()
        elif param == fw.SOFTWARE_REVISION:
            reply = b"\x03\x43"  # 3.67
        elif param == fw.CRYSTAL_SPEED:
            reply = b"\x28\x00"  # 40 MHz
        elif param == fw.POSITION_SCALING:
            reply = bytes([bird.scaling, 0])
        elif param == fw.FILTER:
            reply = b"\x04\x00"
        elif param == fw.MEASUREMENT_RATE:
            reply = round(self.rate_hz * 256).to_bytes(2, "little")
        elif param == fw.ERROR_CODE:
            reply = bytes([self.error_code])
            self.error_code, self.error_info = 0, 0
        elif param == fw.MODEL_ID:
            reply = b"6DFOB     "
        elif param == fw.EXPANDED_ERROR_CODE:
            reply = bytes([self.error_code, self.error_info])
        elif param == fw.ADDRESSING_MODE:
            reply = b"\x00"
        elif param == fw.FBB_ADDRESS:
            reply = bytes([bird.address])
        elif param == fw.GROUP_MODE:
            reply = bytes([int(self.group_mode)])
        elif param == fw.FLOCK_STATUS:
            reply = bytes(self._flock_status(a) for a in range(1, 15))
        elif param in fw.EXAMINE_BYTES:
            reply = bytes(fw.EXAMINE_BYTES[param])
        else:
            self._set_error(6)
            return
        self.send(reply)

    def _flock_status(self, address: int) -> int:
        """The flock system status byte of one FBB address (0: no bird there); the master holds
        the transmitter."""
        bird = self.birds.get(address)
        if bird is None:
            return 0
        return (fw.FLOCK_ACCESSIBLE | fw.FLOCK_HAS_SENSOR | (fw.FLOCK_RUNNING if bird.running else 0)
                | (fw.FLOCK_TRANSMITTER if address == self.master else 0))

    def _change(self, param: int, data: bytes, target: int | None) -> None:
        bird = self._bird(target)
        if bird is None:
            return
        if param == fw.POSITION_SCALING:
            value = int.from_bytes(data, "little")
            if value not in (0, 1):
                self._set_error(6)
                return
            bird.scaling = value
        elif param == fw.MEASUREMENT_RATE:
            rate = int.from_bytes(data, "little") / 256.0
            if not 20.0 <= rate <= 144.0:
                self._set_error(6)
                return
            self.rate_hz = rate
        elif param == fw.GROUP_MODE:
            self.group_mode = bool(data[0])
        elif param == fw.AUTO_CONFIG:
            n = data[0]
            if self.n_birds == 1 or n > self.n_birds or n < 1:
                self._set_error(33)  # slave configuration error
                return
            for a, b in self.birds.items():
                b.running = a <= n
            self.auto_configured = True

    # --- output -----------------------------------------------------------------------------------
    def _record(self, bird: _Bird) -> bytes:
        T = self.poses.pose(self.sensor_id(bird), self.now_s())
        if T is None or bird.sleeping:
            T = _ZERO_POSE
        return fw.record(T, bird.fmt, full_scale_in=72.0 if bird.scaling else 36.0,
                         button=0 if bird.button_mode else None,
                         address=bird.address if self.group_mode else None)

    def _damage(self, rec: bytes) -> bytes:
        now = self.now_s()
        out = bytearray(rec)
        if self.faults.fire("lost_phase", now):
            out[0] &= 0x7F
        spec = self.faults.fire("truncate", now)
        if spec is not None and len(out) > 1:
            out = out[: self.faults.randint(1, len(out) - 1)]
        spec = self.faults.fire("garbage", now)
        if spec is not None:
            at = self.faults.randint(0, len(out))
            out[at:at] = self.faults.random_bytes(self.faults.n_bytes(spec), spec.mask)
        return bytes(out)

    def _send_records(self, target: int | None) -> None:
        if not self.auto_configured:
            self._set_error(9)  # bird is not initialized
            return
        if self.group_mode:
            birds = [b for a, b in sorted(self.birds.items()) if b.running]
        else:
            bird = self._bird(target)
            birds = [bird] if bird is not None and bird.running else []
        self.send(b"".join(self._damage(self._record(b)) for b in birds))

    def tick(self) -> float:
        if not self.stream:
            return 0.02
        period = self.report_divisor / self.rate_hz
        now = self.now_s()
        if now < self._next_record_s:
            return self._next_record_s - now
        if not self.xoff:
            self._send_records(self._stream_target)
        self._next_record_s += period
        if self._next_record_s < now:  # fell behind (a busy machine): do not burst
            self._next_record_s = now + period
        return self._next_record_s - now

