"""Probe a magnetic tracker: the serial port, the baud rate it answers at, its identity, the
configured sensors on the bus, then the driver streaming and each sensor's status.

Flock of Birds (``driver = "fob"``) and NDI Aurora (``driver = "aurora"``) get the wire-level
checks of :mod:`hil.probe.serial_wire`; any other tracker (simulated, plugin) gets the
driver-level checks only.
"""

from __future__ import annotations

import contextlib
import errno
import os
import time
from typing import Any

import numpy as np
import serial
from pydantic import BaseModel

from drivers.interfaces.tracker import PoseTracker, TrackerSample
from hil.probe import serial_wire as sw
from hil.probe.context import ProbeContext, build_step, close_quietly, field_s, open_step
from hil.probe.report import Check, DeviceReport, Status
from hil.probe.runner import Checklist, Finding, Outcome
from plugins.registry import DriverInfo

_DIALOUT_HINT = ("add your user to the group owning the port (usually dialout): "
                 "sudo usermod -aG dialout $USER, then log out and in")


def probe_tracker(ctx: ProbeContext, cfg: BaseModel, info: DriverInfo, role: str = "tracker") -> DeviceReport:
    report = DeviceReport(role, info.name, info.simulated)
    cl = Checklist(report, ctx.timeout_s)
    if info.simulated:
        cl.step("simulated", lambda: Outcome("simulated tracker: no hardware, checking that it starts"))
    elif info.name in ("fob", "aurora") and isinstance(getattr(cfg, "port", None), str):
        ser = _port_checks(cl, cfg, info.name)
        if ser is not None:
            try:
                if info.name == "fob":
                    _fob_checks(cl, cfg, ser)
                else:
                    _aurora_checks(cl, cfg, ser)
            finally:
                _close_port(ser)
    if not cl.failed:
        _driver_checks(cl, ctx, cfg, info, role)
    return report


# ------------------------------------------------------------------------------------------ port
def _port_checks(cl: Checklist, cfg: Any, driver: str) -> serial.Serial | None:
    port: str = cfg.port
    open_baud = cfg.baud_rate if driver == "fob" else 9600
    if not sw.is_url(port):
        def exists() -> Outcome:
            if not os.path.lexists(port):
                found = sw.candidate_ports()
                raise Finding(f"serial port {port} does not exist",
                              "is the adapter plugged in and powered? serial ports here: "
                              + (", ".join(found) if found else "none found (ls /dev/ttyUSB* /dev/ttyACM*)")
                              + "\nprefer a stable /dev/serial/by-id/... path in [tracker] port",
                              {"port": port, "candidates": found})
            if not os.path.exists(port):
                raise Finding(f"serial port {port} is a dangling link (to {os.readlink(port)})",
                              "the adapter was unplugged or renumbered; plug it in again")
            kind = sw.node_kind(port)
            if kind != "char":
                raise Finding(f"{port} exists but is a {kind}, not a serial device",
                              "point [tracker] port at the tty device (/dev/ttyUSB0, /dev/serial/by-id/...)")
            target = sw.resolved(port)
            via = f" (-> {target})" if target != port else ""
            return Outcome(f"serial port {port}{via} exists ({sw.describe_node(port)})",
                           data={"port": port, "device": target})

        if cl.step("port_exists", exists, what=f"looking for {port}") is None:
            return None

        def permissions() -> Outcome:
            if not os.access(port, os.R_OK | os.W_OK):
                raise Finding(f"no read/write permission on {port} ({sw.describe_node(port)})", _DIALOUT_HINT)
            return Outcome(f"read/write permission on {port}")

        if cl.step("port_permissions", permissions) is None:
            return None

    def opens() -> Outcome:
        try:
            ser = sw.open_port(port, open_baud)
        except (serial.SerialException, OSError, ValueError) as exc:
            err = getattr(exc, "errno", None)
            text = str(exc)
            if err == errno.EBUSY or "busy" in text.lower() or "lock" in text.lower():
                raise Finding(f"{port} is in use by another program ({text})",
                              "close the other program (another hil, a serial terminal, ModemManager: "
                              "sudo systemctl stop ModemManager); fuser -v " + port) from None
            if err in (errno.EACCES, errno.EPERM):
                raise Finding(f"permission denied opening {port}", _DIALOUT_HINT) from None
            raise Finding(f"{port} does not open: {text}",
                          "unplug and replug the adapter; check dmesg for USB-serial errors") from None
        return Outcome(f"{port} opens at {open_baud} baud, 8N1", value=ser)

    out = cl.step("port_opens", opens, what=f"opening {port}")
    return None if out is None else out.value


