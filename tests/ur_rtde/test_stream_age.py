"""The age of the RTDE stream's newest sample (drivers/ur_rtde/stream_age.py): exact cases and the
clamp as a property."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.ur_rtde.stream_age import StreamAge


def test_a_stall_is_aged_from_when_the_sample_arrived_not_when_it_was_first_read() -> None:
    a = StreamAge()
    # 125 Hz stream, controller clock = host clock - 100 s, 1 ms transport delay; read every 66 ms
    assert a.observe(1.000, 101.001) == pytest.approx(0.0)
    # the stream stops after the sample stamped 1.060 (arrived at 101.061); first read at 101.066
    assert a.observe(1.060, 101.066) == pytest.approx(0.005, abs=5e-5)  # 200 ppm drift allowance
    # one second later the old rule ("first seen 101.066") said 1.000 s; the sample is 1.005 s old
    assert a.observe(1.060, 102.066) == pytest.approx(1.005, abs=5e-5)


def test_a_lagging_controller_clock_cannot_inflate_the_age() -> None:
    a = StreamAge()
    a.observe(1.000, 101.001)  # offset 100.001
    a.observe(1.008, 101.009)
    assert a.observe(1.010, 101.020) == pytest.approx(0.009, abs=5e-5)  # arrived 1 ms after its stamp, +8 ms
    # the controller (an emulator on a loaded host) paused 0.5 s and does not catch up: its clock
    # now lags the host by 0.5 s for good; the offset estimate would say every sample is 0.5 s old
    a.observe(1.018, 101.527)
    # ...but the previous sample was current at 101.527: this one is at most 8 ms old
    assert a.observe(1.026, 101.535) == pytest.approx(0.008, abs=1e-9)


def test_a_restarted_controller_starts_afresh() -> None:
    a = StreamAge()
    a.observe(500.0, 1000.0)
    assert a.observe(0.5, 1000.1) == pytest.approx(0.0)
    assert a.observe(0.5, 1001.1) == pytest.approx(1.0)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(1e-6, 0.05), st.floats(0.0, 0.2), st.booleans()), min_size=2,
                max_size=60),
       st.floats(-1e3, 1e3))
def test_the_age_lies_between_what_the_observations_prove(
    steps: list[tuple[float, float, bool]], offset_s: float,
) -> None:
    """Whatever the delays and the clock offset: first-seen age <= age <= since the previous
    sample was last seen, and never negative."""
    a = StreamAge()
    ts, host = 10.0, 10.0 + offset_s
    first_seen = host
    prev_seen: float | None = None
    last_obs = host
    a.observe(ts, host)
    for dt_ts, dt_host, new in steps:
        host += dt_host
        if new and dt_ts > 0:
            prev_seen, first_seen = last_obs, host
            ts += dt_ts
        age = a.observe(ts, host)
        last_obs = host
        low = host - first_seen
        high = host - prev_seen if prev_seen is not None else low
        assert low - 1e-9 <= age <= high + 1e-9
        assert age >= -1e-9
