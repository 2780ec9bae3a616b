"""Both ends of each tracker protocol against the manuals' test vectors (reference/device-protocols.md).

The driver's codecs (``drivers.tracker_serial.*_protocol``) and the emulators' own encoders
(``emulators.trackersim.ndi_wire`` / ``fob_wire``) are separate code written from the same facts;
each is checked against the documented bytes here, so a framing bug on either side fails a test
instead of cancelling out.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable

import numpy as np
import pytest
from emulators.trackersim import fob_wire as fw
from emulators.trackersim import ndi_wire as nw

from drivers.tracker_serial import aurora_protocol as ap
from drivers.tracker_serial import fob_protocol as fp
from hil.geometry.transform import RigidTransform

# ---------------------------------------------------------------------- NDI (A2.2 test vectors)
CRC_VECTORS = [
    ("INIT:", 0xE3A5), ("TSTART:", 0x5423), ("TSTOP:", 0x2C14), ("BX:0801", 0x00EC), ("TX:0801", 0xC19B),
    ("PHSR:00", 0x20FF), ("PHSR:01", 0xE03E), ("PHSR:02", 0xE17E), ("PHSR:03", 0x21BF), ("PHSR:04", 0xE3FE),
    ("COMM:50000", 0x0048), ("COMM:00000", 0x0084), ("BEEP:1", 0x8404), ("VER:4", 0xA6EF),
    ("PINIT:0A", 0xD5EB), ("PENA:0AD", 0xAD1E), ("OKAY", 0xA896), ("RESET", 0xBE6F),
    ("ERROR01", 0x6BC2), ("ERROR04", 0x6802), ("123456789", 0xBB3D),
]
CRCS: dict[str, Callable[[bytes], int]] = {"driver": ap.crc16, "emulator": nw.crc16}


@pytest.mark.parametrize("end", sorted(CRCS))
@pytest.mark.parametrize(("text", "crc"), CRC_VECTORS)
def test_ndi_crc16_of_each_documented_string(end: str, text: str, crc: int) -> None:
    assert CRCS[end](text.encode("ascii")) == crc


def test_documented_replies_byte_exact_on_both_ends() -> None:
    # the emulator writes them ...
    assert nw.reply("OKAY") == b"OKAYA896\r"
    assert nw.reset_reply() == b"RESETBE6F\r" == ap.RESET_REPLY
    assert nw.reply("ERROR01") == b"ERROR016BC2\r"
    # ... the driver reads them
    assert ap.check_reply(b"OKAYA896") == "OKAY"
    with pytest.raises(ap.NdiReplyError) as err:
        ap.check_reply(b"ERROR016BC2")
    assert err.value.code == 0x01


@pytest.mark.parametrize(("text", "crc"), [v for v in CRC_VECTORS if ":" in v[0]])
def test_documented_commands_byte_exact_on_both_ends(text: str, crc: int) -> None:
    line = ap.frame_command(text)  # the driver writes ``INIT:E3A5\r`` ...
    assert line == f"{text}{crc:04X}\r".encode("ascii")
    cmd = nw.read_command(line[:-1])  # ... the emulator reads it
    assert cmd is not None
    assert (cmd.name, cmd.crc_ok) == (text.split(":")[0], True)
    assert nw.read_command(line[:-2] + (b"0" if line[-2:-1] != b"0" else b"1")) == nw.Command(
        cmd.name, cmd.params, False)  # a wrong CRC digit is seen


def test_documented_tx_transform_both_ways() -> None:
    # A2.5: "+10000+00000+00000+00000+012345-006789+045678+00123" = q (1,0,0,0),
    # t (123.45, -67.89, 456.78) mm, error 0.0123
    fields = "+10000+00000+00000+00000+012345-006789+045678+00123"
    tool = nw.ToolFrame(0x0A, (1.0, 0.0, 0.0, 0.0, 123.45, -67.89, 456.78, 0.0123), 0x31, 7)
    text = nw.tx_text([tool], 0)
    assert text == "01" + "0A" + fields + "00000031" + "00000007" + "\n" + "0000"
    rec = ap.parse_tx(text).handles[0]
    assert (rec.handle, rec.state, rec.port_status, rec.frame) == (0x0A, "valid", 0x31, 7)
    assert rec.q_wxyz == (1.0, 0.0, 0.0, 0.0)
    assert rec.t_mm == pytest.approx((123.45, -67.89, 456.78), abs=1e-9)
    assert rec.error_rms == pytest.approx(0.0123, abs=1e-9)
    missing = nw.tx_text([nw.ToolFrame(0x0B, None, 0x11, 8)], 0)
    assert missing == "010BMISSING0000001100000008\n0000"
    assert ap.parse_tx(missing).handles[0].state == "missing"


def test_bx_framing_both_ways() -> None:
    # A2.2: C4 A5, u16 LE body length, u16 LE CRC of those 4 bytes, body, u16 LE body CRC
    tool = nw.ToolFrame(0x0A, (1.0, 0.0, 0.0, 0.0, 1.5, -2.5, 300.0, 0.25), 0x31, 9)
    raw = nw.bx_reply([tool, nw.ToolFrame(0x0B, None, 0x11, 9)], 0)
    body_len = 1 + (2 + 32 + 8) + (2 + 8) + 2
    assert raw[:4] == bytes([0xC4, 0xA5]) + struct.pack("<H", body_len)
    assert struct.unpack("<H", raw[4:6])[0] == ap.crc16(raw[:4])
    assert len(raw) == body_len + 8
    # appending a CRC little-endian makes the running CRC zero (A2.2), on both ends
    assert nw.crc16(raw[6:]) == ap.crc16(raw[6:]) == 0
    assert ap.parse_bx_header(raw[:6]) == body_len
    reply = ap.parse_bx_body(raw[6:])
    assert [(h.handle, h.state, h.port_status, h.frame) for h in reply.handles] == [
        (0x0A, "valid", 0x31, 9), (0x0B, "missing", 0x11, 9)]
    assert reply.handles[0].t_mm == (1.5, -2.5, 300.0)


def test_phsr_both_ways() -> None:
    text = nw.phsr_text([(0x0A, 0x001), (0x0B, 0x031)])
    assert text == "020A0010B031"
    assert ap.parse_phsr(text) == [(0x0A, 0x001), (0x0B, 0x031)]


def test_comm_codes_agree() -> None:
    # A2.4: COMM:<b>0000 with b = 0 (9600) ... 7 (1228739), A (230400), on both ends
    assert {code: rate for rate, code in ap.COMM_BAUD_CODES.items()} == nw.COMM_BAUD
    assert ap.comm_command(115200) == "COMM:50000"


# ---------------------------------------------------------------------- Flock of Birds (A1.4)
def test_fob_manual_worked_example_both_ways() -> None:
    # FOB-MAN p.40: words 0x1122, 0x3344, 0x5566 are sent as C8 08 51 19 59 2A
    raw = fw.pack_words([0x1122, 0x3344, 0x5566])
    assert raw == bytes.fromhex("C8 08 51 19 59 2A")
    assert fp.decode_words(raw) == [0x1122 & ~3, 0x3344 & ~3, 0x5566 & ~3]  # 14 bits travel


def test_fob_documented_position_angles_record_both_ways() -> None:
    # A1.4 (the reference's packing check): POS/ANG, x 10", y -5", z 3" at 36" full scale,
    # azimuth 90 deg, elevation -45 deg, roll -180 deg -> these 12 bytes
    documented = bytes.fromhex("e3 11 0e 77 2a 05 00 20 00 70 00 40")
    T = RigidTransform.from_euler_zyx(math.radians(90), math.radians(-45), math.radians(-180))
    T = RigidTransform(T.R, np.array([10.0, -5.0, 3.0]) * 25.4)
    assert fw.record(T, fw.Format.POSITION_ANGLES, full_scale_in=36.0) == documented
    assert fp.decode_words(documented) == [9100, -4552, 2728, 16384, -8192, -32768]
    rec = fp.decode_record(documented, fp.RecordLayout(fp.FobFormat.POSITION_ANGLES), full_scale_mm=36 * 25.4)
    lsb_mm = 4 * 36 * 25.4 / 32768  # the two lost bits
    assert np.allclose(rec.T_tracker_from_sensor.t, [254.0, -127.0, 76.2], atol=lsb_mm)
    assert np.allclose(rec.T_tracker_from_sensor.R, T.R, atol=1e-3)


def test_fob_trailer_bytes_both_ways() -> None:
    # A1.4: after the words the BUTTON byte, then the GROUP MODE address byte
    T = RigidTransform.from_rotvec([0.0, 0.0, 0.3], [100.0, -50.0, 20.0])
    raw = fw.record(T, fw.Format.POSITION_QUATERNION, full_scale_in=36.0, button=0x10, address=3)
    layout = fp.RecordLayout(fp.FobFormat.POSITION_QUATERNION, button_mode=True, group_mode=True)
    assert len(raw) == layout.length == 14 + 2
    rec = fp.decode_record(raw, layout, full_scale_mm=36 * 25.4)
    assert (rec.button, rec.address) == (0x10, 3)
    assert np.allclose(rec.T_tracker_from_sensor.t, T.t, atol=0.12)
    assert np.allclose(rec.T_tracker_from_sensor.R, T.R, atol=1e-3)


@pytest.mark.parametrize("fmt", ["MATRIX", "POSITION_MATRIX", "QUATERNION", "ANGLES", "POSITION"])
def test_fob_every_format_the_emulator_sends_decodes_in_the_driver(fmt: str) -> None:
    T = RigidTransform.from_rotvec([0.2, -0.4, 1.1], [-300.0, 120.0, 45.0])
    raw = fw.record(T, fw.Format[fmt], full_scale_in=72.0)
    rec = fp.decode_record(raw, fp.RecordLayout(fp.FobFormat[fmt]), full_scale_mm=72 * 25.4)
    if "POSITION" in fmt:
        assert np.allclose(rec.T_tracker_from_sensor.t, T.t, atol=0.23)
    if fmt != "POSITION":
        assert np.allclose(rec.T_tracker_from_sensor.R, T.R, atol=1e-3)


def test_fob_bird_status_word_both_ways() -> None:
    # FOB-MAN p.111-112: bit 15 master, 14 initialised, 12 running, 4..1 format (4 = POS/ANG), 0 STREAM
    word = fw.BirdState(master=True, initialized=True, error=False, running=True, sleeping=False,
                        stream=True, fmt=fw.Format.POSITION_ANGLES).word()
    assert word == (0x8000 | 0x4000 | 0x1000 | 4 << 1 | 1).to_bytes(2, "little")
    status = fp.BirdStatus.from_bytes(word)
    assert (status.master, status.initialized, status.error, status.running, status.stream) == (
        True, True, False, True, True)
    assert status.fmt is fp.FobFormat.POSITION_ANGLES


def test_fob_format_table_agrees() -> None:
    assert {f.name: f.value for f in fw.Format} == {f.name: f.value for f in fp.FobFormat}
    assert fw.CHANGE_BYTES == fp.CHANGE_DATA_BYTES
    assert fw.EXAMINE_BYTES == fp.EXAMINE_REPLY_BYTES
