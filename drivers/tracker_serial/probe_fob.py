"""``hil probe`` for a Flock of Birds (``driver = "fob"``): the serial port, the baud rate the Bird
answers at, its identity and error register, and the configured birds on the bus.

Registered through ``hil_register_probes`` (:mod:`drivers.tracker_serial.plugin`); every byte it
sends or expects comes from :mod:`drivers.tracker_serial.fob_protocol` (FOB-MAN): STREAM STOP,
EXAMINE VALUE 15 (model id), 1 (software revision), 10 (error code), 36 (flock status: one byte per
FBB address), through RS232 TO FBB for another bird. The baud rate is set by dip switches: a host
at another rate reads noise, so a silent Bird is asked again at every rate the switches can select.
The driver-level checks (open, stream) follow.
"""

from __future__ import annotations

import serial

from drivers.tracker_serial import fob_protocol as fp
from drivers.tracker_serial.config import FlockOfBirdsConfig
from hil.probe.context import ProbeContext, field_s
from hil.probe.report import Status
from hil.probe.runner import Checklist, Finding, Outcome
from hil.probe.serial_port import WireTimeoutError, close_port, flush, open_port_steps, read_exact

#: The rates a silent Bird is asked at, fastest first.
SCAN_BAUD_RATES: tuple[int, ...] = tuple(sorted(fp.BAUD_RATES, reverse=True))
#: A bird is on the bus when its flock status byte says accessible, with a sensor.
_ON_BUS = fp.FLOCK_ACCESSIBLE | fp.FLOCK_HAS_SENSOR


def examine(ser: serial.Serial, param: int, n_bytes: int, timeout_s: float,
            address: int | None = None) -> bytes:
    """EXAMINE VALUE ``param`` (through RS232 TO FBB for ``address`` 1..14); its ``n_bytes`` reply.

    Raises:
        WireTimeoutError: fewer bytes within ``timeout_s``.
    """
    flush(ser)
    ser.write(fp.examine(param, address=address))
    return read_exact(ser, n_bytes, timeout_s)


def model_id(ser: serial.Serial, timeout_s: float) -> str | None:
    """Stop any stream, ask the model id; the id when it is a Bird's, None for silence or noise."""
    ser.write(bytes([fp.CMD_STREAM_STOP]))
    flush(ser, quiet_s=0.02)  # FOB-MAN p.100: discard input >= 10 ms after stopping
    try:
        raw = examine(ser, fp.PARAM_MODEL_ID, fp.EXAMINE_REPLY_BYTES[fp.PARAM_MODEL_ID], timeout_s)
    except WireTimeoutError:
        return None
    text = raw.decode("ascii", errors="replace").strip().strip("\x00")
    return text if text.startswith(fp.MODEL_IDS) else None


def probe_fob(cl: Checklist, cfg: FlockOfBirdsConfig, ctx: ProbeContext) -> None:
    """Steps ``port_exists``, ``port_permissions``, ``port_opens``, ``baud_rate``, ``identity`` and
    (a flock) ``flock_status``; the port is closed on return."""
    ser = open_port_steps(cl, cfg.port, cfg.baud_rate)
    if ser is None:
        return
    try:
        model = _baud_rate_step(cl, cfg, ser)
        if model is not None and _identity_step(cl, cfg, ser, model) and not cfg.standalone:
            _flock_step(cl, cfg, ser)
    finally:
        close_port(ser)


def _reply_s(cl: Checklist, cfg: FlockOfBirdsConfig, rate: int) -> float:
    """Wait for one reply at ``rate``: 10 reply bytes + 2 command bytes at 10 bits each."""
    return min(field_s(cfg, "response_timeout_s", 1.0), max(0.2, cl.timeout_s / 4)) + 120.0 / rate


