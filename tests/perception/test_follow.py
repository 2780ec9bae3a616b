"""The flange source a perception process's world reads the arm from: the servo's state ring,
attached by name, interpolated between records, turned from TCP to flange poses."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.geometry.transform import RigidTransform
from hil.perception.follow import RingFlangeSource
from hil.servo.link import RING_SLOTS
from hil.servo.shm import ShmRegion, StateRing, ring_words

T_FLANGE_FROM_TCP = RigidTransform(np.eye(3), np.array([0.0, 0.0, 150.0]))


@pytest.fixture(scope="module")
def ring_and_source() -> Iterator[tuple[StateRing, RingFlangeSource]]:
    region = ShmRegion.create(ring_words(RING_SLOTS))
    source = RingFlangeSource(str(region.name), T_FLANGE_FROM_TCP)
    ring = StateRing(region, RING_SLOTS)
    assert source.T_robot_from_flange_at(0) is None   # before the loop's first record
    R = RigidTransform.from_rotvec(np.array([0.0, 0.0, 0.3])).R
    for k in range(50):   # TCP at x = k mm, every 2 ms from t = 1 s
        pose = np.concatenate([R.reshape(9), [float(k), 0.0, 0.0]])
        ring.write(t_ns=10**9 + k * 2_000_000, cmd_t_ns=0, safety_code=0, mode_code=0, period=k, servo_mode=0,
                   pose=pose, q_rad=np.zeros(6), tcp_speed_mm_s=0.0)
    try:
        yield ring, source
    finally:
        source.close()
        region.close()


def _tcp_x(source: RingFlangeSource, t_ns: int) -> float:
    T = source.T_robot_from_flange_at(t_ns)
    assert T is not None
    tcp = T @ T_FLANGE_FROM_TCP
    return float(tcp.t[0])


@given(k=st.integers(0, 48), frac=st.floats(0.0, 1.0))
@settings(max_examples=100, deadline=None)
def test_poses_between_records_are_interpolated(ring_and_source: tuple[StateRing, RingFlangeSource], k: int,
                                                frac: float) -> None:
    _, source = ring_and_source
    t = 10**9 + k * 2_000_000 + round(frac * 2_000_000)
    assert _tcp_x(source, t) == pytest.approx(k + round(frac * 2_000_000) / 2_000_000, abs=1e-9)


Fixture = tuple[StateRing, RingFlangeSource]


def test_past_the_newest_record_the_motion_goes_on_for_one_period_then_holds(
        ring_and_source: Fixture) -> None:
    """A pair rendered before the loop recorded the arm at its exposure (a CB3's 8 ms period): the
    last two records' motion carries on for one of their spacings, no further."""
    _, source = ring_and_source
    newest_ns = 10**9 + 49 * 2_000_000
    assert _tcp_x(source, newest_ns) == pytest.approx(49.0)
    assert _tcp_x(source, newest_ns + 1_000_000) == pytest.approx(49.5)
    assert _tcp_x(source, newest_ns + 2_000_000) == pytest.approx(50.0)
    assert _tcp_x(source, 10**12) == pytest.approx(50.0)      # held at one spacing ahead


def test_before_the_oldest_record_the_oldest_stands(ring_and_source: Fixture) -> None:
    _, source = ring_and_source
    assert _tcp_x(source, 0) == pytest.approx(0.0)


def test_a_single_record_is_held() -> None:
    region = ShmRegion.create(ring_words(RING_SLOTS))
    source = RingFlangeSource(str(region.name), T_FLANGE_FROM_TCP)
    try:
        StateRing(region, RING_SLOTS).write(
            t_ns=10**9, cmd_t_ns=0, safety_code=0, mode_code=0, period=0, servo_mode=0,
            pose=np.concatenate([np.eye(3).reshape(9), [7.0, 0.0, 0.0]]), q_rad=np.zeros(6),
            tcp_speed_mm_s=0.0)
        assert _tcp_x(source, 10**9 + 5_000_000) == pytest.approx(7.0)
    finally:
        source.close()
        region.close()


def test_the_flange_is_the_tcp_moved_back_along_the_tool(ring_and_source: Fixture) -> None:
    _, source = ring_and_source
    T = source.T_robot_from_flange_at(10**9)
    assert T is not None
    R = RigidTransform.from_rotvec(np.array([0.0, 0.0, 0.3])).R
    assert np.allclose(T.R, R)
    assert np.allclose(T.t, np.array([0.0, 0.0, -150.0]))   # R keeps z: the flange 150 mm behind the TCP


def test_follow_moves_to_a_restarted_loops_ring() -> None:
    """A restarted servo process records the arm in a new ring: after ``follow`` (from another
    thread, in the perception process) the poses come from it, and the old ring may be gone."""
    def ring_at(x_mm: float) -> tuple[ShmRegion, StateRing]:
        region = ShmRegion.create(ring_words(RING_SLOTS))
        ring = StateRing(region, RING_SLOTS)
        ring.write(t_ns=10**9, cmd_t_ns=0, safety_code=0, mode_code=0, period=0, servo_mode=0,
                   pose=np.concatenate([np.eye(3).reshape(9), [x_mm, 0.0, 0.0]]), q_rad=np.zeros(6),
                   tcp_speed_mm_s=0.0)
        return region, ring

    old_region, _ = ring_at(1.0)
    new_region, _ = ring_at(2.0)
    source = RingFlangeSource(str(old_region.name), T_FLANGE_FROM_TCP)
    try:
        assert _tcp_x(source, 10**9) == pytest.approx(1.0)
        source.follow(str(new_region.name))
        old_region.close()
        assert _tcp_x(source, 10**9) == pytest.approx(2.0)
        source.follow("/hil-no-such-ring")            # gone already: the current ring stays
        assert _tcp_x(source, 10**9) == pytest.approx(2.0)
        third_region, _ = ring_at(3.0)
        try:
            source.follow("/hil-no-such-ring")        # two restarts before the next pose: the last
            source.follow(str(third_region.name))
            assert _tcp_x(source, 10**9) == pytest.approx(3.0)
        finally:
            source.close()
            third_region.close()
    finally:
        source.close()
        new_region.close()