def _close_port(ser: serial.Serial) -> None:
    with contextlib.suppress(serial.SerialException, OSError):
        ser.close()


# --------------------------------------------------------------------------------- Flock of Birds
def _fob_checks(cl: Checklist, cfg: Any, ser: serial.Serial) -> None:
    baud: int = cfg.baud_rate
    reply_s = min(field_s(cfg, "response_timeout_s", 1.0), max(0.2, cl.timeout_s / 4))

    def per_rate_s(rate: int) -> float:
        return reply_s + 120.0 / rate  # 10 reply bytes + 2 command bytes at 10 bits each

    def baud_rate() -> Outcome:
        model = sw.fob_model_id(ser, per_rate_s(baud))
        if model is not None:
            return Outcome(f"the Bird answers at the configured {baud} baud", value=model,
                           data={"baud_rate": baud})
        for rate in sw.FOB_BAUD_RATES:
            if rate == baud:
                continue
            ser.baudrate = rate
            found = sw.fob_model_id(ser, per_rate_s(rate))
            if found is not None:
                raise Finding(f"no valid answer at the configured {baud} baud; the Bird ({found}) answers "
                              f"at {rate} baud",
                              f"set baud_rate = {rate} in [tracker], or set the Bird's baud dip switches "
                              f"to {baud} (then power-cycle it)",
                              {"configured_baud": baud, "answers_at_baud": rate, "model": found})
        raise Finding(f"no answer to EXAMINE VALUE (model id) at {baud} baud nor at any other standard "
                      f"rate ({', '.join(map(str, sw.FOB_BAUD_RATES))})",
                      "is the Bird powered and switched to FLY? is the RS-232 cable on the master bird "
                      "(the one at the lowest address) and of the right kind (straight vs null-modem)? "
                      "is this the right port?",
                      {"configured_baud": baud})

    scan_s = sum(per_rate_s(r) + 0.1 for r in sw.FOB_BAUD_RATES) + cl.timeout_s
    out = cl.step("baud_rate", baud_rate, timeout_s=scan_s, what=f"asking the Bird's model id at {baud} baud")
    if out is None:
        return
    model: str = out.value

    def identity() -> Outcome:
        rev = sw.fob_examine(ser, sw.FOB_PARAM_REVISION, 2, per_rate_s(baud))
        code = sw.fob_examine(ser, sw.FOB_PARAM_ERROR, 1, per_rate_s(baud))[0]
        data = {"model": model, "software_revision": f"{rev[0]}.{rev[1]}", "error_code": code}
        text = f"identity: model {model}, software revision {rev[0]}.{rev[1]}"
        if code:
            return Outcome(f"{text}; error register holds {code} ({sw.fob_error_text(code)})", Status.WARN,
                           "reading the register cleared it; if it comes back, see the FOB manual's "
                           "error table (a framing error means a host once talked at another baud rate)",
                           data)
        return Outcome(f"{text}, no error", data=data)

    if cl.step("identity", identity, what="reading the Bird's revision and error register") is None:
        return
    sensors: dict[str, int] = dict(cfg.sensors)
    if list(sensors.values()) == [0]:
        return

    def flock() -> Outcome:
        status = sw.fob_examine(ser, sw.FOB_PARAM_FLOCK_STATUS, 14, per_rate_s(baud) + 0.1)
        missing = []
        per: dict[str, str] = {}
        for name, addr in sensors.items():
            bits = status[addr - 1]
            ok = bool(bits & 0x80) and bool(bits & 0x20)
            per[name] = f"address {addr}: " + ("present" if ok else "absent")
            if not ok:
                missing.append(f"{name!r} (FBB address {addr})")
                continue
            raw = sw.fob_examine(ser, sw.FOB_PARAM_MODEL, 10, per_rate_s(baud) + 0.1, address=addr)
            per[name] += f" ({raw.decode('ascii', errors='replace').strip()})"
        if missing:
            raise Finding(f"flock status: {', '.join(missing)} not on the bus",
                          "power the bird(s), check the FBB cables and each bird's address dip switches",
                          {"sensors": per})
        return Outcome(f"flock status: every configured bird is on the bus ({', '.join(per.values())})",
                       data={"sensors": per})

    cl.step("flock_status", flock, what="reading the flock status (EXAMINE VALUE 36)")


