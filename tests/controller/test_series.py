"""A run's sample series (hil/controller/series.py): exact up to its capacity (as a plain array),
a uniform reservoir beyond with the count, extremes, last and RMS still exact, paired series stay
paired, and its memory is taken once."""

from __future__ import annotations

import math
from array import array

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.controller.metrics import percentile
from hil.controller.series import SampleSeries

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)


@given(st.lists(finite, max_size=300))
def test_within_capacity_it_is_exactly_the_array(values: list[float]) -> None:
    s, a = SampleSeries(capacity=300), array("d")
    for v in values:
        s.append(v)
        a.append(v)
    assert len(s) == len(a)
    assert bool(s) == bool(a)
    assert s.exact
    assert list(s) == list(a)
    assert percentile(s, 95) == percentile(a, 95)
    if a:
        assert s.rms == float(np.sqrt(np.mean(np.square(a))))   # bit for bit
        assert s.max == max(a)
        assert s.min == min(a)
        assert s.last == a[-1]
    else:
        assert (s.rms, s.max, s.min, s.last) == (None, None, None, None)


def test_beyond_capacity_it_holds_a_uniform_sample_and_exact_extremes() -> None:
    s = SampleSeries(capacity=1000)
    n = 100_000
    for k in range(n):
        s.append(float(k))
    assert len(s) == n
    assert not s.exact
    held = s.held()
    assert len(held) == 1000
    assert len(set(held.tolist())) == 1000      # each sample at most once
    assert s.max == n - 1
    assert s.min == 0.0
    assert s.last == n - 1
    assert s.rms == pytest.approx(math.sqrt(sum(k * k for k in range(n)) / n), rel=1e-12)
    # uniform over the whole run: the held median is near the run's, the p95 too
    assert abs(percentile(s, 50) - n / 2) < 0.05 * n
    assert abs(percentile(s, 95) - 0.95 * n) < 0.03 * n


def test_series_appended_in_lockstep_stay_paired() -> None:
    errors, ages = SampleSeries(capacity=64), SampleSeries(capacity=64)
    for k in range(10_000):
        errors.append(float(k))
        ages.append(float(k) * 0.5)
    assert (ages.held() * 2.0 == errors.held()).all()


def test_memory_is_taken_once_and_resident_from_the_start() -> None:
    s = SampleSeries(capacity=4096)
    buf = s._buf
    assert np.isnan(buf).all()          # written (resident) at construction
    for k in range(50_000):
        s.append(float(k))
    assert s._buf is buf                # never reallocated
    assert s._buf.nbytes == 4096 * 8


def test_the_held_view_is_read_only_and_bad_capacity_is_refused() -> None:
    s = SampleSeries(capacity=4)
    s.append(1.0)
    with pytest.raises(ValueError, match="read-only"):
        s.held()[0] = 2.0
    with pytest.raises(ValueError, match="capacity must be > 0"):
        SampleSeries(capacity=0)
