"""Property tests of the session-log reader: any JSON lines give SessionData or a typed
InputFileError naming the file and the line — never another exception."""

from __future__ import annotations

import json
import re
import tempfile
from pathlib import Path
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from hil.console.app import gate_windows
from hil.errors import InputFileError
from hil.report.plots import PLOTS
from hil.report.session_data import load_session

EVENTS = ["session_started", "state_entered", "transition_applied", "fault_detected", "registration_done",
          "gate_measured", "compensation_step", "lock_measured", "approach_measured", "truth_error",
          "command_sent", "robot_state", "markers_measured", "session_closed", "something_new"]
FIELDS = ["state", "reason", "fre_mm", "tre_expected_mm", "robot_fre_mm", "markers", "reference_optical_mm",
          "residuals_mm", "deviation_rms_mm", "open", "guide_error_mm", "gate_deviation_mm", "position_mm",
          "direction_deg", "speed_mm_s", "tcp_speed_mm_s", "marker_residuals_mm", "live_mm", "procedure",
          "transition", "source", "target"]
scalars = st.one_of(st.none(), st.booleans(), st.integers(-10, 10), st.floats(-1e3, 1e3), st.text(max_size=5))
values: st.SearchStrategy[Any] = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.sampled_from(FIELDS), inner, max_size=3),
    max_leaves=12)
records = st.fixed_dictionaries(
    {"t_ns": st.one_of(st.integers(0, 10**10), st.none(), st.text(max_size=3)),
     "event": st.one_of(st.sampled_from(EVENTS), st.none(), st.integers())},
    optional=dict.fromkeys(FIELDS, values))


@settings(max_examples=150)
@given(st.lists(records, min_size=1, max_size=8))
def test_any_records_load_or_raise_a_typed_error(recs: list[dict[str, Any]]) -> None:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "s.jsonl"
        path.write_text("".join(json.dumps(r) + "\n" for r in recs))
        error: InputFileError | None = None
        try:
            data = load_session(path)
        except InputFileError as exc:
            error = exc
        if error is not None:
            assert error.path == str(path)
            m = re.match(r"line (\d+): ", error.reason)
            assert m is not None, error.reason
            assert 1 <= int(m.group(1)) <= len(recs)
            return
        assert data.records == len(recs)
        assert data.duration_s >= 0.0
        total = sum(data.time_in_state_s().values())
        assert abs(total - data.duration_s) < 1e-6
        for _key, fn in PLOTS[:1]:  # rendering every plot per example is slow; the timeline covers states
            assert fn(data).png.startswith(b"\x89PNG")


def test_gate_windows_colours_buckets_by_their_maximum() -> None:
    t = gate_windows((0.5, 0.6, 2.0, 0.4, 3.0, 3.0), 1.5, 3)
    assert t.plain == "▀▀▀"
    assert [str(s.style) for s in t.spans] == ["green", "red", "red"]
    assert gate_windows((), 1.5, 10).plain.startswith("no breathing data")
