"""hil.io.traces: hypothesis properties — points-csv round trip, exact resampling of a linear signal,
strictly increasing time accepted and any non-increase refused at its line."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.io.traces import Trace, TraceError, read_trace, resample

_NAMES = st.lists(st.from_regex(r"[A-Za-z0-9_-]{1,8}", fullmatch=True), min_size=1, max_size=4,
                  unique_by=str.lower)
_STEPS = st.lists(st.floats(min_value=1e-3, max_value=2.0), min_size=2, max_size=40)
_COORD = st.floats(min_value=-500.0, max_value=500.0, allow_nan=False)


def _tmp_file(text: str, name: str) -> tuple[tempfile.TemporaryDirectory[str], str]:
    d = tempfile.TemporaryDirectory()
    p = Path(d.name) / name
    p.write_text(text)
    return d, str(p)


@given(names=_NAMES, steps=_STEPS, data=st.data())
def test_points_csv_round_trip(names: list[str], steps: list[float], data: st.DataObject) -> None:
    time_s = np.cumsum([0.0, *steps])
    n = time_s.size
    pts = {name: np.asarray(data.draw(st.lists(st.tuples(_COORD, _COORD, _COORD), min_size=n, max_size=n)))
           for name in names}
    header = ",".join(["time_s", *(f"{m}_{a}_mm" for m in names for a in "xyz")])
    rows = [",".join([repr(float(time_s[i])), *(repr(float(v)) for m in names for v in pts[m][i])])
            for i in range(n)]
    d, path = _tmp_file("\n".join([header, *rows]) + "\n", "rec.csv")
    with d:
        tr = read_trace(path, min_duration_s=0.0, min_samples=2)
    assert tr.format == "points-csv"
    assert list(tr.points_mm) == names
    np.testing.assert_array_equal(tr.time_s, time_s)
    for name in names:
        np.testing.assert_array_equal(tr.points_mm[name], pts[name])


@given(steps=_STEPS, a=_COORD, b=st.floats(-50.0, 50.0), rate_hz=st.floats(0.5, 200.0))
def test_resample_of_linear_signal_is_exact(steps: list[float], a: float, b: float, rate_hz: float) -> None:
    time_s = np.cumsum([3.0, *steps])
    line = a + b * time_s
    target = np.column_stack([line, -line, 2 * line])
    tr = Trace("mem", "paired", time_s, {"p": target.copy()}, None, line.copy(), target, None, {"time": "s"})
    n = int(np.floor(tr.duration_s * rate_hz + 1e-9)) + 1
    if n < 2:
        return
    out = resample(tr, rate_hz, min_samples=2)
    assert out.time_s.size == n
    assert out.time_s[0] == time_s[0]
    assert out.time_s[-1] <= time_s[-1] + 1e-9
    np.testing.assert_allclose(np.diff(out.time_s), 1.0 / rate_hz, rtol=1e-9, atol=1e-9)
    expected = a + b * out.time_s
    scale = 1e-9 * (abs(a) + abs(b) * float(time_s[-1]) + 1.0)
    assert out.surrogate is not None
    assert out.target_mm is not None
    np.testing.assert_allclose(out.surrogate, expected, rtol=0, atol=scale)
    np.testing.assert_allclose(out.target_mm[:, 2], 2 * expected, rtol=0, atol=2 * scale)
    np.testing.assert_allclose(out.points_mm["p"][:, 1], -expected, rtol=0, atol=scale)


@given(deltas=st.lists(st.integers(-3, 8), min_size=1, max_size=30))
def test_time_must_strictly_increase(deltas: list[int]) -> None:
    t = [float(v) for v in np.cumsum([0.0, *(0.1 * k for k in deltas)])]
    d, path = _tmp_file("\n".join(f"{v!r} 1.0" for v in t), "s.txt")
    bad = next((i for i in range(1, len(t)) if t[i] <= t[i - 1]), None)
    with d:
        if bad is not None:
            with pytest.raises(TraceError) as e:
                read_trace(path, min_duration_s=0.0, min_samples=2)
            assert e.value.line == bad + 1
            what = "repeats" if t[bad] == t[bad - 1] else "goes back from"
            assert e.value.reason == f"time {t[bad]:g} s {what} the previous sample's {t[bad - 1]:g} s"
            return
        tr = read_trace(path, min_duration_s=0.0, min_samples=2)
    np.testing.assert_array_equal(tr.time_s, t)
    assert np.all(np.diff(tr.time_s) > 0)
