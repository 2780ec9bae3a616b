"""drivers.ur_rtde.packet.one_packet: fields read between two equal controller timestamps come from
one state packet. The library is modelled as what it guarantees (a packet replaces every field at
once; each getter returns one field of the packet current at its call); packets arrive between
any two getter calls, as the receive thread's do."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from drivers.ur_rtde.packet import READ_TRIES, one_packet


class Stream:
    """Packet k has timestamp 0.002 * k and every field equal to k; ``arrivals`` are the getter
    call numbers before which a new packet arrives."""

    def __init__(self, arrivals: set[int]) -> None:
        self.arrivals = arrivals
        self.calls = 0
        self.packet = 0

    def _tick(self) -> None:
        if self.calls in self.arrivals:
            self.packet += 1
        self.calls += 1

    def timestamp(self) -> float:
        self._tick()
        return 0.002 * self.packet

    def field(self) -> int:
        self._tick()
        return self.packet

    def three_fields(self) -> tuple[int, int, int]:
        return self.field(), self.field(), self.field()


def test_a_quiet_stream_is_read_once() -> None:
    s = Stream(set())
    assert one_packet(s.timestamp, s.three_fields) == (0.0, (0, 0, 0))
    assert s.calls == 5   # timestamp, three fields, timestamp


def test_a_packet_arriving_between_two_getters_is_read_again() -> None:
    s = Stream({2})   # after the first field: the "safety normal, script stopped" tear
    assert one_packet(s.timestamp, s.three_fields) == (0.002, (1, 1, 1))
    assert s.calls == 10


def test_a_packet_arriving_during_every_try_gives_none() -> None:
    s = Stream({5 * k + 2 for k in range(READ_TRIES)})
    assert one_packet(s.timestamp, s.three_fields) is None
    assert s.calls == 5 * READ_TRIES


@given(st.sets(st.integers(min_value=0, max_value=5 * READ_TRIES)))
def test_the_fields_always_come_from_the_packet_of_the_returned_timestamp(arrivals: set[int]) -> None:
    s = Stream(arrivals)
    got = one_packet(s.timestamp, s.three_fields)
    if got is None:   # only when a packet arrived inside every try's getters
        assert all(any(5 * k + 1 <= a <= 5 * k + 4 for a in arrivals) for k in range(READ_TRIES))
        return
    ts, fields = got
    assert fields == (round(ts / 0.002),) * 3
