"""Flock of Birds wire format: the manual's vectors, scaling, records, the resynchroniser."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.tracker_serial import fob_protocol as fp
from hil.geometry.transform import RigidTransform

FULL_36_MM = 36 * 25.4


def test_manual_worked_example_encodes_byte_exact() -> None:
    # FOB-MAN p.40: words 0x1122, 0x3344, 0x5566 are sent as C8 08 51 19 59 2A.
    assert fp.encode_words([0x1122, 0x3344, 0x5566]) == bytes.fromhex("C8 08 51 19 59 2A")


def test_manual_worked_example_decodes_to_its_words_at_14_bits() -> None:
    words = fp.decode_words(bytes.fromhex("C8 08 51 19 59 2A"))
    # Only the 14 most significant bits travel: the two LSBs come back as zero.
    assert words == [0x1122 & ~3, 0x3344 & ~3, 0x5566 & ~3]


def test_pos_ang_packing_vector() -> None:
    words = [9100, -4552, 2728, 16384, -8192, -32768]
    assert fp.encode_words(words) == bytes.fromhex("e3 11 0e 77 2a 05 00 20 00 70 00 40")
    assert fp.decode_words(bytes.fromhex("e3 11 0e 77 2a 05 00 20 00 70 00 40")) == words


@given(st.lists(st.integers(-32768, 32767), min_size=1, max_size=12))
def test_words_round_trip_at_14_bits(words: list[int]) -> None:
    raw = fp.encode_words(words)
    assert raw[0] & 0x80
    assert all(not b & 0x80 for b in raw[1:])
    assert fp.decode_words(raw) == [w & ~3 for w in words]


def test_decode_rejects_bad_phasing() -> None:
    raw = bytearray(fp.encode_words([1, 2, 3]))
    with pytest.raises(fp.FobDecodeError, match="phasing"):
        fp.decode_words(bytes([raw[0] & 0x7F]) + raw[1:])
    raw[3] |= 0x80
    with pytest.raises(fp.FobDecodeError, match="byte 3"):
        fp.decode_words(raw)
    with pytest.raises(fp.FobDecodeError, match="whole words"):
        fp.decode_words(raw[:5])


def test_scaling_rules() -> None:
    assert fp.position_full_scale_mm(0) == pytest.approx(914.4)
    assert fp.position_full_scale_mm(1) == pytest.approx(1828.8)
    assert fp.position_full_scale_mm(0, extended_range=True) == pytest.approx(3657.6)
    assert fp.position_to_word(914.4, FULL_36_MM) == 0x7FFF  # +full scale saturates at 0x7FFF
    assert fp.position_to_word(-914.4, FULL_36_MM) == -32768
    assert fp.word_to_position_mm(-32768, FULL_36_MM) == pytest.approx(-914.4)
    assert fp.word_to_angle_rad(-32768) == pytest.approx(-math.pi)
    assert fp.angle_to_word(math.pi) == -32768  # +180 deg is -180 deg
    assert fp.word_to_unit(0x7FFF) == pytest.approx(0.99997, abs=1e-5)
    assert fp.unit_to_word(-1.0) == -32768


def test_record_lengths_match_the_manual_table() -> None:
    expected = {"POSITION": 6, "ANGLES": 6, "MATRIX": 18, "POSITION_ANGLES": 12, "POSITION_MATRIX": 24,
                "QUATERNION": 8, "POSITION_QUATERNION": 14}
    for fmt in fp.FobFormat:
        assert fp.RecordLayout(fmt).length == expected[fmt.name]
    assert fp.RecordLayout(fp.FobFormat.POSITION_ANGLES, button_mode=True, group_mode=True).length == 14


poses = st.builds(
    lambda az, el, roll, x, y, z: RigidTransform(RigidTransform.from_euler_zyx(az, el, roll).R, [x, y, z]),
    st.floats(-3.1, 3.1), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1),
    st.floats(-900, 900), st.floats(-900, 900), st.floats(-900, 900))


@pytest.mark.parametrize("fmt", [fp.FobFormat.POSITION_ANGLES, fp.FobFormat.POSITION_MATRIX,
                                 fp.FobFormat.POSITION_QUATERNION])
@given(T=poses, button=st.sampled_from([0x00, 0x10, 0x30, 0x70]), address=st.integers(1, 14))
def test_record_round_trip(fmt: fp.FobFormat, T: RigidTransform, button: int, address: int) -> None:
    layout = fp.RecordLayout(fmt, button_mode=True, group_mode=True)
    raw = fp.encode_record(T, layout, full_scale_mm=FULL_36_MM, button=button, address=address)
    assert len(raw) == layout.length
    rec = fp.decode_record(raw, layout, full_scale_mm=FULL_36_MM)
    assert rec.button == button
    assert rec.address == address
    # 14-bit resolution: 4 counts of 914.4/32768 mm, 4 counts of 180/32768 deg (and 1/8192 units).
    np.testing.assert_allclose(rec.T_tracker_from_sensor.t, T.t, atol=0.12)
    rel = rec.T_tracker_from_sensor.inverse() @ T
    assert rel.rotation_angle_rad() < math.radians(0.1)


def test_matrix_record_is_the_transpose_column_major() -> None:
    # The Bird's matrix maps transmitter axes into sensor axes (FOB-MAN p.77): M = R^T, sent
    # M(1,1), M(2,1), M(3,1), ... For a 90 deg azimuth, R = Rz(90): M(1,2) = +1 is the 4th word.
    T = RigidTransform(RigidTransform.from_euler_zyx(math.pi / 2, 0, 0).R, [0, 0, 0])
    raw = fp.encode_record(T, fp.RecordLayout(fp.FobFormat.MATRIX), full_scale_mm=FULL_36_MM)
    words = fp.decode_words(raw)
    assert words[3] == 0x7FFF & ~3  # M(1,2) = sin(A) = +1
    assert words[1] == -32768  # M(2,1) = -sin(A) = -1


def test_quaternion_record_is_the_conjugate() -> None:
    T = RigidTransform(RigidTransform.from_euler_zyx(0.5, 0, 0).R, [0, 0, 0])
    raw = fp.encode_record(T, fp.RecordLayout(fp.FobFormat.QUATERNION), full_scale_mm=FULL_36_MM)
    q = [fp.word_to_unit(w) for w in fp.decode_words(raw)]
    assert q[0] == pytest.approx(math.cos(0.25), abs=2e-4)
    assert q[3] == pytest.approx(-math.sin(0.25), abs=2e-4)  # conjugate of a +z rotation


def test_implausible_content_is_refused() -> None:
    layout = fp.RecordLayout(fp.FobFormat.POSITION_QUATERNION)
    raw = fp.encode_words([0, 0, 0, 16384, 0, 0, 0])  # quaternion norm 0.5
    with pytest.raises(fp.FobDecodeError, match="norm"):
        fp.decode_record(raw, layout, full_scale_mm=FULL_36_MM)
    ang = fp.RecordLayout(fp.FobFormat.POSITION_ANGLES)
    with pytest.raises(fp.FobDecodeError, match="elevation"):
        fp.decode_record(fp.encode_words([0, 0, 0, 0, 20000, 0]), ang, full_scale_mm=FULL_36_MM)
    btn = fp.RecordLayout(fp.FobFormat.POSITION, button_mode=True)
    with pytest.raises(fp.FobDecodeError, match="button"):
        fp.decode_record(fp.encode_words([0, 0, 0]) + b"\x05", btn, full_scale_mm=FULL_36_MM)


# --- resynchroniser ---------------------------------------------------------------------------------
LAYOUT = fp.RecordLayout(fp.FobFormat.POSITION_QUATERNION, group_mode=True)


def _records(n: int) -> list[bytes]:
    out = []
    for i in range(n):
        T = RigidTransform(RigidTransform.from_euler_zyx(0.1 * i, 0.2, -0.3).R, [10.0 * i, -5.0, 300.0])
        out.append(fp.encode_record(T, LAYOUT, full_scale_mm=FULL_36_MM, address=1 + i % 3))
    return out


def _feed(data: bytes, chunks: list[int]) -> list[fp.FobRecord]:
    sync = fp.RecordSynchronizer(LAYOUT, full_scale_mm=FULL_36_MM, addresses=range(1, 4))
    out: list[fp.FobRecord] = []
    pos = 0
    for c in chunks:
        out += sync.feed(data[pos:pos + c])
        pos += c
    out += sync.feed(data[pos:])
    return out


def test_clean_stream_in_any_chunking_loses_only_the_unconfirmed_last_record() -> None:
    recs = _records(6)
    out = _feed(b"".join(recs), [1, 5, 13, 2, 40])
    assert [r.words for r in out] == [fp.decode_record(r, LAYOUT, full_scale_mm=FULL_36_MM).words
                                      for r in recs[:5]]
    assert [r.end_offset for r in out] == [LAYOUT.length * (i + 1) for i in range(5)]


def test_end_of_reply_accepts_the_last_record() -> None:
    recs = _records(2)
    sync = fp.RecordSynchronizer(LAYOUT, full_scale_mm=FULL_36_MM)
    assert len(sync.feed(b"".join(recs))) == 1
    assert len(sync.end_of_reply()) == 1


@st.composite
def damaged_stream(draw: st.DrawFn, phase_free: bool) -> tuple[list[bytes], list[int], bytes]:
    """Records with garbage inserted at random places; returns (records, damaged indices, stream)."""
    recs = _records(draw(st.integers(3, 12)))
    n = len(recs)
    inserts = draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, LAYOUT.length),
                                      st.binary(min_size=1, max_size=20)), max_size=4))
    damaged: set[int] = set()
    pieces = [bytearray(r) for r in recs]
    for idx, at, garbage in sorted(inserts, key=lambda x: (x[0], -x[1])):
        g = bytes(b & 0x7F for b in garbage) if phase_free else garbage
        pieces[idx][at:at] = g
        damaged.add(idx)
        if at == 0 and idx > 0:
            damaged.add(idx - 1)  # inserted at a boundary: it is "after" the previous record too
    return recs, sorted(damaged), b"".join(bytes(p) for p in pieces)


@given(damaged_stream(phase_free=True), st.lists(st.integers(1, 30), max_size=10))
def test_resync_never_emits_a_corrupt_record_under_phase_free_noise(
        case: tuple[list[bytes], list[int], bytes], chunks: list[int]) -> None:
    recs, damaged, stream = case
    out = _feed(stream, chunks)
    good = {fp.decode_record(r, LAYOUT, full_scale_mm=FULL_36_MM).words for r in recs}
    assert all(r.words in good for r in out)
    # Completeness: every record untouched by the noise (and not the unconfirmed last one) comes out.
    want = [fp.decode_record(r, LAYOUT, full_scale_mm=FULL_36_MM).words
            for i, r in enumerate(recs[:-1]) if i not in damaged and i + 1 not in damaged]
    got = [r.words for r in out]
    assert all(w in got for w in want)


@given(damaged_stream(phase_free=False), st.lists(st.integers(1, 30), max_size=10))
def test_resync_loses_no_more_than_the_damaged_records_under_any_noise(
        case: tuple[list[bytes], list[int], bytes], chunks: list[int]) -> None:
    recs, damaged, stream = case
    out = [r.words for r in _feed(stream, chunks)]
    for i, r in enumerate(recs[:-1]):
        if i not in damaged and i + 1 not in damaged:
            assert fp.decode_record(r, LAYOUT, full_scale_mm=FULL_36_MM).words in out


@given(st.lists(st.integers(0, 5), min_size=1, max_size=3))
def test_truncation_and_lost_phasing_never_produce_a_record(cuts: list[int]) -> None:
    recs = [bytearray(r) for r in _records(8)]
    for k in cuts:
        recs[k + 1] = recs[k + 1][: len(recs[k + 1]) // 2]  # truncated
        recs[k + 2][0] &= 0x7F  # lost phasing
    out = _feed(b"".join(bytes(r) for r in recs), [7])
    good = {fp.decode_record(r, LAYOUT, full_scale_mm=FULL_36_MM).words for r in _records(8)}
    assert out
    assert all(r.words in good for r in out)


def test_unknown_group_address_is_damage() -> None:
    recs = _records(3)
    bad = bytearray(recs[1])
    bad[-1] = 9
    sync = fp.RecordSynchronizer(LAYOUT, full_scale_mm=FULL_36_MM, addresses=range(1, 4))
    out = sync.feed(recs[0] + bytes(bad) + recs[2]) + sync.end_of_reply()
    assert [r.address for r in out] == [1, 3]
    assert sync.stats.damaged == 1


def test_commands_and_parameters() -> None:
    assert fp.examine(fp.PARAM_MODEL_ID) == b"O\x0f"
    assert fp.examine(fp.PARAM_BIRD_STATUS, address=2) == b"\xf2O\x00"
    assert fp.rs232_to_fbb(17) == b"\xe1"
    assert fp.change(fp.PARAM_GROUP_MODE, b"\x01") == b"P\x23\x01"
    assert fp.change(fp.PARAM_MEASUREMENT_RATE, (100 * 256).to_bytes(2, "little")) == b"P\x07\x00\x64"
    with pytest.raises(ValueError, match="takes 1 data bytes"):
        fp.change(fp.PARAM_AUTO_CONFIG, b"\x01\x02")
    with pytest.raises(ValueError, match="outside"):
        fp.rs232_to_fbb(31)


def test_bird_status_word() -> None:
    st_ = fp.BirdStatus.build(master=True, initialized=True, error=False, running=True, sleeping=False,
                              stream=True, fmt=fp.FobFormat.POSITION_QUATERNION)
    assert st_.word == 0x8000 | 0x4000 | 0x1000 | (8 << 1) | 1
    back = fp.BirdStatus.from_bytes(st_.to_bytes())
    assert back.master
    assert back.running
    assert back.stream
    assert not back.error
    assert back.fmt is fp.FobFormat.POSITION_QUATERNION
    # GOBBI derives the format command as 'V' - 1 + format code.
    assert ord("V") - 1 + ((back.word & 0x1E) >> 1) == ord("]")


def test_error_codes() -> None:
    assert fp.error_text(6) == "invalid RS232 command"
    assert 1 in fp.FATAL_ERROR_CODES
    assert 6 not in fp.FATAL_ERROR_CODES
    assert fp.error_text(99) == "unknown error 99"
