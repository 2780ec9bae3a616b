"""The Aurora emulator's tool and device faults, byte-exact (raw pyserial, no driver).

The expected replies are built here from the manual's layout (reference A2.2, A2.5, A2.6: TX text
fields, BX body, port status bits 0x01 tool in port, 0x10 initialised, 0x20 enabled, 0x40 out of
volume; ``RESETBE6F`` after a reset) with the frame number read back from the reply itself.
"""

from __future__ import annotations

import struct

import pytest
import serial
from emulators.trackersim.__main__ import control_command
from emulators.trackersim.faults import Faults, parse_fault
from emulators.trackersim.poses import StaticPoses

from drivers.tracker_serial import aurora_protocol as ap
from hil.geometry.transform import RigidTransform

from .conftest import AuroraFactory, wait_until

#: 0A and 0B, identity rotation, inside the emulator's default volume and away from its faces.
POSES = StaticPoses({"0A": RigidTransform.from_translation([0.0, 0.0, -250.0]),
                     "0B": RigidTransform.from_translation([40.0, 0.0, -250.0])})
IN_USE = 0x31  # tool in port | initialised | enabled
OUT_OF_VOLUME = 0x40


def _cmd(text: str) -> bytes:
    return f"{text}{ap.crc16(text):04X}\r".encode()


def _ask(ser: serial.Serial, text: str) -> bytes:
    ser.reset_input_buffer()
    ser.write(_cmd(text))
    return bytes(ser.read_until(b"\r"))


def _tracking(ser: serial.Serial) -> None:
    """Break, INIT, PINIT and PENA of 0A and 0B, TSTART, all at 9600 baud."""
    ser.write(b"\x00")
    assert ser.read_until(b"\r") == b"RESETBE6F\r"
    for text in ("INIT:", "PINIT:0A", "PINIT:0B", "PENA:0AD", "PENA:0BD", "TSTART:"):
        assert _ask(ser, text) == b"OKAYA896\r", text


def _bx(ser: serial.Serial, mode: str = "0801") -> bytes:
    ser.reset_input_buffer()
    ser.write(_cmd(f"BX:{mode}"))
    head = bytes(ser.read(6))
    (length,) = struct.unpack("<H", head[2:4])
    return head + bytes(ser.read(length + 2))


def _bx_expected(entries: list[bytes]) -> bytes:
    body = bytes([len(entries)]) + b"".join(entries) + struct.pack("<H", 0)
    head = b"\xc4\xa5" + struct.pack("<H", len(body))
    return head + struct.pack("<H", ap.crc16(head)) + body + struct.pack("<H", ap.crc16(body))


def _bx_valid(handle: int, x_mm: float, status: int, frame: int) -> bytes:
    return bytes([handle, 0x01]) + struct.pack("<8f", 1.0, 0.0, 0.0, 0.0, x_mm, 0.0, -250.0, 0.05) + \
        struct.pack("<II", status, frame)


def _bx_missing(handle: int, status: int, frame: int) -> bytes:
    return bytes([handle, 0x02]) + struct.pack("<II", status, frame)


def _bx_frame(reply: bytes) -> int:
    """The frame number of the last handle entry (the 4 bytes before the system status and CRC)."""
    (frame,) = struct.unpack("<I", reply[-8:-4])
    return int(frame)


def _tx_valid(handle: str, x: str, status: int, frame: int) -> str:
    return f"{handle}+10000+00000+00000+00000{x}+000000-025000+00500{status:08X}{frame:08X}\n"


