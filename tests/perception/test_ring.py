"""The marker ring: records round-trip exactly, errors round-trip, too many markers are refused,
and a reader never accepts a slot the writer overran while it was copying."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.perception.ring import (
    ERROR_BYTES,
    MAX_MARKERS,
    RECORD_WORDS,
    SLOTS,
    MarkerRecord,
    MarkerRing,
    RecordKind,
    ring_words,
)
from hil.servo.shm import ShmRegion


@pytest.fixture
def ring() -> Iterator[MarkerRing]:
    region = ShmRegion.local(ring_words())
    yield MarkerRing(region)
    region.close()


def _write(ring: MarkerRing, k: int, n: int = 3) -> None:
    """Record ``k``: every field derived from ``k`` (so a torn copy shows)."""
    pts = np.full((n, 3), float(k))
    ring.write_markers(pair_seq=k, left=(k, 1000 * k, 7 * k), right=(k + 1, 1000 * k + 5, None),
                       time_source=k % 2, grab_done_t_ns=1000 * k + 9, locate_ms=k / 8,
                       image_size=(640 + k, 480), points_mm=pts, left_px=np.full((n, 2), -float(k)),
                       right_px=None)


def _consistent(rec: MarkerRecord) -> bool:
    k = rec.pair_seq
    return (rec.left_seq == k and rec.right_seq == k + 1 and rec.left_t_ns == 1000 * k
            and rec.right_t_ns == 1000 * k + 5 and rec.left_device_t_ns == 7 * k
            and rec.right_device_t_ns is None and rec.grab_done_t_ns == 1000 * k + 9
            and rec.locate_ms == k / 8 and rec.image_size == (640 + k, 480)
            and rec.time_source == k % 2 and bool(np.all(rec.points_mm == k))
            and rec.left_px is not None and bool(np.all(rec.left_px == -k)) and rec.right_px is None)


def test_empty_ring_reads_none(ring: MarkerRing) -> None:
    assert ring.head == 0
    assert ring.read_latest() is None


@given(n_pts=st.integers(0, MAX_MARKERS), n_left=st.integers(0, MAX_MARKERS),
       n_right=st.one_of(st.none(), st.integers(0, MAX_MARKERS)),
       dev=st.one_of(st.none(), st.integers(-(2**62), 2**62)), source=st.integers(0, 1),
       seed=st.integers(0, 2**32 - 1))
@settings(max_examples=60, deadline=None)
def test_a_marker_set_round_trips_exactly(n_pts: int, n_left: int, n_right: int | None, dev: int | None,
                                          source: int, seed: int) -> None:
    region = ShmRegion.local(ring_words())
    try:
        ring = MarkerRing(region)
        rng = np.random.default_rng(seed)
        pts = rng.normal(0, 100, (n_pts, 3))
        left = rng.normal(0, 300, (n_left, 2))
        right = None if n_right is None else rng.normal(0, 300, (n_right, 2))
        for k in range(seed % 40):   # anywhere in the ring, wrapped or not
            _write(ring, k)
        ring.write_markers(pair_seq=99, left=(5, 123, dev), right=(6, 456, None), time_source=source,
                           grab_done_t_ns=789, locate_ms=2.5, image_size=(1280, 1024), points_mm=pts,
                           left_px=left, right_px=right)
        rec = ring.read_latest()
        assert rec is not None
        assert rec.kind is RecordKind.MARKERS
        assert rec.error is None
        assert (rec.pair_seq, rec.left_seq, rec.right_seq) == (99, 5, 6)
        assert (rec.left_t_ns, rec.right_t_ns) == (123, 456)
        assert (rec.left_device_t_ns, rec.right_device_t_ns) == (dev, None)
        assert (rec.time_source, rec.grab_done_t_ns, rec.locate_ms) == (source, 789, 2.5)
        assert rec.image_size == (1280, 1024)
        assert np.array_equal(rec.points_mm, pts.reshape(-1, 3))
        assert rec.left_px is not None
        assert np.array_equal(rec.left_px, left.reshape(-1, 2))
        if right is None:
            assert rec.right_px is None
        else:
            assert rec.right_px is not None
            assert np.array_equal(rec.right_px, right.reshape(-1, 2))
    finally:
        region.close()


@given(message=st.text(max_size=2000))
@settings(max_examples=40, deadline=None)
def test_an_error_record_round_trips(message: str) -> None:
    region = ShmRegion.local(ring_words())
    try:
        ring = MarkerRing(region)
        _write(ring, 1)
        ring.write_error(RecordKind.GRAB_ERROR, 2, ("DisconnectedError", "camera", message), 55)
        rec = ring.read_latest()
        assert rec is not None
        assert rec.kind is RecordKind.GRAB_ERROR
        assert rec.pair_seq == 2
        assert rec.grab_done_t_ns == 55
        assert rec.error is not None
        assert rec.error[:2] == ("DisconnectedError", "camera")
        full = "\x00".join(("DisconnectedError", "camera", message)).encode()
        if len(full) <= ERROR_BYTES and "\x00" not in message:
            assert rec.error[2] == message
        else:   # cut to fit: a prefix, never garbage
            got = rec.error[2].encode("utf-8", "replace").rstrip(b"\xef\xbf\xbd")
            assert message.encode().startswith(got)
    finally:
        region.close()


def test_too_many_markers_are_refused_not_truncated(ring: MarkerRing) -> None:
    too_many = f"{MAX_MARKERS + 1} triangulated markers located, at most {MAX_MARKERS}"
    with pytest.raises(ValueError, match=too_many):
        ring.write_markers(pair_seq=1, left=(1, 1, None), right=(1, 1, None), time_source=0, grab_done_t_ns=1,
                           locate_ms=0.0, image_size=(1, 1), points_mm=np.zeros((MAX_MARKERS + 1, 3)),
                           left_px=None, right_px=None)
    with pytest.raises(ValueError, match="left markers"):
        ring.write_markers(pair_seq=1, left=(1, 1, None), right=(1, 1, None), time_source=0, grab_done_t_ns=1,
                           locate_ms=0.0, image_size=(1, 1), points_mm=np.zeros((1, 3)),
                           left_px=np.zeros((MAX_MARKERS + 1, 2)), right_px=None)
    assert ring.head == 0


class _Racing(MarkerRing):
    """A ring whose reader's i-th copy is interrupted half-way by the writer publishing
    ``writes[i]`` records (what a concurrent writer could do), and remembers which slot it copied."""

    def __init__(self, region: ShmRegion, writes: list[int], start: int) -> None:
        super().__init__(region)
        self.writes, self.next_k, self.copied = list(writes), start, -1

    def _copy_slot(self, k: int) -> None:
        b = self._base(k)
        half = RECORD_WORDS // 2
        self._copy[:half] = self.region.f[b:b + half]
        for _ in range(self.writes.pop(0) if self.writes else 0):
            _write(self, self.next_k)
            self.next_k += 1
        self._copy[half:] = self.region.f[b + half:b + RECORD_WORDS]
        self.copied = k


@given(start=st.integers(1, 3 * SLOTS), writes=st.lists(st.integers(0, 2 * SLOTS), max_size=5))
@settings(max_examples=200, deadline=None)
def test_a_reader_never_accepts_an_overrun_slot(start: int, writes: list[int]) -> None:
    region = ShmRegion.local(ring_words())
    try:
        ring = _Racing(region, writes, start)
        for k in range(start):
            _write(ring, k)
        ring.next_k = start
        rec = ring.read_latest()
        assert rec is not None
        assert _consistent(rec)
        assert rec.pair_seq == ring.copied   # the record it meant to read, whole
    finally:
        region.close()


def test_the_overrun_check_is_needed() -> None:
    """A copy the writer lapped is torn, and the check rejects it: the test above can fail."""
    region = ShmRegion.local(ring_words())
    try:
        ring = _Racing(region, [SLOTS], 5)
        for k in range(5):
            _write(ring, k)
        ring.next_k = 5
        ring._copy_slot(4)            # half of record 4, then the writer laps the ring
        from hil.perception.ring import _decode

        assert not _consistent(_decode(ring._copy))
        assert not ring._still_valid(5)
    finally:
        region.close()