def _baud_rate_step(cl: Checklist, cfg: FlockOfBirdsConfig, ser: serial.Serial) -> str | None:
    baud = cfg.baud_rate

    def baud_rate() -> Outcome:
        model = model_id(ser, _reply_s(cl, cfg, baud))
        if model is not None:
            return Outcome(f"the Bird answers at the configured {baud} baud", value=model,
                           data={"baud_rate": baud})
        for rate in SCAN_BAUD_RATES:
            if rate == baud:
                continue
            ser.baudrate = rate
            found = model_id(ser, _reply_s(cl, cfg, rate))
            if found is not None:
                raise Finding(f"no valid answer at the configured {baud} baud; the Bird ({found}) answers "
                              f"at {rate} baud",
                              f"set baud_rate = {rate} in [tracker], or set the Bird's baud dip switches "
                              f"to {baud} (then power-cycle it)",
                              {"configured_baud": baud, "answers_at_baud": rate, "model": found})
        raise Finding(f"no answer to EXAMINE VALUE (model id) at {baud} baud nor at any other standard "
                      f"rate ({', '.join(map(str, SCAN_BAUD_RATES))})",
                      "is the Bird powered and switched to FLY? is the RS-232 cable on the master bird "
                      "(the one at the lowest address) and of the right kind (straight vs null-modem)? "
                      "is this the right port?",
                      {"configured_baud": baud})

    scan_s = sum(_reply_s(cl, cfg, r) + 0.1 for r in SCAN_BAUD_RATES) + cl.timeout_s
    out = cl.step("baud_rate", baud_rate, timeout_s=scan_s, what=f"asking the Bird's model id at {baud} baud")
    return None if out is None else str(out.value)


def _identity_step(cl: Checklist, cfg: FlockOfBirdsConfig, ser: serial.Serial, model: str) -> bool:
    reply_s = _reply_s(cl, cfg, cfg.baud_rate)

    def identity() -> Outcome:
        rev = examine(ser, fp.PARAM_SOFTWARE_REVISION, fp.EXAMINE_REPLY_BYTES[fp.PARAM_SOFTWARE_REVISION],
                      reply_s)
        code = examine(ser, fp.PARAM_ERROR_CODE, fp.EXAMINE_REPLY_BYTES[fp.PARAM_ERROR_CODE], reply_s)[0]
        data = {"model": model, "software_revision": f"{rev[0]}.{rev[1]}", "error_code": code}
        text = f"identity: model {model}, software revision {rev[0]}.{rev[1]}"
        if code:
            return Outcome(f"{text}; error register holds {code} ({fp.error_text(code)})", Status.WARN,
                           "reading the register cleared it; if it comes back, see the FOB manual's "
                           "error table (a framing error means a host once talked at another baud rate)",
                           data)
        return Outcome(f"{text}, no error", data=data)

    return cl.step("identity", identity, what="reading the Bird's revision and error register") is not None


def _flock_step(cl: Checklist, cfg: FlockOfBirdsConfig, ser: serial.Serial) -> None:
    sensors: dict[str, int] = dict(cfg.sensors)
    reply_s = _reply_s(cl, cfg, cfg.baud_rate) + 0.1

    def flock() -> Outcome:
        status = examine(ser, fp.PARAM_FLOCK_STATUS, fp.EXAMINE_REPLY_BYTES[fp.PARAM_FLOCK_STATUS], reply_s)
        missing = []
        per: dict[str, str] = {}
        for name, addr in sensors.items():
            ok = status[addr - 1] & _ON_BUS == _ON_BUS
            per[name] = f"address {addr}: " + ("present" if ok else "absent")
            if not ok:
                missing.append(f"{name!r} (FBB address {addr})")
                continue
            raw = examine(ser, fp.PARAM_MODEL_ID, fp.EXAMINE_REPLY_BYTES[fp.PARAM_MODEL_ID], reply_s,
                          address=addr)
            per[name] += f" ({raw.decode('ascii', errors='replace').strip()})"
        if missing:
            raise Finding(f"flock status: {', '.join(missing)} not on the bus",
                          "power the bird(s), check the FBB cables and each bird's address dip switches",
                          {"sensors": per})
        return Outcome(f"flock status: every configured bird is on the bus ({', '.join(per.values())})",
                       data={"sensors": per})

    cl.step("flock_status", flock, what="reading the flock status (EXAMINE VALUE 36)")
