"""``hil probe`` for an NDI Aurora (``driver = "aurora"``): the serial port, the reset on a serial
break, the firmware, the configured baud rate and a tool on every configured port handle.

Registered through ``hil_register_probes`` (:mod:`drivers.tracker_serial.plugin`); the framing, the
CRC-16, the COMM codes and the PHSR layout come from :mod:`drivers.tracker_serial.aurora_protocol`.
A serial break resets the device to 9600 baud (reply ``RESET`` + CRC); ``VER:4`` names the
firmware and proves the link at a rate (a CRC-valid reply, or an ``ERRORnn``); ``COMM`` switches
the rate (OKAY at the old rate); ``PHSR:00`` lists the port handles. The Aurora is left at 9600
baud, where a new session starts. The driver-level checks (open, stream) follow.
"""

from __future__ import annotations

import contextlib
import termios
import time
from collections.abc import Callable

import serial

from drivers.tracker_serial import aurora_protocol as ap
from drivers.tracker_serial.config import AuroraConfig
from hil.probe.context import ProbeContext, field_s
from hil.probe.runner import Checklist, Finding, Outcome, WireProblem
from hil.probe.serial_port import WireTimeoutError, close_port, flush, open_port_steps, read_line

#: Wait after COMM before talking at the new rate (s; NDICAPI sleeps 100 ms).
COMM_SETTLE_S = 0.1
#: The order a silent Aurora is asked in: the rates the OS has a standard termios speed for first,
#: then the custom-divisor ones (14400, 1228739), which an adapter or a pseudo-terminal may accept
#: without really running at them, so that they cannot shadow the true rate.
SCAN_BAUD_RATES: tuple[int, ...] = tuple(sorted(ap.BAUD_RATES,
                                                key=lambda rate: (not hasattr(termios, f"B{rate}"), rate)))


class NdiError(WireProblem):
    """The Aurora answered ``ERRORnn`` (``code``) or a reply failed its CRC (``code`` None)."""

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        self.code = code


def command(ser: serial.Serial, text: str, timeout_s: float) -> str:
    """Send ``NAME:params`` with its CRC; the checked reply text.

    Raises:
        WireTimeoutError: no whole reply in time.  NdiError: an ``ERRORnn`` reply or a bad CRC.
    """
    flush(ser)
    ser.write(ap.frame_command(text))
    line = read_line(ser, b"\r", timeout_s)
    try:
        return ap.check_reply(line)
    except ap.NdiReplyError as exc:
        raise NdiError(f"ERROR{exc.code:02X}", exc.code) from None
    except ap.NdiDecodeError:
        raise NdiError(f"reply {line[:40]!r} fails its CRC check") from None


def reset(ser: serial.Serial, *, break_s: float, break_as_nul: bool, timeout_s: float) -> bool:
    """Serial break at the reset rate, then wait for the ``RESET`` reply; True when it came."""
    ser.baudrate = ap.RESET_BAUD
    flush(ser)
    with contextlib.suppress(OSError, serial.SerialException):
        ser.send_break(break_s)
    if break_as_nul:
        ser.write(b"\x00")
    deadline = time.monotonic() + timeout_s
    seen = bytearray()
    while time.monotonic() < deadline:
        seen += ser.read_until(b"\r")
        if ap.RESET_REPLY in seen:
            return True
        del seen[:-64]
    return False


def answers(ser: serial.Serial, baud: int, timeout_s: float) -> str | None:
    """Switch the host to ``baud`` and send ``VER:4``: the first firmware line when a CRC-valid
    reply comes (an ``ERRORnn`` reply also proves the link), else None."""
    ser.baudrate = baud
    flush(ser, quiet_s=0.02)
    try:
        return command(ser, "VER:4", timeout_s).strip().splitlines()[0]
    except NdiError as exc:
        return None if exc.code is None else f"(answers {exc})"
    except (WireTimeoutError, IndexError):
        return None


def probe_aurora(cl: Checklist, cfg: AuroraConfig, ctx: ProbeContext) -> None:
    """Steps ``port_exists``, ``port_permissions``, ``port_opens``, ``reset`` (or ``answers`` with
    ``reset_on_open = false``), ``identity``, ``baud_rate`` and ``tools``; the port is closed on
    return, the Aurora back at 9600 baud when the probe switched it."""
    ser = open_port_steps(cl, cfg.port, ap.RESET_BAUD)
    if ser is None:
        return
    reply_s = min(field_s(cfg, "response_timeout_s", 1.0), max(0.3, cl.timeout_s / 4))
    try:
        if _checks(cl, cfg, ser, reply_s) and cfg.baud_rate != ap.RESET_BAUD:
            with contextlib.suppress(NdiError, WireTimeoutError, serial.SerialException, OSError):
                command(ser, ap.comm_command(ap.RESET_BAUD), reply_s)  # where a new session starts
                time.sleep(COMM_SETTLE_S)
    finally:
        close_port(ser)


