"""The soak: its figures from a synthetic servo record (exact), and a short real-time soak.

Documented bounds of the short soak (docs/benchmarks.md), counts only, no timing value asserted:

- On the wall clock the controller grabs and locates the next stereo pair in its prefetch thread
  (hil/controller/prefetch.py) and keeps streaming servo commands until the pair is ready, so a
  frame no longer leaves a gap in the stream. Before that change one interval per frame was over
  two periods (the grab + detection on the control thread, ~40-60 ms): 12.5-16 % of the 125 Hz
  intervals. With it we measured 0.3-1.5 % at 125 Hz on this shared 2-core machine with a load
  average of 0.3 to 3 (other engineers' test runs): the rest is the OS and the GIL handing the
  CPU to the other thread late. MISSED_FRACTION_BOUND = 5 % is ~3x the worst of those and still
  well below what the old once-per-frame pause gives, so the test fails if the pause comes back.
- The property itself, counted where it happens: the servo intervals that span the start of a
  control tick (a new pair taken) may be over two periods for at most a quarter of those
  boundaries (the old design: all of them; measured now: 0.02-0.05, with a load average of 4).
- Memory must not grow by more than 20 MB after the warm-up.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from hil.campaign.recorder import CommandRecord, Recording
from hil.config import default_setup_path
from hil.soak.soak import SoakOperator, analyse, run_soak

MISSED_FRACTION_BOUND = 0.05
#: missed deadlines per frame processed in COMPENSATE, at most (the old design: ~1)
MISSED_PER_FRAME_BOUND = 0.25
RSS_GROWTH_BOUND_MB = 20.0


def _servo(t_ms: float) -> CommandRecord:
    return CommandRecord(round(t_ms * 1e6), "servo", (0.0, 0.0, 0.0), 1.0, None, ())


def test_analyse_on_a_known_stream() -> None:
    # 125 Hz: four commands 8 ms apart, one 9 ms late, then a 40 ms gap (a frame being processed),
    # then 8 ms again; a 2 s pause (not compensating) is not counted as an interval
    times = [0, 8, 16, 24, 33, 73, 81, 2081, 2089]
    rec = SimpleNamespace(servo_t_ns=[_servo(t).t_ns for t in times], recording=Recording())
    ctl = SimpleNamespace(frame_period_s=1 / 15, latency_ms=[30.0, 40.0, 50.0], servo_deadlines_missed=2,
                          frames_overwritten=4)
    op = SoakOperator(60.0, 60.0, lambda: None)
    rss = [(0.0, 100.0), (10.0, 100.5), (20.0, 101.0), (30.0, 101.0), (40.0, 101.5)]
    op.t_comp = 0.0
    # control ticks: inside a short interval, inside the 40 ms gap, inside the pause
    op.tick_ns.extend([round(28e6), round(50e6), round(1000e6)])
    res = analyse(125.0, 1.0, rec, ctl, op, rss, "compensate", [], [], "x")  # type: ignore[arg-type]
    assert res.servo_commands == 9
    assert res.limit_violations == 0
    assert res.intervals == 7  # the 2000 ms pause is dropped
    assert res.missed_deadlines == 1  # the 40 ms gap
    assert res.stream_deadlines_missed == 2  # the controller's own count, reported as is
    assert res.longest_gap_ms == 40.0
    assert res.frame_boundaries == 2  # the 24-33 and 33-73 intervals; the pause is not an interval
    assert res.frame_boundary_missed == 1  # the 40 ms gap
    assert res.frame_boundary_ms == {"p50": 24.5, "p99": 39.69, "max": 40.0}
    assert res.period_ms == {"p50": 8.0, "p99": 8.95, "max": 9.0}
    assert res.jitter_ms["max"] == 1.0
    assert res.frame_to_command_ms == {"p50": 40.0, "p99": 49.8, "max": 50.0}
    assert res.compensation_frames == 3  # one compensation step per frame
    assert res.frames_overwritten == 4
    assert res.rss_mb["after_warmup"] == 101.0  # warm-up: min(30 s, a quarter of 1 min) = 15 s
    assert res.rss_mb["growth"] == 0.5


def test_bad_arguments_are_typed_errors(tmp_path: Path) -> None:
    from hil.errors import InputFileError

    with pytest.raises(InputFileError, match="--rate"):
        run_soak(0.1, 200.0, config=default_setup_path(), plan=None, session_dir=tmp_path)
    with pytest.raises(InputFileError, match="--minutes"):
        run_soak(0.0, 125.0, config=default_setup_path(), plan=None, session_dir=tmp_path)


@pytest.fixture(scope="module")
def short_soak(tmp_path_factory: pytest.TempPathFactory) -> Any:
    return run_soak(
        10 / 60, 125.0, config=default_setup_path(), plan=None, session_dir=tmp_path_factory.mktemp("soak")
    )


def test_short_soak_compensates_and_streams(short_soak: Any) -> None:
    res = short_soak
    assert res.compensate_s >= 10.0
    assert res.servo_commands >= 10 * 15  # at least one servo command per frame
    assert res.final_state != "done"  # it stayed in the procedure


def test_short_soak_missed_deadlines_within_bound(short_soak: Any) -> None:
    assert short_soak.missed_fraction <= MISSED_FRACTION_BOUND


def test_short_soak_streams_across_frame_boundaries(short_soak: Any) -> None:
    """The stream goes on while the next pair is grabbed and located: most frame boundaries
    leave no interval over two servo periods (counts from the recorder and the controller)."""
    res = short_soak
    assert res.compensation_frames >= 10 * 3   # frames were processed in compensation (15 Hz nominal)
    assert res.frame_boundaries >= res.compensation_frames // 2
    assert res.frame_boundary_missed <= MISSED_PER_FRAME_BOUND * res.frame_boundaries


def test_short_soak_does_not_grow(short_soak: Any) -> None:
    assert short_soak.rss_mb["growth"] is not None
    assert short_soak.rss_mb["growth"] <= RSS_GROWTH_BOUND_MB