def test_tool_missing_in_bx_and_tx(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator(poses=POSES)
    with serial.Serial(dev.link.path, 9600, timeout=1.0) as ser:
        _tracking(ser)
        dev.faults.inject("tool_missing,handles=0A", dev.now_s())
        reply = _bx(ser)
        f = _bx_frame(reply)
        assert reply == _bx_expected([_bx_missing(0x0A, IN_USE, f), _bx_valid(0x0B, 40.0, IN_USE, f)])
        reply = _ask(ser, "TX:0801")
        f = int(reply[-18:-10], 16)  # frame, LF, system status, CRC, CR
        text = f"020AMISSING{IN_USE:08X}{f:08X}\n" + _tx_valid("0B", "+004000", IN_USE, f) + "0000"
        assert reply == ap.frame_reply(text)
        dev.faults.clear("tool_missing")
        reply = _bx(ser)
        f = _bx_frame(reply)
        assert reply == _bx_expected([_bx_valid(0x0A, 0.0, IN_USE, f), _bx_valid(0x0B, 40.0, IN_USE, f)])


def test_every_tool_missing_without_handles(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator(poses=POSES)
    with serial.Serial(dev.link.path, 9600, timeout=1.0) as ser:
        _tracking(ser)
        dev.faults.inject("tool_missing", dev.now_s())
        reply = _bx(ser)
        f = _bx_frame(reply)
        assert reply == _bx_expected([_bx_missing(0x0A, IN_USE, f), _bx_missing(0x0B, IN_USE, f)])


def test_out_of_volume_with_and_without_option_0800(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator(poses=POSES)
    with serial.Serial(dev.link.path, 9600, timeout=1.0) as ser:
        _tracking(ser)
        dev.faults.inject("out_of_volume,handles=0B", dev.now_s())
        # 0x0800 asks for the transforms not normally reported: sent, with bit 0x40
        reply = _bx(ser, "0801")
        f = _bx_frame(reply)
        assert reply == _bx_expected([_bx_valid(0x0A, 0.0, IN_USE, f),
                                      _bx_valid(0x0B, 40.0, IN_USE | OUT_OF_VOLUME, f)])
        # without it the out-of-volume tool is reported MISSING, still with bit 0x40
        reply = _ask(ser, "TX:0001")
        f = int(reply[-18:-10], 16)  # frame, LF, system status, CRC, CR
        missing = f"0BMISSING{IN_USE | OUT_OF_VOLUME:08X}{f:08X}\n"
        text = "02" + _tx_valid("0A", "+000000", IN_USE, f) + missing + "0000"
        assert reply == ap.frame_reply(text)


def test_reset_fault_sends_reset_and_stops_tracking(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator(poses=POSES)
    with serial.Serial(dev.link.path, 9600, timeout=1.0) as ser:
        _tracking(ser)
        assert dev.tracking
        ser.reset_input_buffer()
        dev.faults.inject("reset", dev.now_s())
        assert ser.read_until(b"\r") == b"RESETBE6F\r"
        assert (dev.baud, dev.initialized, dev.tracking) == (9600, False, False)
        assert _ask(ser, "BX:0801") == ap.frame_reply("ERROR0C")  # not tracking: an ASCII error
        assert _ask(ser, "PENA:0AD") == ap.frame_reply("ERROR0E")  # handles forgot their PINIT
        assert dev.faults.fired["reset"] == 1


def test_reset_fault_at_the_comm_rate_arrives_as_noise(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator(poses=POSES)
    with serial.Serial(dev.link.path, 9600, timeout=0.3) as ser:
        _tracking(ser)
        assert _ask(ser, "COMM:50000") == b"OKAYA896\r"
        wait_until(lambda: dev.baud == 115200, what="the emulator at 115200 baud")
        ser.baudrate = 115200
        assert _ask(ser, "BEEP:1").startswith(b"1")
        dev.faults.inject("reset", dev.now_s())
        wait_until(lambda: dev.faults.fired["reset"] == 1, what="the reset")
        wait_until(lambda: dev.baud == 9600, what="the device back at 9600 baud")
        # its RESET follows the fault's firing (at 9600: noise to us); drain until the line is
        # quiet for the read timeout, so the next read holds only what our command causes
        while ser.read(64):
            pass
        ser.write(_cmd("BX:0801"))
        assert ser.read(64) == b""  # the device at 9600 reads our bytes as framing errors


def test_comm_baud_answers_okay_then_runs_at_the_wrong_rate(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator(poses=POSES)
    with serial.Serial(dev.link.path, 9600, timeout=0.3) as ser:
        _tracking(ser)
        # both in one control line: armed together, under the device lock
        assert control_command(dev, "fault comm_baud,baud=57600; fault wrong_baud,baud=9600") == "ok"
        assert control_command(dev, "clear wrong_baud; fault nonsense; fault silence").startswith("error: ")
        assert dev.faults.wrong_baud is None  # the first command of the line ran, the third did not
        assert dev.faults.fire("silence", dev.now_s()) is None
        assert _ask(ser, "COMM:50000") == b"OKAYA896\r"  # the OKAY at the old rate, as always
        wait_until(lambda: dev.baud != 9600, what="the switch")
        assert dev.baud == 57600  # not the 115200 asked
        ser.baudrate = 115200
        ser.reset_input_buffer()
        ser.write(_cmd("BEEP:1"))
        assert ser.read(16) == b""  # our bytes are framing errors to it
        ser.baudrate = 57600
        assert _ask(ser, "BEEP:1") == ap.frame_reply("1")
        assert dev.faults.fired["comm_baud"] == 1
        assert _ask(ser, "COMM:50000") == b"OKAYA896\r"  # count=1: the next COMM is honoured
        wait_until(lambda: dev.baud == 115200, what="115200")


def test_window_faults_end_by_themselves() -> None:
    faults = Faults(seed=1)
    faults.inject("tool_missing,seconds=0.5,after=1.0,handles=0A+0C", now_s=10.0)
    assert faults.fire("tool_missing", 10.9) is None  # not yet
    spec = faults.fire("tool_missing", 11.2)
    assert spec is not None
    assert spec.handles == (0x0A, 0x0C)
    assert (spec.hits(0x0A), spec.hits(0x0B)) == (True, False)
    assert faults.fire("tool_missing", 11.4) is spec  # every reply in the window
    assert faults.fire("tool_missing", 11.5) is None  # over
    assert faults.fire("tool_missing", 11.2) is None  # and disarmed
    faults.inject("out_of_volume", now_s=0.0)  # no seconds: until cleared
    assert faults.fire("out_of_volume", 1e6) is not None
    faults.clear("out_of_volume")
    assert faults.fire("out_of_volume", 1e6) is None
    faults.inject("out_of_volume,count=2", now_s=0.0)  # a count: the next two replies
    assert [faults.fire("out_of_volume", 0.0) is not None for _ in range(3)] == [True, True, False]


@pytest.mark.parametrize(("spec", "message"), [
    ("tool_missing,handles=0G", "handles"),
    ("tool_missing,handles=", "handles"),
    ("out_of_volume,handles=100", "handles"),
    ("tool_missing,colour=red", "unknown key"),
    ("comm_baud", "needs baud=B"),
])
def test_bad_fault_specs_are_refused(spec: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_fault(spec)
