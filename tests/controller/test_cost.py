"""The pair path's cost histogram (hil/controller/cost.py): fixed size, exact bin edges."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from hil.controller.cost import COST_BINS, CostHistogram


def test_empty_histogram_has_no_figures() -> None:
    f = CostHistogram().figures()
    assert f.to_dict() == {"count": 0, "p50_us": None, "p99_us": None, "max_us": None}


def test_percentiles_are_the_upper_edge_of_their_bin_capped_at_the_maximum() -> None:
    h = CostHistogram()
    for us in range(1, 101):          # 1 .. 100 µs, each 0.5 µs into its bin
        h.add_ns(us * 1000 + 500)
    f = h.figures()
    assert f.count == 100
    assert f.p50_us == 51.0           # the 50th step (50.5 µs) is in bin [50, 51)
    assert f.p99_us == 100.0          # the 99th (99.5 µs) is in bin [99, 100)
    assert f.max_us == 100.5


def test_longer_than_the_range_counts_in_the_last_bin_and_keeps_its_maximum() -> None:
    h = CostHistogram()
    h.add_ns(25_000_000)              # 25 ms
    h.add_ns(-5)                      # a clock step backwards counts as 0
    f = h.figures()
    assert f.count == 2
    assert f.p50_us == 1.0
    assert f.max_us == 25_000.0
    assert f.p99_us == 25_000.0       # in the last bin (10 ms and over): the maximum
    assert len(h._bins) == COST_BINS  # never grows


@given(st.lists(st.integers(min_value=0, max_value=20_000_000), min_size=1, max_size=200))
def test_a_percentile_is_never_below_the_true_one_nor_above_it_by_more_than_a_bin(ns: list[int]) -> None:
    h = CostHistogram()
    for d in ns:
        h.add_ns(d)
    f = h.figures()
    s = sorted(ns)
    for q, got in ((0.5, f.p50_us), (0.99, f.p99_us)):
        true_us = s[math.ceil(q * len(s)) - 1] / 1000.0   # the ceil(q n)-th smallest
        assert got is not None
        assert got >= true_us - 1e-9
        if true_us < 10_000.0 - 1.0:
            assert got <= true_us + 1.0
        else:
            assert got <= max(ns) / 1000.0
    assert f.max_us == round(max(ns) / 1000.0, 3)