# ----------------------------------------------------------------------------------------- Aurora
def _aurora_checks(cl: Checklist, cfg: Any, ser: serial.Serial) -> None:
    baud: int = cfg.baud_rate
    reply_s = min(field_s(cfg, "response_timeout_s", 1.0), max(0.3, cl.timeout_s / 4))
    scan_s = len(sw.AURORA_BAUD_RATES) * (reply_s + 0.05) + cl.timeout_s

    def scan(skip: int | None) -> tuple[int, str] | None:
        for rate in sw.AURORA_BAUD_RATES:
            if rate == skip:
                continue
            found = sw.ndi_answers(ser, rate, reply_s)
            if found is not None:
                return rate, found
        return None

    if getattr(cfg, "reset_on_open", True):
        reset_s = field_s(cfg, "reset_timeout_s", 7.0)

        def reset() -> Outcome:
            if sw.ndi_reset(ser, break_s=field_s(cfg, "break_duration_s", 0.25),
                            break_as_nul=bool(getattr(cfg, "break_as_nul", False)), timeout_s=reset_s):
                sw.ndi_command(ser, "INIT:", reply_s)
                return Outcome("the Aurora resets on a serial break (RESET at 9600 baud) and initialises")
            found = scan(None)
            if found is not None:
                rate, version = found
                raise Finding(f"no RESET after a serial break, but the Aurora answers at {rate} baud "
                              f"({version})",
                              "the serial adapter may not send breaks, or the device is stuck at another "
                              "rate: "
                              "power-cycle the Aurora (it starts at 9600); a pseudo-terminal needs "
                              "break_as_nul = true",
                              {"answers_at_baud": rate})
            raise Finding(f"no RESET within {reset_s:g} s after a serial break, and no reply to VER at any "
                          "standard rate",
                          "is the Aurora (system control unit) powered and its serial cable on this port? "
                          "a pseudo-terminal (emulator) needs break_as_nul = true")

        if cl.step("reset", reset, timeout_s=reset_s + scan_s + cl.timeout_s,
                   what="resetting the Aurora with a serial break") is None:
            return
    else:
        def answers() -> Outcome:
            if sw.ndi_answers(ser, 9600, reply_s) is not None:
                sw.ndi_command(ser, "INIT:", reply_s)
                return Outcome("the Aurora answers at 9600 baud (no reset: reset_on_open = false)")
            found = scan(9600)
            if found is not None:
                raise Finding(f"the Aurora answers at {found[0]} baud, not at 9600 where a session starts",
                              "power-cycle it, or set reset_on_open = true so a break resets it",
                              {"answers_at_baud": found[0]})
            raise Finding("no reply to VER at any standard rate", "check power and cable")

        if cl.step("answers", answers, timeout_s=scan_s + cl.timeout_s) is None:
            return

    def identity() -> Outcome:
        version = sw.ndi_command(ser, "VER:4", reply_s)
        lines = [ln.strip() for ln in version.strip().splitlines() if ln.strip()]
        shown = lines[:2] + [ln for ln in lines[2:] if "serial" in ln.lower()]
        return Outcome(f"identity: {' / '.join(shown) or '?'}", data={"firmware": lines})

    if cl.step("identity", identity, what="asking the firmware version (VER:4)") is None:
        return

    def baud_rate() -> Outcome:
        if baud == 9600:
            return Outcome("works at 9600 baud (configured; no COMM switch)", data={"baud_rate": baud})
        reply = sw.ndi_command(ser, f"COMM:{sw.AURORA_COMM_CODES[baud]}0000", reply_s)
        if reply != "OKAY":
            raise Finding(f"COMM to {baud} baud answered {reply!r}", "the firmware may not support this rate")
        time.sleep(0.1)
        if sw.ndi_answers(ser, baud, reply_s) is not None:
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

    if cl.step("baud_rate", baud_rate, timeout_s=scan_s + cl.timeout_s,
               what=f"switching to {baud} baud") is None:
        return

    def tools() -> Outcome:
        handles = dict(sw.parse_phsr(sw.ndi_command(ser, "PHSR:00", reply_s)))
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

    cl.step("tools", tools, what="listing port handles (PHSR:00)")
    if baud != 9600:  # leave it where a new session starts
        try:
            sw.ndi_command(ser, "COMM:00000", reply_s)
            time.sleep(0.1)
        except (sw.NdiError, sw.WireTimeoutError, serial.SerialException, OSError):
            pass


