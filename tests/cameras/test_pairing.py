"""Pair rules of two-camera stereo sources (drivers.camera.pairing)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.camera.pairing import FrameIdUnwrapper, PairRule, StereoPairer
from drivers.interfaces.camera import Frame

IMG = np.zeros((2, 2), dtype=np.uint8)
PERIOD_NS = 20_000_000


def frame(t_ns: int, seq: int = 0, device_t_ns: int | None = None) -> Frame:
    return Frame(image=IMG, t_ns=t_ns, seq=seq, device_t_ns=device_t_ns)


def test_unwrapper_counts_across_the_16_bit_wrap() -> None:
    unwrap = FrameIdUnwrapper()
    assert [unwrap(i) for i in (65533, 65534, 65535, 1, 2)] == [0, 1, 2, 3, 4]


def test_unwrapper_counts_lost_frames() -> None:
    unwrap = FrameIdUnwrapper()
    assert [unwrap(i) for i in (10, 11, 14, 15)] == [0, 1, 4, 5]


@given(start=st.integers(1, 65535), steps=st.lists(st.integers(1, 1000), max_size=200))
def test_unwrapper_recovers_the_true_index(start: int, steps: list[int]) -> None:
    unwrap = FrameIdUnwrapper()
    true_index = 0
    assert unwrap(start) == 0
    for step in steps:
        true_index += step
        raw = (start - 1 + true_index) % 65535 + 1  # 1..65535, 0 skipped
        assert unwrap(raw) == true_index


def test_trigger_id_pairs_equal_keys_and_waits_for_both() -> None:
    pairer = StereoPairer(PairRule.TRIGGER_ID, PERIOD_NS)
    pairer.push("left", frame(100, seq=0), key=1)
    assert pairer.pop_pair() is None
    pairer.push("right", frame(900, seq=0), key=1)
    pair = pairer.pop_pair()
    assert pair is not None
    assert (pair.left.t_ns, pair.right.t_ns) == (100, 900)
    assert pairer.pop_pair() is None  # not returned twice


def test_trigger_id_min_key_rejects_a_late_older_pair() -> None:
    pairer = StereoPairer(PairRule.TRIGGER_ID, PERIOD_NS)
    pairer.push("left", frame(1, seq=4), key=5)
    pairer.push("right", frame(2, seq=4), key=5)
    assert pairer.pop_pair(min_key=6) is None
    pairer.push("left", frame(3, seq=5), key=6)
    pairer.push("right", frame(4, seq=5), key=6)
    pair = pairer.pop_pair(min_key=6)
    assert pair is not None
    assert pair.left.seq == 5
    assert pairer.pending("left") == 0
    assert pairer.dropped == 2  # the two frames of trigger 5


def test_id_rule_needs_a_key() -> None:
    pairer = StereoPairer(PairRule.FRAME_ID, PERIOD_NS)
    with pytest.raises(ValueError, match="needs a key"):
        pairer.push("left", frame(0))


def test_host_time_takes_the_newest_pair_within_half_a_period() -> None:
    pairer = StereoPairer(PairRule.HOST_TIME, PERIOD_NS)
    for k in range(3):
        pairer.push("left", frame(k * PERIOD_NS, seq=k))
        pairer.push("right", frame(k * PERIOD_NS + 3_000_000, seq=k))
    pair = pairer.pop_pair()
    assert pair is not None
    assert (pair.left.seq, pair.right.seq) == (2, 2)
    assert pairer.dropped == 4
    assert pairer.pop_pair() is None


def test_host_time_refuses_more_than_half_a_period() -> None:
    pairer = StereoPairer(PairRule.HOST_TIME, PERIOD_NS)
    pairer.push("left", frame(0))
    pairer.push("right", frame(PERIOD_NS // 2 + 1))
    assert pairer.pop_pair() is None
    pairer.push("left", frame(PERIOD_NS))
    pair = pairer.pop_pair()
    assert pair is not None
    assert pair.skew_ns == PERIOD_NS // 2 + 1 - PERIOD_NS


def test_device_time_uses_device_clock_not_host_time() -> None:
    pairer = StereoPairer(PairRule.DEVICE_TIME, PERIOD_NS)
    # Host receive times are far apart (transport), device times agree.
    pairer.push("left", frame(0, seq=0, device_t_ns=5_000_000_000))
    pairer.push("right", frame(15_000_000, seq=7, device_t_ns=5_000_001_000))
    pair = pairer.pop_pair()
    assert pair is not None
    assert pair.right.seq == 7


def test_device_time_without_device_timestamps_is_an_error() -> None:
    pairer = StereoPairer(PairRule.DEVICE_TIME, PERIOD_NS)
    pairer.push("left", frame(0))
    pairer.push("right", frame(0))
    with pytest.raises(ValueError, match="device_t_ns"):
        pairer.pop_pair()


def test_pending_queue_is_bounded() -> None:
    pairer = StereoPairer(PairRule.TRIGGER_ID, PERIOD_NS, max_pending=3)
    for k in range(5):
        pairer.push("left", frame(k), key=k + 1)
    assert pairer.pending("left") == 3
    assert pairer.dropped == 2


@given(offsets=st.lists(st.integers(-9_000_000, 9_000_000), min_size=1, max_size=30))
def test_time_pairs_are_never_older_than_the_last_and_within_half_period(offsets: list[int]) -> None:
    pairer = StereoPairer(PairRule.HOST_TIME, PERIOD_NS)
    last_t: int | None = None
    for k, off in enumerate(offsets):
        t = (k + 1) * PERIOD_NS
        pairer.push("left", frame(t, seq=k))
        pairer.push("right", frame(t + off, seq=k))
        pair = pairer.pop_pair()
        assert pair is not None
        assert abs(pair.skew_ns) <= PERIOD_NS // 2
        assert pair.left.seq == pair.right.seq == k
        assert last_t is None or pair.left.t_ns > last_t
        last_t = pair.left.t_ns


def test_frame_id_learns_the_counter_offset_from_host_time() -> None:
    pairer = StereoPairer(PairRule.FRAME_ID, PERIOD_NS)
    # The right camera started one pulse later: its key k is the left's key k + 1.
    for k in range(1, 4):
        pairer.push("left", frame(k * PERIOD_NS, seq=k), key=k)
        pairer.push("right", frame(k * PERIOD_NS + 1_000_000, seq=k - 1), key=k - 1)
        pair = pairer.pop_pair()
        assert pair is not None
        assert (pair.left.seq, pair.right.seq) == (k, k - 1)
    assert pairer.realigned == 0


def test_frame_id_realigns_when_a_camera_misses_a_pulse() -> None:
    pairer = StereoPairer(PairRule.FRAME_ID, PERIOD_NS)
    pairer.push("left", frame(PERIOD_NS, seq=0), key=1)
    pairer.push("right", frame(PERIOD_NS, seq=0), key=1)
    assert pairer.pop_pair() is not None
    # The right camera misses pulse 2: its next frame (key 2) is taken at pulse 3.
    pairer.push("left", frame(2 * PERIOD_NS, seq=1), key=2)
    pairer.push("left", frame(3 * PERIOD_NS, seq=2), key=3)
    pairer.push("right", frame(3 * PERIOD_NS, seq=1), key=2)
    pair = pairer.pop_pair()
    assert pair is not None
    assert (pair.left.seq, pair.right.seq) == (2, 1)  # by time, not the wrong id pair (1, 1)
    assert pairer.realigned == 1
    pairer.push("left", frame(4 * PERIOD_NS, seq=3), key=4)
    pairer.push("right", frame(4 * PERIOD_NS, seq=2), key=3)
    pair = pairer.pop_pair()
    assert pair is not None
    assert (pair.left.seq, pair.right.seq) == (3, 2)
