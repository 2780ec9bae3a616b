"""An NDI Aurora on its serial port, byte-exact (NDI combined API; reference section A2).

Power-up and reset state: 9600 8N1, not initialised. Wired tools are plugged into port handles
0x0A, 0x0B, ... (``n_tools``). Implemented: INIT, COMM (the OKAY is sent at the old baud, then
the device switches), VER, BEEP, GETINFO (answered ERROR01 like older firmware, so a host falls
back to VER), PHSR, PHF, PINIT, PENA, TSTART, TSTOP, TX and BX with reply option 0x0001 (+0x0800),
both command forms (``NAME:params`` + CRC, ``NAME params``); ``ERROR04`` for a bad command CRC,
``ERROR01`` unknown command, ``ERROR0C`` invalid in the current mode, ``ERROR0E``/``ERROR0F`` port
not initialised/enabled, ``ERROR10`` system not initialised.

Break: a pty carries no serial break. The receiver of a real UART reads a break as a NUL byte
(a framing error with all-zero data), so the emulator takes a NUL byte from the host as the
break (the driver's ``break_as_nul`` option sends one). NUL never occurs in a valid command.

Tool status: a sensor whose pose source gives None is ``MISSING``; a pose outside the box
volume gets the out-of-volume port status bit (0x40) and is sent with its transform only when the
host asked for out-of-volume transforms (reply option 0x0800), else as ``MISSING`` with that bit;
one within ``margin_mm`` of a face gets the partially-in-volume bit (0x80). Frame numbers count at
``frame_rate_hz``. The faults ``tool_missing`` and ``out_of_volume`` put the chosen handles in those
states whatever their pose; ``reset`` resets the device mid-session (below); ``comm_baud`` makes
the next COMM leave the device at another rate than the one asked (after its OKAY).

Reset: a break (see below), the ``reset`` fault or the control interface's ``reset``: back to the
power-up state (9600 baud, not initialised, not tracking, handles neither initialised nor
enabled, the frame counter restarted). After a break and after the ``reset`` fault the device sends
``RESETBE6F`` at 9600 baud (a host still at the COMM rate reads it as noise).

The bytes come from the emulator's own encoder (:mod:`emulators.trackersim.ndi_wire`), written
from the manual's facts and independent of the driver's codec.
"""

from __future__ import annotations

import numpy as np

from emulators.trackersim import ndi_wire as nw
from emulators.trackersim.device import EmulatedDevice
from emulators.trackersim.faults import Faults
from emulators.trackersim.poses import PoseSource
from emulators.trackersim.pty_link import PtyLink

_PS = nw.Port
_RMS_ERROR = 0.05  # the error figure every valid transform reports
_SYSTEM_STATUS = 0  # no system fault


