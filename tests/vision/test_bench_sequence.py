"""The vision benchmark's sequence runner: several passes, the fastest reported, results checked
equal across passes (tools/benchmarks/vision_sequence.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools" / "benchmarks"))
from vision_sequence import ModeTally, _same_every_pass, run_sequence, scaled_rig


def test_a_sequence_runs_every_pass_and_reports_the_fastest() -> None:
    r = run_sequence(scaled_rig(1280), 4, 8, 2.0, 7, passes=3)
    for mode in ("track", "full"):
        tally: ModeTally = r[mode]
        assert len(tally.pass_pairs_per_s) == 3
        assert len(tally.times) == 8
        assert tally.pairs_per_s() == pytest.approx(max(tally.pass_pairs_per_s), rel=1e-12)
        assert min(tally.pass_pairs_per_s) <= tally.median_pass_pairs_per_s() <= tally.pairs_per_s()
    # scored once, from the first pass: 4 markers in 8 pairs (marker 0 hidden in 2), none missed
    # by the full-frame search
    assert len(r["track"].err3d) + r["track"].missed == len(r["full"].err3d) + r["full"].missed
    assert r["full"].missed == 0


def test_add_pass_keeps_the_fastest_pass() -> None:
    t = ModeTally()
    t.add_pass([0.002, 0.002])
    t.add_pass([0.001, 0.001])
    t.add_pass([0.004, 0.004])
    assert t.times == [0.001, 0.001]
    assert t.pass_pairs_per_s == [500.0, 1000.0, 250.0]
    assert t.median_pass_pairs_per_s() == 500.0


def test_a_pass_with_other_points_stops_the_benchmark() -> None:
    first: dict[str, list[np.ndarray]] = {}
    a = [np.zeros((2, 3)), np.ones((1, 3))]
    _same_every_pass("tracking", 0, a, first)
    _same_every_pass("tracking", 1, [x.copy() for x in a], first)
    with pytest.raises(RuntimeError, match="tracking: pass 3 located other points than pass 1 in pair 1"):
        _same_every_pass("tracking", 2, [a[0], np.ones((2, 3))], first)
