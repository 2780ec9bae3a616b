"""NDI serial API wire format: CRC-16 vectors, framing, replies, TX/BX parsing."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.tracker_serial import aurora_protocol as ap


def test_crc16_check_value() -> None:
    # CRC-16/ARC (NDI's CalcCRC16): the standard check value over "123456789".
    assert ap.crc16(b"123456789") == 0xBB3D


@pytest.mark.parametrize(("text", "crc"), [
    ("INIT:", 0xE3A5), ("TSTART:", 0x5423), ("TSTOP:", 0x2C14), ("BX:0801", 0x00EC), ("TX:0801", 0xC19B),
    ("PHSR:00", 0x20FF), ("PHSR:01", 0xE03E), ("PHSR:02", 0xE17E), ("PHSR:03", 0x21BF), ("PHSR:04", 0xE3FE),
    ("COMM:50000", 0x0048), ("COMM:00000", 0x0084), ("BEEP:1", 0x8404), ("VER:4", 0xA6EF),
    ("PINIT:0A", 0xD5EB), ("PENA:0AD", 0xAD1E), ("OKAY", 0xA896), ("RESET", 0xBE6F),
    ("ERROR01", 0x6BC2), ("ERROR04", 0x6802),
])
def test_crc_vectors(text: str, crc: int) -> None:
    assert ap.crc16(text) == crc


def test_appending_the_crc_little_endian_zeroes_the_running_crc() -> None:
    body = b"\x02\x0a\x01binary body"
    assert ap.crc16(body + struct.pack("<H", ap.crc16(body))) == 0


def test_framing() -> None:
    assert ap.frame_command("INIT:") == b"INIT:E3A5\r"
    assert ap.frame_command("COMM 50000") == b"COMM 50000\r"
    assert ap.frame_reply("OKAY") == b"OKAYA896\r"
    assert ap.frame_reply("RESET") == ap.RESET_REPLY
    with pytest.raises(ValueError, match="ASCII"):
        ap.frame_command("INIT:\r")


def test_parse_command_both_forms_and_bad_crc() -> None:
    assert ap.parse_command(b"INIT:E3A5") == ap.ParsedCommand("INIT", "", True)
    assert ap.parse_command(b"PENA:0ADAD1E") == ap.ParsedCommand("PENA", "0AD", True)
    assert ap.parse_command(b"TX 0801") == ap.ParsedCommand("TX", "0801", None)
    assert ap.parse_command(b"INIT:E3A6").crc_ok is False
    with pytest.raises(ap.NdiDecodeError):
        ap.parse_command(b"\x01\x02")


@pytest.mark.parametrize("line", [b" ", b" TX 0801", b":", b":0801E3A5", b""])
def test_parse_command_without_a_name_is_a_decode_error(line: bytes) -> None:
    with pytest.raises(ap.NdiDecodeError, match="no name" if line else "not a command"):
        ap.parse_command(line)


def test_check_reply() -> None:
    assert ap.check_reply(b"OKAYA896") == "OKAY"
    with pytest.raises(ap.NdiReplyError) as err:
        ap.check_reply(b"ERROR046802")
    assert err.value.code == 4
    assert "bad CRC in command" in str(err.value)
    with pytest.raises(ap.NdiDecodeError, match="CRC"):
        ap.check_reply(b"OKAYA897")
    with pytest.raises(ap.NdiDecodeError, match="shorter"):
        ap.check_reply(b"OK")


def test_comm_codes() -> None:
    assert ap.comm_command(115200) == "COMM:50000"
    assert ap.comm_command(9600) == "COMM:00000"
    assert ap.comm_command(230400) == "COMM:A0000"
    with pytest.raises(ValueError, match="baud"):
        ap.comm_command(12345)


def test_phsr() -> None:
    assert ap.parse_phsr("020A0010B031") == [(0x0A, 0x001), (0x0B, 0x031)]
    assert ap.format_phsr([(0x0A, 0x001), (0x0B, 0x031)]) == "020A0010B031"
    assert ap.parse_phsr("00") == []
    with pytest.raises(ap.NdiDecodeError):
        ap.parse_phsr("020A001")


def test_tx_reference_example() -> None:
    # reference A2.5: q = (1, 0, 0, 0), t = (123.45, -67.89, 456.78) mm, error 0.0123.
    text = ("01" + "0A" + "+10000+00000+00000+00000+012345-006789+045678+00123" + "00000031"
            + "0000002A" + "\n" + "0000")
    reply = ap.parse_tx(text)
    (h,) = reply.handles
    assert h.state == "valid"
    assert h.t_mm == pytest.approx((123.45, -67.89, 456.78))
    assert h.error_rms == pytest.approx(0.0123)
    assert h.frame == 42
    assert h.port_status == 0x31


quat = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(
    lambda q: sum(v * v for v in q) > 0.1).map(lambda q: tuple(v / sum(w * w for w in q) ** 0.5 for v in q))
handle_rec = st.one_of(
    st.builds(lambda h, q, t, e, s, f: ap.HandleRecord(h, "valid", q, t, e, s, f),
              st.integers(1, 255), quat, st.tuples(*[st.floats(-9999, 9999)] * 3), st.floats(0, 3),
              st.integers(0, 0xFFFFFFFF), st.integers(0, 0xFFFFFFFF)),
    st.builds(lambda h, s, f: ap.HandleRecord(h, "missing", port_status=s, frame=f),
              st.integers(1, 255), st.integers(0, 0xFFFFFFFF), st.integers(0, 0xFFFFFFFF)),
    st.builds(lambda h: ap.HandleRecord(h, "disabled"), st.integers(1, 255)),
)
replies = st.builds(lambda hs, s: ap.TrackingReply(tuple(hs), s), st.lists(handle_rec, max_size=5),
                    st.integers(0, 0xFFFF))


@given(replies)
def test_tx_round_trip(reply: ap.TrackingReply) -> None:
    framed = ap.frame_reply(ap.format_tx(reply))
    back = ap.parse_tx(ap.check_reply(framed[:-1]))
    assert back.system_status == reply.system_status
    assert [(h.handle, h.state, h.port_status, h.frame) for h in back.handles] == [
        (h.handle, h.state, h.port_status, h.frame) for h in reply.handles]
    for a, b in zip(back.handles, reply.handles, strict=True):
        if b.state == "valid":
            assert a.q_wxyz == pytest.approx(b.q_wxyz, abs=6e-5)
            assert a.t_mm == pytest.approx(b.t_mm, abs=6e-3)


@given(replies)
def test_bx_round_trip(reply: ap.TrackingReply) -> None:
    raw = ap.format_bx(reply)
    length = ap.parse_bx_header(raw[:6])
    assert len(raw) == length + 8
    back = ap.parse_bx_body(raw[6:])
    assert [(h.handle, h.state, h.port_status, h.frame) for h in back.handles] == [
        (h.handle, h.state, h.port_status if h.state != "disabled" else 0,
         h.frame if h.state != "disabled" else None) for h in reply.handles]


@given(replies, st.data())
def test_bx_detects_any_single_byte_corruption(reply: ap.TrackingReply, data: st.DataObject) -> None:
    raw = bytearray(ap.format_bx(reply))
    i = data.draw(st.integers(0, len(raw) - 1))
    raw[i] ^= data.draw(st.integers(1, 255))
    def parse(data: bytes) -> ap.TrackingReply:
        length = ap.parse_bx_header(data[:6])
        return ap.parse_bx_body(data[6:6 + length + 2])

    with pytest.raises(ap.NdiDecodeError):
        parse(bytes(raw))


@given(replies, st.data())
def test_tx_detects_any_single_byte_corruption(reply: ap.TrackingReply, data: st.DataObject) -> None:
    line = bytearray(ap.frame_reply(ap.format_tx(reply))[:-1])
    i = data.draw(st.integers(0, len(line) - 1))
    line[i] ^= data.draw(st.integers(1, 255))
    with pytest.raises((ap.NdiDecodeError, ap.NdiReplyError)):
        ap.parse_tx(ap.check_reply(bytes(line)))


def test_tool_status_flags() -> None:
    rec = ap.HandleRecord(0x0A, "valid", (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.1,
                          ap.PortStatus.OUT_OF_VOLUME | ap.PortStatus.ENABLED, 3)
    assert rec.flags == ("out_of_volume",)
    assert ap.HandleRecord(0x0A, "missing", port_status=0x80, frame=1).flags == ("partially_out", "missing")
    assert ap.HandleRecord(0x0B, "missing").transform() is None


def test_error_text() -> None:
    assert ap.error_text(0x0C) == "command invalid in current mode"
    assert ap.error_text(0x99) == "unknown error 0x99"
