"""The emulators answer byte-exactly as the manuals say (raw pyserial, no driver)."""

from __future__ import annotations

import serial

from drivers.tracker_serial import aurora_protocol as ap
from drivers.tracker_serial import fob_protocol as fp

from .conftest import AuroraFactory, FobFactory, wait_until


def _exchange(ser: serial.Serial, data: bytes, n: int) -> bytes:
    ser.reset_input_buffer()
    ser.write(data)
    return bytes(ser.read(n))


def test_flock_examine_point_and_errors(fob_emulator: FobFactory) -> None:
    dev = fob_emulator()
    with serial.Serial(dev.link.path, 115200, timeout=1.0) as ser:
        assert _exchange(ser, b"O\x0f", 10) == b"6DFOB     "
        assert _exchange(ser, b"O\x01", 2) == b"\x03\x43"  # revision 3.67: INT, FRA
        assert _exchange(ser, b"O\x07", 2) == (100 * 256).to_bytes(2, "little")
        status = fp.BirdStatus.from_bytes(_exchange(ser, b"O\x00", 2))
        assert status.fmt is fp.FobFormat.POSITION_ANGLES  # the power-up format
        assert not status.stream
        rec = _exchange(ser, b"B", 12)  # POINT: one POSITION/ANGLES record
        assert len(rec) == 12
        assert rec[0] & 0x80
        assert not any(b & 0x80 for b in rec[1:])
        ser.write(b"\x99")  # not a command
        assert _exchange(ser, b"O\x0a", 1) == b"\x06"  # error 6: invalid RS232 command
        assert _exchange(ser, b"O\x0a", 1) == b"\x00"  # ... cleared by the read
        ser.write(b"M\x01")  # BUTTON MODE on: the record grows by the button byte
        assert len(_exchange(ser, b"B", 13)) == 13


def test_flock_needs_auto_config_before_points(fob_emulator: FobFactory) -> None:
    dev = fob_emulator(n_birds=2)
    with serial.Serial(dev.link.path, 115200, timeout=0.3) as ser:
        assert _exchange(ser, b"B", 12) == b""
        assert _exchange(ser, b"O\x0a", 1) == b"\x09"  # bird is not initialised
        ser.write(b"P\x32\x02P\x23\x01")  # AUTO-CONFIG 2 birds, GROUP MODE on
        reply = _exchange(ser, b"B", 26)  # two POS/ANG records, each + its address byte
        assert reply[12] == 1
        assert reply[25] == 2
        flock = _exchange(ser, b"O\x24", 14)
        assert flock[0] & 0xC0 == 0xC0  # address 1 accessible and running


def test_aurora_command_replies(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator()
    with serial.Serial(dev.link.path, 9600, timeout=1.0) as ser:
        ser.write(b"\x00")  # the break, as a UART receives it
        assert ser.read_until(b"\r") == b"RESETBE6F\r"
        assert _exchange(ser, b"INIT:E3A6\r", 12) == b"ERROR046802\r"  # bad command CRC
        assert _exchange(ser, b"INIT:E3A5\r", 9) == b"OKAYA896\r"
        assert _exchange(ser, b"TX:0801C19B\r", 12) == ap.frame_reply("ERROR0C")  # not tracking
        ser.write(b"PHSR:02E17E\r")
        assert ser.read_until(b"\r") == ap.frame_reply("020A0010B001")  # both handles need PINIT
        assert _exchange(ser, b"NOPE \r", 12) == ap.frame_reply("ERROR01")
        ser.reset_input_buffer()
        ser.write(b"COMM:500000048\r")
        assert ser.read_until(b"\r") == b"OKAYA896\r"  # still at 9600
        # the device switches after its reply has gone out (the driver waits 100 ms for it, as the
        # manual says); asserting at once raced the emulator's thread
        wait_until(lambda: dev.baud == 115200, timeout_s=5.0, what="the emulator at 115200 baud")
        ser.baudrate = 115200
        assert _exchange(ser, b"BEEP 1\r", 6) == ap.frame_reply("1")
