"""Flock of Birds records from a hostile serial line: the resynchroniser never crashes, never
hangs, and never returns a record that was not sent (for damage that framing can detect)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.tracker_serial import fob_protocol as fp
from hil.geometry.transform import RigidTransform

from .strategies import require_message

FULL_MM = 36 * 25.4
LAYOUTS = [
    fp.RecordLayout(fmt, button, group)
    for fmt in fp.FobFormat
    for button in (False, True)
    for group in (False, True)
]

poses = st.builds(
    lambda rv, t: RigidTransform(RigidTransform.from_rotvec(np.array(rv)).R, np.array(t)),
    st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    st.lists(st.floats(-800.0, 800.0), min_size=3, max_size=3),
)


def _encode(T: RigidTransform, layout: fp.RecordLayout, address: int = 3) -> bytes:
    return fp.encode_record(T, layout, full_scale_mm=FULL_MM, button=0x10, address=address)


@settings(max_examples=150)
@given(st.sampled_from(LAYOUTS), poses)
def test_record_round_trip_within_quantisation(layout: fp.RecordLayout, T: RigidTransform) -> None:
    rec = fp.decode_record(_encode(T, layout), layout, full_scale_mm=FULL_MM)
    if layout.fmt.has_position:
        # 14 bits over +-full scale: one LSB is 4 * FULL_MM / 32768 mm
        assert np.allclose(rec.T_tracker_from_sensor.t, T.t, atol=4 * FULL_MM / 32768 + 1e-9)
    else:
        assert np.allclose(rec.T_tracker_from_sensor.t, 0.0)
    if layout.fmt is not fp.FobFormat.POSITION:
        dR = rec.T_tracker_from_sensor.R.T @ T.R
        angle = np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))
        assert angle < 2e-3
    assert rec.button == (0x10 if layout.button_mode else None)
    assert rec.address == (3 if layout.group_mode else None)


@settings(max_examples=200)
@given(st.sampled_from(LAYOUTS), st.binary(max_size=400), st.lists(st.integers(1, 64), max_size=10))
def test_random_bytes_never_crash(layout: fp.RecordLayout, data: bytes, cuts: list[int]) -> None:
    sync = fp.RecordSynchronizer(layout, full_scale_mm=FULL_MM)
    out = []
    pos = 0
    for c in cuts:
        out += sync.feed(data[pos : pos + c])
        pos += c
    out += sync.feed(data[pos:])
    out += sync.end_of_reply()
    for rec in out:  # whatever came out passed every decode check
        assert np.all(np.isfinite(rec.T_tracker_from_sensor.t))
        assert abs(np.linalg.det(rec.T_tracker_from_sensor.R) - 1.0) < 1e-6
    # bounded memory: nothing accumulates past one record after end_of_reply
    assert len(sync._buf) <= layout.length
    assert sync.stats.records == len(out)


@st.composite
def damaged_stream(draw: st.DrawFn) -> tuple[fp.RecordLayout, list[bytes], bytes]:
    """Records, then damage of the kinds framing can detect: bytes without the phasing bit
    inserted anywhere, and any bytes deleted."""
    layout = draw(st.sampled_from(LAYOUTS))
    recs = [_encode(T, layout) for T in draw(st.lists(poses, min_size=1, max_size=6))]
    buf = bytearray(b"".join(recs))
    for _ in range(draw(st.integers(0, 4))):
        i = draw(st.integers(0, len(buf)))
        if draw(st.booleans()) and buf:
            del buf[min(i, len(buf) - 1) : min(i, len(buf) - 1) + draw(st.integers(1, 4))]
        else:
            buf[i:i] = bytes(b & 0x7F for b in draw(st.binary(min_size=1, max_size=5)))
    return layout, recs, bytes(buf)


@settings(max_examples=200)
@given(damaged_stream(), st.integers(1, 17))
def test_damaged_stream_yields_only_sent_records_in_order(
    case: tuple[fp.RecordLayout, list[bytes], bytes], chunk: int
) -> None:
    layout, recs, stream = case
    sync = fp.RecordSynchronizer(layout, full_scale_mm=FULL_MM)
    out = []
    for i in range(0, len(stream), chunk):
        out += sync.feed(stream[i : i + chunk])
    out += sync.end_of_reply()
    sent = [fp.decode_record(r, layout, full_scale_mm=FULL_MM).words for r in recs]
    got = [r.words for r in out]
    it = iter(sent)
    assert all(any(g == s for s in it) for g in got), "a record that was never sent came out"
    if stream == b"".join(recs):
        assert got == sent  # undamaged: every record, in order


@settings(max_examples=100)
@given(st.sampled_from(LAYOUTS), st.lists(poses, min_size=2, max_size=5), st.integers(1, 9))
def test_clean_stream_in_any_chunking_gives_every_record(
    layout: fp.RecordLayout, Ts: list[RigidTransform], chunk: int
) -> None:
    stream = b"".join(_encode(T, layout) for T in Ts)
    sync = fp.RecordSynchronizer(layout, full_scale_mm=FULL_MM)
    out = []
    for i in range(0, len(stream), chunk):
        out += sync.feed(stream[i : i + chunk])
    # all but the last are known whole when the next phasing byte arrives
    assert len(out) == len(Ts) - 1
    out += sync.end_of_reply()
    assert len(out) == len(Ts)
    assert sync.stats.damaged == 0
    assert [r.end_offset for r in out] == [layout.length * (k + 1) for k in range(len(Ts))]


@settings(max_examples=200)
@given(st.sampled_from(LAYOUTS), st.binary(max_size=60))
def test_decode_record_typed_errors_only(layout: fp.RecordLayout, data: bytes) -> None:
    try:
        rec = fp.decode_record(data, layout, full_scale_mm=FULL_MM)
    except fp.FobDecodeError as exc:
        require_message(exc)
        return
    assert len(data) == layout.length
    assert np.all(np.isfinite(rec.T_tracker_from_sensor.as_matrix()))


@settings(max_examples=100)
@given(st.binary(min_size=0, max_size=8))
def test_bird_status_from_any_bytes(data: bytes) -> None:
    try:
        fp.BirdStatus.from_bytes(data)
    except (fp.FobDecodeError, ValueError) as exc:
        require_message(exc)