def _checks(cl: Checklist, cfg: AuroraConfig, ser: serial.Serial, reply_s: float) -> bool:
    """The steps after the port opened; True when the Aurora was switched to the configured rate."""
    scan_s = len(SCAN_BAUD_RATES) * (reply_s + 0.05) + cl.timeout_s

    def scan(skip: int | None) -> tuple[int, str] | None:
        for rate in SCAN_BAUD_RATES:
            if rate != skip:
                found = answers(ser, rate, reply_s)
                if found is not None:
                    return rate, found
        return None

    first: Callable[[], Outcome] = (_reset(cfg, ser, reply_s, scan) if cfg.reset_on_open
                                    else _answers(ser, reply_s, scan))
    name = "reset" if cfg.reset_on_open else "answers"
    limit = (field_s(cfg, "reset_timeout_s", 7.0) if cfg.reset_on_open else 0.0) + scan_s + cl.timeout_s
    if cl.step(name, first, timeout_s=limit,
               what="resetting the Aurora with a serial break" if cfg.reset_on_open else "") is None:
        return False

    def identity() -> Outcome:
        lines = [ln.strip() for ln in command(ser, "VER:4", reply_s).strip().splitlines() if ln.strip()]
        shown = lines[:2] + [ln for ln in lines[2:] if "serial" in ln.lower()]
        return Outcome(f"identity: {' / '.join(shown) or '?'}", data={"firmware": lines})

    if cl.step("identity", identity, what="asking the firmware version (VER:4)") is None:
        return False
    if cl.step("baud_rate", _baud_rate(cfg.baud_rate, ser, reply_s, scan), timeout_s=scan_s + cl.timeout_s,
               what=f"switching to {cfg.baud_rate} baud") is None:
        return False
    cl.step("tools", _tools(cfg, ser, reply_s), what="listing port handles (PHSR:00)")
    return True


Scan = Callable[[int | None], tuple[int, str] | None]


def _reset(cfg: AuroraConfig, ser: serial.Serial, reply_s: float, scan: Scan) -> Callable[[], Outcome]:
    reset_s = cfg.reset_timeout_s

    def step() -> Outcome:
        if reset(ser, break_s=cfg.break_duration_s, break_as_nul=cfg.break_as_nul, timeout_s=reset_s):
            command(ser, "INIT:", reply_s)
            return Outcome("the Aurora resets on a serial break (RESET at 9600 baud) and initialises")
        found = scan(None)
        if found is not None:
            rate, version = found
            raise Finding(f"no RESET after a serial break, but the Aurora answers at {rate} baud ({version})",
                          "the serial adapter may not send breaks, or the device is stuck at another rate: "
                          "power-cycle the Aurora (it starts at 9600); a pseudo-terminal needs "
                          "break_as_nul = true",
                          {"answers_at_baud": rate})
        raise Finding(f"no RESET within {reset_s:g} s after a serial break, and no reply to VER at any "
                      "standard rate",
                      "is the Aurora (system control unit) powered and its serial cable on this port? "
                      "a pseudo-terminal (emulator) needs break_as_nul = true")

    return step


def _answers(ser: serial.Serial, reply_s: float, scan: Scan) -> Callable[[], Outcome]:
    def step() -> Outcome:
        if answers(ser, ap.RESET_BAUD, reply_s) is not None:
            command(ser, "INIT:", reply_s)
            return Outcome("the Aurora answers at 9600 baud (no reset: reset_on_open = false)")
        found = scan(ap.RESET_BAUD)
        if found is not None:
            raise Finding(f"the Aurora answers at {found[0]} baud, not at 9600 where a session starts",
                          "power-cycle it, or set reset_on_open = true so a break resets it",
                          {"answers_at_baud": found[0]})
        raise Finding("no reply to VER at any standard rate", "check power and cable")

    return step


def _baud_rate(baud: int, ser: serial.Serial, reply_s: float, scan: Scan) -> Callable[[], Outcome]:
    def step() -> Outcome:
        if baud == ap.RESET_BAUD:
            return Outcome("works at 9600 baud (configured; no COMM switch)", data={"baud_rate": baud})
        reply = command(ser, ap.comm_command(baud), reply_s)
        if reply != ap.OKAY:
            raise Finding(f"COMM to {baud} baud answered {reply!r}", "the firmware may not support this rate")
        time.sleep(COMM_SETTLE_S)
        if answers(ser, baud, reply_s) is not None:
            return Outcome(f"switches to the configured {baud} baud (COMM) and answers there",
                           data={"baud_rate": baud})
        found = scan(baud)
        if found is not None:
            raise Finding(f"after COMM to {baud} baud the Aurora answers at {found[0]} baud, not {baud}",
                          f"the adapter or the firmware does not do {baud}: set baud_rate = {found[0]}",
                          {"configured_baud": baud, "answers_at_baud": found[0]})
        raise Finding(f"no answer at {baud} baud after COMM (nor at any other rate)",
                      f"the USB-serial adapter may not support {baud} baud: try baud_rate = 115200 or 57600",
                      {"configured_baud": baud})

    return step


def _tools(cfg: AuroraConfig, ser: serial.Serial, reply_s: float) -> Callable[[], Outcome]:
    def step() -> Outcome:
        try:
            handles = dict(ap.parse_phsr(command(ser, "PHSR:00", reply_s)))
        except ap.NdiDecodeError as exc:
            raise NdiError(str(exc)) from None
        sensors: dict[str, str] = dict(cfg.sensors)
        missing = [f"{name!r} (port handle {h})" for name, h in sensors.items() if int(h, 16) not in handles]
        data = {"handles": sorted(f"{h:02X}" for h in handles)}
        if missing:
            raise Finding(f"no tool on {', '.join(missing)}; the Aurora has handles "
                          f"{', '.join(data['handles']) or 'none'}",
                          "plug the sensor's tool connector into the system control unit; check "
                          "[tracker] sensors (name -> port handle, as PHSR lists them)", data)
        return Outcome(f"every configured sensor has a tool on its port handle "
                       f"({', '.join(f'{n} {h}' for n, h in sensors.items())})", data=data)

    return step