class AuroraDevice(EmulatedDevice):
    """The emulated Aurora system control unit."""

    def __init__(self, link: PtyLink, poses: PoseSource, faults: Faults, *, n_tools: int = 2,
                 frame_rate_hz: float = 40.0,
                 volume_min_mm: tuple[float, float, float] = (-250.0, -250.0, -550.0),
                 volume_max_mm: tuple[float, float, float] = (250.0, 250.0, -50.0),
                 margin_mm: float = 20.0) -> None:
        if not 1 <= n_tools <= 16:
            raise ValueError(f"n_tools must be 1..16, got {n_tools}")
        self.n_tools = n_tools
        self.frame_rate_hz = frame_rate_hz
        self.volume_min = np.asarray(volume_min_mm, dtype=float)
        self.volume_max = np.asarray(volume_max_mm, dtype=float)
        self.margin_mm = margin_mm
        super().__init__(link, poses, faults, baud=nw.RESET_BAUD)
        self.reset()

    def reset(self) -> None:
        with self.lock:
            self.baud = nw.RESET_BAUD
            self.initialized = False
            self.tracking = False
            self.handles: dict[int, int] = {0x0A + i: _PS.TOOL_IN_PORT for i in range(self.n_tools)}
            self._line = bytearray()
            self._frame_t0_s = self.now_s()

    def frame_number(self) -> int:
        return int((self.now_s() - self._frame_t0_s) * self.frame_rate_hz)

    # --- input ------------------------------------------------------------------------------------
    def handle_input(self, data: bytes) -> None:
        if b"\x00" in data:  # the break, whatever the baud
            data = data[data.rindex(b"\x00") + 1:]
            self.reset()
            self.send(nw.reset_reply())
        if data:
            super().handle_input(data)

    def on_bytes(self, data: bytes) -> None:
        self._line += data
        while b"\r" in self._line:
            i = self._line.index(b"\r")
            line = bytes(self._line[:i])
            del self._line[:i + 1]
            self._execute(line)
        if len(self._line) > 1024:
            self._line.clear()
            self._reply_error(0x02)

    def _reply(self, text: str) -> None:
        self.send(self._damage(nw.reply(text), ascii_reply=True))

    def _reply_error(self, code: int) -> None:
        self._reply(f"ERROR{code:02X}")

    def _damage(self, reply: bytes, *, ascii_reply: bool) -> bytes:
        now = self.now_s()
        out = bytearray(reply)
        if self.faults.fire("bad_crc", now):
            if ascii_reply:
                i = len(out) - 2  # last CRC digit
                out[i] = ord("0") if out[i] != ord("0") else ord("1")
            else:
                out[-1] ^= 0x5A
        spec = self.faults.fire("truncate", now)
        if spec is not None and len(out) > 1:
            out = out[: self.faults.randint(1, len(out) - 1)]
        spec = self.faults.fire("garbage", now)
        if spec is not None:
            at = self.faults.randint(0, len(out))
            out[at:at] = self.faults.random_bytes(self.faults.n_bytes(spec), spec.mask)
        return bytes(out)

    def _execute(self, line: bytes) -> None:
        cmd = nw.read_command(line)
        if cmd is None:
            self._reply_error(0x01)
            return
        if cmd.crc_ok is False:
            self._reply_error(0x04)
            return
        name, params = cmd.name, cmd.params
        handler = getattr(self, f"_cmd_{name.lower()}", None)
        if handler is None:
            self._reply_error(0x01)
            return
        handler(params)

    # --- commands ---------------------------------------------------------------------------------
    def _cmd_init(self, params: str) -> None:
        self.initialized = True
        self._reply(nw.OKAY)

    def _cmd_comm(self, params: str) -> None:
        if len(params) != 5 or params[0] not in nw.COMM_BAUD or params[1:] != "0000":
            self._reply_error(0x06 if len(params) == 5 else 0x07)
            return
        self._reply(nw.OKAY)  # at the old settings
        wrong = self.faults.fire("comm_baud", self.now_s())
        self.baud = nw.COMM_BAUD[params[0]] if wrong is None or wrong.baud is None else wrong.baud

    def _cmd_ver(self, params: str) -> None:
        self._reply("NDI AURORA Control Firmware\nFreeze Tag: AURORA Rev 008\n"
                    "(C) Northern Digital Inc. (emulated by trackersim)\n")

    def _cmd_beep(self, params: str) -> None:
        self._reply("1")

    def _cmd_getinfo(self, params: str) -> None:
        self._reply_error(0x01)

    def _handle(self, params: str) -> int | None:
        try:
            h = int(params[:2], 16)
        except ValueError:
            self._reply_error(0x07)
            return None
        if h not in self.handles:
            self._reply_error(0x2B)  # handle not allocated
            return None
        return h

    def _cmd_phsr(self, params: str) -> None:
        mode = params or "00"
        entries: list[tuple[int, int]] = []
        for h, st in sorted(self.handles.items()):
            init, ena = bool(st & _PS.INITIALIZED), bool(st & _PS.ENABLED)
            if (mode == "00" or (mode == "02" and not init) or (mode == "03" and init and not ena)
                    or (mode == "04" and ena)):
                entries.append((h, int(st) & 0xFFF))
        if mode not in ("00", "01", "02", "03", "04"):
            self._reply_error(0x09)
            return
        self._reply(nw.phsr_text(entries))

    def _cmd_phf(self, params: str) -> None:
        if self._handle(params) is not None:
            self._reply(nw.OKAY)

    def _cmd_pinit(self, params: str) -> None:
        if not self.initialized:
            self._reply_error(0x10)
            return
        h = self._handle(params)
        if h is not None:
            self.handles[h] |= _PS.INITIALIZED
            self._reply(nw.OKAY)

    def _cmd_pena(self, params: str) -> None:
        h = self._handle(params)
        if h is None:
            return
        if len(params) != 3 or params[2] not in "SDB":
            self._reply_error(0x09)
            return
        if not self.handles[h] & _PS.INITIALIZED:
            self._reply_error(0x0E)
            return
        self.handles[h] |= _PS.ENABLED
        self._reply(nw.OKAY)

    def _cmd_tstart(self, params: str) -> None:
        if not self.initialized or self.tracking:
            self._reply_error(0x10 if not self.initialized else 0x0C)
            return
        self.tracking = True
        self._frame_t0_s = self.now_s()
        self._reply(nw.OKAY)

    def _cmd_tstop(self, params: str) -> None:
        if not self.tracking:
            self._reply_error(0x0C)
            return
        self.tracking = False
        self._reply(nw.OKAY)

    def _tracking_reply(self, params: str) -> list[nw.ToolFrame] | None:
        if not self.tracking:
            self._reply_error(0x0C)
            return None
        try:
            mode = int(params or "0001", 16)
        except ValueError:
            self._reply_error(0x07)
            return None
        if mode & ~(nw.REPLY_TRANSFORMS | nw.REPLY_OUT_OF_VOLUME):
            self._reply_error(0x23)  # reply options this emulator does not produce
            return None
        frame = self.frame_number()
        now = self.now_s()
        gone = self.faults.fire("tool_missing", now)
        away = self.faults.fire("out_of_volume", now)
        tools = []
        for h, st in sorted(self.handles.items()):
            if not st & _PS.ENABLED:
                continue
            T = None if gone is not None and gone.hits(h) else self.poses.pose(f"{h:02X}", now)
            if T is None:
                tools.append(nw.ToolFrame(h, None, int(st), frame))
                continue
            bits = int(_PS.OUT_OF_VOLUME) if away is not None and away.hits(h) else self._volume_bits(T.t)
            if bits & _PS.OUT_OF_VOLUME and not mode & nw.REPLY_OUT_OF_VOLUME:
                tools.append(nw.ToolFrame(h, None, int(st) | bits, frame))  # not normally reported
                continue
            q = T.as_quaternion()
            pose = (float(q[0]), float(q[1]), float(q[2]), float(q[3]),
                    float(T.t[0]), float(T.t[1]), float(T.t[2]), _RMS_ERROR)
            tools.append(nw.ToolFrame(h, pose, int(st) | bits, frame))
        return tools

    def _volume_bits(self, p: np.ndarray) -> int:
        if np.any(p < self.volume_min) or np.any(p > self.volume_max):
            return int(_PS.OUT_OF_VOLUME)
        if np.any(p < self.volume_min + self.margin_mm) or np.any(p > self.volume_max - self.margin_mm):
            return int(_PS.PARTIALLY_IN_VOLUME)
        return 0

    def _cmd_tx(self, params: str) -> None:
        tools = self._tracking_reply(params)
        if tools is not None:
            self._reply(nw.tx_text(tools, _SYSTEM_STATUS))

    def _cmd_bx(self, params: str) -> None:
        tools = self._tracking_reply(params)
        if tools is not None:
            self.send(self._damage(nw.bx_reply(tools, _SYSTEM_STATUS), ascii_reply=False))

    def tick(self) -> float:
        if self.faults.fire("reset", self.now_s()) is not None:
            self.reset()
            self.send(nw.reset_reply())  # at 9600, whatever the host's rate
        return 0.02