# ---------------------------------------------------------------------------------------- driver
def _driver_checks(cl: Checklist, ctx: ProbeContext, cfg: BaseModel, info: DriverInfo, role: str) -> None:
    device = build_step(cl, ctx, role, cfg, info)
    if device is None:
        return
    if not isinstance(device, PoseTracker):
        cl.report.add(Check("driver_builds", Status.FAIL, f"driver {info.name} did not build a tracker"))
        return
    try:
        if not open_step(cl, device, cfg, f"{info.name} driver"):
            return
        window_s = max(ctx.window_s, 3.0 / max(field_s(cfg, "update_rate_hz", 40.0), 1.0))

        def stream() -> Outcome:
            seen: dict[str, set[int]] = {s: set() for s in device.sensors}
            last: dict[str, TrackerSample] = {}
            clock = ctx.clock  # a ManualClock (all-simulated setup) advances in sleep()
            t_end_ns = clock.now_ns() + round(window_s * 1e9)
            while clock.now_ns() < t_end_ns:
                for name, sample in device.latest().items():
                    if name in seen:
                        seen[name].add(sample.seq)
                        last[name] = sample
                clock.sleep(0.01)
            return Outcome(f"the driver streams ({sum(len(v) for v in seen.values())} records in "
                           f"{window_s:g} s)", value=(seen, last))

        out = cl.step("streams", stream, timeout_s=window_s + cl.timeout_s, what="reading records")
        if out is None:
            return
        seen, last = out.value
        for name in device.sensors:
            cl.report.add(_sensor_check(name, last.get(name), len(seen[name]), window_s))
    finally:
        close_quietly(device, cl.timeout_s)


def _sensor_check(name: str, sample: TrackerSample | None, n_records: int, window_s: float) -> Check:
    check = f"sensor_{name}"
    if sample is None:
        return Check(check, Status.FAIL, f"sensor {name!r}: no record in {window_s:g} s",
                     "is the sensor plugged in and configured with the right address / port handle?")
    rate = n_records / window_s
    data: dict[str, Any] = {"records": n_records, "rate_hz": round(rate, 1), "flags": list(sample.flags)}
    if sample.missing or sample.T_tracker_from_sensor is None:
        where = "out of the field volume" if "out_of_volume" in sample.flags else "missing"
        return Check(check, Status.WARN, f"sensor {name!r}: {where} "
                                         f"({', '.join(sample.flags) or 'no pose'})",
                     "move the sensor into the field generator's measurement volume; check its cable",
                     data)
    p = np.round(sample.T_tracker_from_sensor.t, 1).tolist()
    data["position_mm"] = p
    if sample.quality is not None:
        data["quality"] = round(float(sample.quality), 3)
    extra = f", quality {sample.quality:.2f}" if sample.quality is not None else ""
    flags = f", flags {', '.join(sample.flags)}" if sample.flags else ""
    status = Status.WARN if "partially_out" in sample.flags else Status.OK
    return Check(check, status, f"sensor {name!r}: pose at {p} mm{extra}{flags}, ~{rate:.0f} records/s",
                 "near the edge of the volume: move it towards the field generator's centre"
                 if status is Status.WARN else "", data)
