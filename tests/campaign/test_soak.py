"""The soak: its figures from known loop figures (exact), the host's steal, and a short real-time
soak.

Documented bounds of the short soak (docs/benchmarks.md), counts only, no timing value asserted:

- The servo loop runs in its own process (hil/servo) and never waits for a camera, the session log
  or the supervisor. Intervals over two servo periods, counted over the windows in which the host
  took none of the loop's CPU (hil/soak/host.py): at most 0.5 % when the OS granted SCHED_FIFO and
  a pinned CPU (as root: what CI runs), at most 5 % otherwise. Counted over the whole run, the
  late share follows the hypervisor's steal (0.2 % late at 1 % steal, 12 % at 43 %, on this
  project's VM): that test failed about one CI run in five.
- Memory of either process must not grow by more than 5 MB after the warm-up (measured: < 0.1 MB).
"""

from __future__ import annotations

import io
import json
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.cli.cmd_soak import _latency_bound, _print_memory
from hil.config import default_setup_path, load_setup
from hil.controller.cost import CostHistogram, PairCosts
from hil.controller.series import SampleSeries
from hil.errors import InputFileError
from hil.heap import HeapTrimmer
from hil.servo.figures import LoopFigures
from hil.soak.attribution import fault_outcomes, unexplained_faults
from hil.soak.host import (
    StealFreeFigures,
    StealFreeLate,
    StealSample,
    parse_steal_s,
    sample_steal,
    steal_percent,
)
from hil.soak.soak import (
    LATE_FRACTION_BOUND,
    LATE_FRACTION_BOUND_RT,
    TRANSIENT_FAULTS,
    SoakOperator,
    SoakResult,
    analyse,
    latency_bound,
    rss_by_minute,
    run_soak,
    soak_setup,
    transient_schedule,
)

RSS_GROWTH_BOUND_MB = 5.0


def test_analyse_maps_the_loop_figures_and_memory() -> None:
    figs = LoopFigures(periods=1000, commands=990, intervals=999, late=2, late_fraction=0.002002,
                       longest_ms=30.0, period_ms={"p50": 2.005, "p99": 2.015, "max": 30.0},
                       jitter_ms={"p50": 0.005, "p99": 0.015, "max": 28.0},
                       latency_ms={"p50": 41.25, "p99": 60.05, "max": 60.05}, refusals=1, stale_periods=7,
                       read_errors=0, command_errors=0, stops_sent=0, late_wakes=1, overruns=1,
                       wake_late_max_ms=26.0, step_max_ms=3.5, overrun_max_ms=2.5, overruns_off_cpu=1,
                       step_cpu_max_ms=0.9, step_off_cpu_max_ms=2.6)
    cost, pair = CostHistogram(), CostHistogram()
    for ns in (12_300, 15_000, 80_200):
        cost.add_ns(ns)
    for ns in (52_100, 60_000):
        pair.add_ns(ns)
    heap = HeapTrimmer(1.0, trim=lambda: 1)
    for t_ns in (0, 1_000_000_000, 2_500_000_000):
        heap.after_tick(t_ns)
    latency = SampleSeries()
    for ms in (30.0, 40.0, 50.0):
        latency.append(ms)
    ctl = SimpleNamespace(latency_ms=latency, servo_deadlines_missed=0, frames_overwritten=4,
                          pair_costs=PairCosts(cost.figures(), CostHistogram().figures(), pair.figures()),
                          heap=heap)
    op = SoakOperator(60.0, 60.0, lambda: None)
    op.t_comp = 0.0
    rss = [(0.0, 100.0, 500.0), (10.0, 100.5, 500.0), (20.0, 101.0, 500.0), (30.0, 101.0, 500.2),
           (40.0, 101.5, 500.2)]
    res = analyse(500.0, 1.0, figs, ctl, op, rss, "compensate", [], [], "x")  # type: ignore[arg-type]
    assert res.servo_commands == 990
    assert res.limit_violations == 1           # refused by the loop's check, never sent
    assert res.intervals == 999
    assert res.missed_deadlines == 2
    assert res.missed_fraction == 0.002002
    assert res.longest_gap_ms == 30.0
    assert res.late_causes == {"woke_late": 1, "overran": 1, "overran_off_cpu": 1,
                               "longest_wake_delay_ms": 26.0, "longest_step_ms": 3.5,
                               "longest_step_cpu_ms": 0.9, "longest_off_cpu_ms": 2.6,
                               "longest_overrun_ms": 2.5}
    assert res.jitter_ms == figs.jitter_ms
    assert res.frame_to_command_ms == figs.latency_ms
    assert res.stale_periods == 7
    assert res.compensation_frames == 3
    assert res.setpoint_us == {"count": 3, "p50_us": 16.0, "p99_us": 80.2, "max_us": 80.2}
    assert res.change_fit_us == {"count": 0, "p50_us": None, "p99_us": None, "max_us": None}
    assert res.pair_model_us == {"count": 2, "p50_us": 53.0, "p99_us": 60.0, "max_us": 60.0}
    assert res.heap_trim["trims"] == 2
    assert res.heap_trim["released"] == 2
    assert res.frames_overwritten == 4
    assert res.rss_mb["after_warmup"] == 101.0  # warm-up: min(30 s, a quarter of 1 min) = 15 s
    # windows of min(60 s, a quarter of 1 min) = 15 s: medians of [20, 35) and (25, 40]
    assert res.rss_mb["window_s"] == 15.0
    assert res.rss_mb["growth"] == 0.25         # median(101, 101.5) - median(101, 101)
    assert res.rss_mb["end"] - res.rss_mb["after_warmup"] == 0.5
    assert res.servo_rss_mb["growth"] == 0.1     # median(500.2, 500.2) - median(500, 500.2)
    assert res.rss_mb_by_minute == [100.0]      # the samples span 40 s: only minute 0


def test_the_latency_bound_is_camera_plus_locate_plus_one_servo_period_plus_the_hand_over() -> None:
    """Issue 45: camera p50 + locate p50 + one servo period + 2 ms (p99: + 10 ms): at 500 Hz the
    period is 2 ms, at 125 Hz 8 ms (the room the robot's own period needs)."""
    cam, loc = {"p50": 30.5, "p99": 41.0}, {"p50": 1.5, "p95": 3.0}
    assert latency_bound(cam, loc, 2.0) == {"p50": 36.0, "p99": 46.0}
    assert latency_bound(cam, loc, 8.0) == {"p50": 42.0, "p99": 52.0}
    assert latency_bound({}, {"p50": 1.5}, 2.0) == {}
    assert latency_bound({"p50": None, "p99": None}, {"p50": 1.5}, 2.0) == {}
    res = SoakResult(500.0, 1.0, frame_to_command_ms={"p50": 35.9, "p99": 47.0, "max": 60.0},
                     camera_latency_ms={"p50": 30.5, "p99": 41.0}, locate_ms={"p50": 1.5, "p95": 3.0},
                     latency_bound_ms={"p50": 36.0, "p99": 46.0})
    assert _latency_bound(res) == ("p50 36.00 ms (camera p50 30.50 + locate p50 1.50 + period 2 + 2): "
                                   "within; p99 46.00 ms (+ 10): OVER; camera p99 41.00 ms")
    res = SoakResult(125.0, 1.0, frame_to_command_ms={"p50": 36.25, "p99": 40.55, "max": 60.0},
                     camera_latency_ms={"p50": 28.0, "p99": 41.0}, locate_ms={"p50": 1.43, "p95": 3.0},
                     latency_bound_ms={"p50": 39.43, "p99": 49.43})
    assert _latency_bound(res) == ("p50 39.43 ms (camera p50 28.00 + locate p50 1.43 + period 8 + 2): "
                                   "within; p99 49.43 ms (+ 10): within; camera p99 41.00 ms")
    assert _latency_bound(SoakResult(500.0, 1.0)).startswith("n/a (the camera's latency is measured in")


def test_bench_loop_reports_the_bound_beside_frame_to_command() -> None:
    """tools/bench loop's JSON carries the soak's bound and what it is made of."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools" / "benchmarks"))
    try:
        from bench_loop import figures
    finally:
        sys.path.pop(0)
    res = SoakResult(125.0, 1.0, frame_to_command_ms={"p50": 36.25, "p99": 40.55, "max": 60.0},
                     camera_latency_ms={"p50": 28.0, "p99": 41.0}, locate_ms={"p50": 1.43, "p95": 3.0},
                     latency_bound_ms=latency_bound({"p50": 28.0, "p99": 41.0}, {"p50": 1.43}, 8.0))
    out = figures(res, 60.0)
    assert out["period_ms"] == 8.0
    assert out["latency_bound_ms"] == {"p50": 39.43, "p99": 49.43}
    assert out["camera_latency_ms"] == {"p50": 28.0, "p99": 41.0}
    assert out["locate_ms"] == {"p50": 1.43, "p95": 3.0}
    assert out["frame_to_command_ms"] == {"p50": 36.25, "p99": 40.55, "max": 60.0}


def test_memory_growth_reads_through_the_heap_trims_saw_tooth() -> None:
    """RSS once a second over 10 min: a floor of 200 MB with a 12 MB tooth for 5 s after each
    trim period (allocations the next trim gives back): no growth; the same with the floor 0.8 MB
    higher in the last minutes: that growth."""
    def series(rise_mb: float) -> list[tuple[float, float, float]]:
        out = []
        for t in range(600):
            tooth = 12.0 if t % 60 < 5 else 0.0
            floor = 200.0 + (rise_mb if t >= 480 else 0.0)
            out.append((float(t), floor + tooth, 500.0))
        return out

    op = SoakOperator(600.0, 60.0, lambda: None)
    op.t_comp = 0.0
    figs = LoopFigures(periods=1, commands=1, intervals=1, late=0, late_fraction=0.0, longest_ms=2.0,
                       period_ms={}, jitter_ms={}, latency_ms={}, refusals=0, stale_periods=0,
                       read_errors=0, command_errors=0, stops_sent=0, late_wakes=0, overruns=0,
                       wake_late_max_ms=0.0, step_max_ms=0.0, overrun_max_ms=0.0, overruns_off_cpu=0,
                       step_cpu_max_ms=0.0, step_off_cpu_max_ms=0.0)
    ctl = SimpleNamespace(latency_ms=SampleSeries(), servo_deadlines_missed=0, frames_overwritten=0,
                          pair_costs=PairCosts(*(CostHistogram().figures() for _ in range(3))),
                          heap=HeapTrimmer(0.0))
    flat = analyse(500.0, 10.0, figs, ctl, op, series(0.0), "compensate", [], [], "x")  # type: ignore[arg-type]
    assert flat.rss_mb["after_warmup"] == 200.0
    assert flat.rss_mb["growth"] == 0.0
    risen = analyse(500.0, 10.0, figs, ctl, op, series(0.8), "compensate", [], [], "x")  # type: ignore[arg-type]
    assert risen.rss_mb["growth"] == 0.8


def test_rss_by_minute_takes_the_first_sample_of_each_whole_minute() -> None:
    rss = [(5.0, 90.0), (10.0, 100.0), (69.9, 101.0), (70.0, 102.0), (131.0, 103.456), (140.0, 104.0)]
    assert rss_by_minute(rss, t_comp=10.0) == [100.0, 102.0, 103.46]
    assert rss_by_minute(rss, t_comp=None) == [90.0, 101.0, 103.46]
    assert rss_by_minute([], t_comp=3.0) == []


def test_bad_arguments_are_typed_errors(tmp_path: Path) -> None:
    from hil.errors import InputFileError

    with pytest.raises(InputFileError, match="--rate"):
        run_soak(0.1, 200.0, config=default_setup_path(), plan=None, session_dir=tmp_path)
    with pytest.raises(InputFileError, match="--minutes"):
        run_soak(0.0, 125.0, config=default_setup_path(), plan=None, session_dir=tmp_path)


@pytest.fixture(scope="module")
def short_soak(tmp_path_factory: pytest.TempPathFactory) -> Any:
    return run_soak(
        10 / 60, 500.0, config=default_setup_path(), plan=None, session_dir=tmp_path_factory.mktemp("soak")
    )


def test_short_soak_compensates_with_the_servo_loop(short_soak: Any) -> None:
    res = short_soak
    assert res.compensate_s >= 10.0
    assert res.final_state != "done"            # it stayed in the procedure
    assert res.compensation_frames >= 10 * 3    # pairs processed in compensation (15 Hz nominal)
    assert res.camera_clock_ppm == 50.0           # the soak's default: a free-running camera
    assert res.intervals >= 10 * 500 // 2       # the loop ran at its rate, not at the camera's
    assert res.servo_commands >= res.compensation_frames
    assert res.limit_violations == 0
    assert res.rt_granted.get("requested") is True
    assert res.perception_process is False      # the default: located in the supervisor
    assert res.servo_cpu_percent is not None
    assert 0.0 < res.servo_cpu_percent <= 105.0
    assert "rt_cpu_cap" in res.rt_granted       # the kernel's cap on a FIFO loop's CPU share
    assert res.locate_ms["p50"] is not None
    # both parts of frame -> command are measured. Their medians are not compared: the setpoints
    # (every pair handed to the loop) and the commands (pairs whose setpoint a period picked up;
    # frames_overwritten are not among them) are different populations, so on a loaded host the
    # setpoints' median can exceed the commands' though each command follows its own setpoint
    f2s, f2c = res.frame_to_setpoint_ms["p50"], res.frame_to_command_ms["p50"]
    assert f2s is not None
    assert f2c is not None
    assert f2s > 0.0
    assert f2c > 0.0
    # the setpoint's own work is timed for every pair that published one (alpha-beta: the filter's)
    assert res.predictor == "alpha-beta"
    assert res.setpoint_us["count"] == res.compensation_frames
    assert 0.0 < res.setpoint_us["p50_us"] <= res.setpoint_us["p99_us"] <= res.setpoint_us["max_us"]
    # the supervisor gave its free heap back every 10 s of the run (hil/heap.py; glibc here)
    assert res.heap_trim["trims"] >= 1
    # the change estimator is timed on every registered pair (compensation and before it)
    assert res.estimator == "rigid"
    assert res.change_fit_us["count"] >= res.compensation_frames
    # and each compensation pair's estimate and setpoint added (a pair whose change was not its
    # own, held from an earlier pair, is not counted)
    assert 0 < res.pair_model_us["count"] <= res.setpoint_us["count"]
    assert res.setpoint_us["p50_us"] < res.pair_model_us["p50_us"] <= res.pair_model_us["max_us"]


#: further 10 s soaks (about 60 s of wall time each on a busy host) tried when the host took the
#: loop's CPU in nearly every window of one: its steal comes in bursts (29-38 % for a whole 10 s
#: soak, 4.6 % in the 10 s after)
QUIET_SPELL_TRIES = 1


def _compensated(res: Any) -> bool:
    """Whether the soak streamed at all (a soak the host starved into camera faults before
    COMPENSATE has no intervals, no windows and no late causes: it says nothing of the loop)."""
    return bool(res.intervals > 0 and res.steal_free and res.late_causes)


def _judgeable(res: Any) -> bool:
    """Whether the windows in which the host took none of the loop's CPU hold a tenth of the run."""
    return _compensated(res) and bool(res.steal_free["intervals"] >= res.intervals // 10)


@pytest.mark.timeout(240)   # one more soak (~60 s on a busy host) when the first was not judgeable
def test_short_soak_late_periods_within_bound(short_soak: Any, tmp_path: Path) -> None:
    """The documented bound on late intervals, judged on what the loop and the guest's kernel did,
    not the hypervisor: over the windows in which the host took none of the loop's CPU
    (hil/soak/host.py), when those hold a tenth of the run at least. When the host took the CPU in
    nearly every window (29-32 % steal on the loop's CPU in CI runs), that share is not
    observable: nothing meets the bound then, not even fixed work with none of our code
    (`tools/bench host`: 293-365 late in 10,000 at 19-24 % steal), and the loop's CPU clock is
    stretched with it. The test then soaks again, up to :data:`QUIET_SPELL_TRIES` times, for a
    quieter spell of the host; the loop's own on-CPU overruns (``overran - overran_off_cpu``,
    hil/servo/process.py) within the bound also pass. Only when neither shows, the run is skipped
    with the figures: the bound cannot be judged on this host now."""
    res = short_soak
    assert res.rt_granted["realtime"] is True          # CI runs as root: FIFO and a pinned CPU
    assert res.late_fraction_bound() == LATE_FRACTION_BOUND_RT
    assert _compensated(res), "the soak never streamed in COMPENSATE"
    tried = [res]
    while not _judgeable(res) and len(tried) <= QUIET_SPELL_TRIES:
        res = run_soak(10 / 60, 500.0, config=default_setup_path(), plan=None,
                       session_dir=tmp_path / f"try{len(tried)}")
        tried.append(res)
    bound = LATE_FRACTION_BOUND_RT
    if _judgeable(res):
        assert res.steal_free["late_fraction"] <= bound, res.steal_free
        return
    streamed = [r for r in tried if _compensated(r)]   # the first did (asserted above)
    own = [r.late_causes["overran"] - r.late_causes["overran_off_cpu"] for r in streamed]
    if min(o / r.intervals for o, r in zip(own, streamed, strict=True)) <= bound:
        return
    pytest.skip(
        f"the host took the servo loop's CPU in nearly every window of {len(tried)} soaks (steal on it "
        f"{[r.host_steal_percent.get('loop_cpu') for r in tried]} %; on-CPU overruns {own} of "
        f"{[r.intervals for r in streamed]}; {len(tried) - len(streamed)} never reached COMPENSATE): the "
        f"{100 * bound:g} % late bound cannot be judged on this host now (hil soak "
        "--probe-host shows what the machine alone does)")


def test_short_soak_reports_the_hosts_steal(short_soak: Any) -> None:
    res = short_soak
    assert set(res.host_steal_percent) == {"loop_cpu", "all_cpus"}
    assert all(0.0 <= v <= 100.0 for v in res.host_steal_percent.values())
    assert 0 <= res.steal_free["late"] <= res.missed_deadlines
    assert res.steal_free["intervals"] <= res.intervals
    assert res.missed_fraction == round(res.missed_deadlines / res.intervals, 6)
    assert SoakResult(125.0, 1.0).late_fraction_bound() == LATE_FRACTION_BOUND   # nothing granted


def test_short_soak_says_where_late_periods_came_from(short_soak: Any) -> None:
    """The servo process timed every period after its warm-up, on the wall clock and on its
    thread's CPU clock (hil/servo/process.py ``_count_late_causes``)."""
    lc = short_soak.late_causes
    assert set(lc) == {"woke_late", "overran", "overran_off_cpu", "longest_wake_delay_ms", "longest_step_ms",
                       "longest_step_cpu_ms", "longest_off_cpu_ms", "longest_overrun_ms"}
    assert 0 <= lc["overran_off_cpu"] <= lc["overran"]
    assert 0.0 < lc["longest_step_cpu_ms"] <= lc["longest_step_ms"] + 0.01   # clocks read microseconds apart
    assert 0.0 <= lc["longest_off_cpu_ms"] <= lc["longest_step_ms"]


STAT = """cpu  32067 0 1883 64097 201 0 280 1127 0 0
cpu0 16000 0 900 32000 100 0 140 500 0 0
cpu1 16067 0 983 32097 101 0 140 627 0 0
intr 123 0
"""


def test_steal_is_read_per_cpu_from_proc_stat(tmp_path: Path) -> None:
    import os

    ticks_per_s = os.sysconf("SC_CLK_TCK")
    assert parse_steal_s(STAT, None) == 1127 / ticks_per_s
    assert parse_steal_s(STAT, 1) == 627 / ticks_per_s
    with pytest.raises(ValueError, match="no line 'cpu2'"):
        parse_steal_s(STAT, 2)
    with pytest.raises(ValueError, match="no steal value"):
        parse_steal_s("cpu0 1 2 3 4 5 6 7\n", 0)
    path = tmp_path / "stat"
    path.write_text(STAT)
    got = sample_steal(1, path)
    assert got is not None
    assert (got.cpu, got.steal_s) == (1, 627 / ticks_per_s)
    assert sample_steal(1, tmp_path / "missing") is None       # not Linux: no figure, not a wrong one
    assert sample_steal(7, path) is None


@given(st.lists(st.integers(0, 2**48), min_size=8, max_size=10), st.integers(0, 255))
def test_steal_is_the_eighth_value_of_a_cpus_line(values: list[int], cpu: int) -> None:
    import os

    other = [v + 1 for v in values]
    text = (f"cpu  {' '.join(map(str, other))}\ncpu{cpu}0 {' '.join(map(str, other))}\n"
            f"cpu{cpu} {' '.join(map(str, values))}\nctxt 5\n")
    assert parse_steal_s(text, cpu) == values[7] / os.sysconf("SC_CLK_TCK")
    assert parse_steal_s(text, None) == other[7] / os.sysconf("SC_CLK_TCK")


def test_steal_percent_is_of_the_wall_time_between_samples() -> None:
    assert steal_percent(StealSample(1, 10.0, 2.0), StealSample(1, 20.0, 4.5)) == 25.0
    assert steal_percent(StealSample(None, 10.0, 2.0), StealSample(None, 20.0, 4.5), n_cpus=2) == 12.5
    assert steal_percent(StealSample(1, 10.0, 2.0), StealSample(1, 10.0, 2.0)) is None
    with pytest.raises(ValueError, match="different CPUs"):
        steal_percent(StealSample(0, 10.0, 2.0), StealSample(1, 20.0, 2.0))


def test_short_soak_does_not_grow(short_soak: Any) -> None:
    for rss in (short_soak.rss_mb, short_soak.servo_rss_mb):
        assert rss["growth"] is not None
        assert rss["growth"] <= RSS_GROWTH_BOUND_MB


def test_transient_faults_are_scheduled_every_period_after_the_warm_up() -> None:
    sched = transient_schedule(3.0, 45.0)
    assert [(f.kind.value, f.start_s, f.duration_s) for f in sched] == [
        ("frame_drop", 60.0, 0.6), ("robot_disconnect", 105.0, 0.6), ("protective_stop", 150.0, 0.6)]
    assert transient_schedule(3.0, 0.0) == ()
    assert [f.kind for f in transient_schedule(60.0, 300.0)][:6] == [k for k, _ in TRANSIENT_FAULTS] + [
        TRANSIENT_FAULTS[0][0]]


def test_each_injected_fault_is_matched_to_what_the_controller_said(tmp_path: Path) -> None:
    t0 = 10**9
    def fault(t_s: float, reason: str) -> dict[str, Any]:
        return {"event": "fault_detected", "reason": reason, "t_ns": t0 + round(t_s * 1e9)}

    def comp(t_s: float) -> dict[str, Any]:
        return {"event": "state_entered", "state": "compensate", "t_ns": t0 + round(t_s * 1e9)}

    rec = [comp(30.0),
           fault(59.7, "watchdog: robot state 0.06 s old > 0.05 s"),   # within the slack, not naming it
           fault(60.1, "camera: no stereo pair within 0.04 s"),
           fault(60.4, "watchdog: camera data 0.3 s old > 0.25 s"),    # the same drop, its watchdog
           comp(63.0),
           fault(105.05, "robot: RTDE connection lost (injected)"),
           fault(140.0, "robot: still not connected"),                  # never back: explained
           fault(151.7, "robot: protective stop"),                      # 0.1 s after 150 + 0.6 + 1 s
           comp(160.0)]
    log = tmp_path / "s.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in rec))
    schedule = transient_schedule(4.0, 45.0)
    out = fault_outcomes(schedule, str(log), t0)
    assert out == [
        {"kind": "frame_drop", "onset_s": 60.0, "duration_s": 0.6,
         "detected": "camera: no stereo pair within 0.04 s", "back_in_compensation_s": 3.0,
         "reasons": ["watchdog: robot state 0.06 s old > 0.05 s", "camera: no stereo pair within 0.04 s",
                     "watchdog: camera data 0.3 s old > 0.25 s"]},
        {"kind": "robot_disconnect", "onset_s": 105.0, "duration_s": 0.6,
         "detected": "robot: RTDE connection lost (injected)", "back_in_compensation_s": None,
         "reasons": ["robot: RTDE connection lost (injected)", "robot: still not connected"]},
        {"kind": "protective_stop", "onset_s": 150.0, "duration_s": 0.6, "detected": "tolerated",
         "back_in_compensation_s": None, "reasons": []},
        {"kind": "occlusion", "onset_s": 195.0, "duration_s": 1.0, "detected": "tolerated",
         "back_in_compensation_s": None, "reasons": []}]
    # detected no later than a second after its window: the protective stop at 151.7 s is not its
    assert unexplained_faults(schedule, str(log), t0) == ["robot: protective stop"]
    assert unexplained_faults((), str(log), t0) == [str(r["reason"]) for r in rec if "reason" in r]
    # the perception process opened its camera 2.5 s after the robot: the camera's faults count from
    # then, so records from 59.7 to 60.4 s come a second too early for the frame drop at 62.5 s
    late = fault_outcomes(schedule, str(log), t0, {"camera": t0 + 2_500_000_000})
    assert late[0]["detected"] == "tolerated"
    assert late[1]["detected"] == "robot: RTDE connection lost (injected)"
    assert unexplained_faults(schedule, str(log), t0, {"camera": t0 + 2_500_000_000})[:3] == [
        "watchdog: robot state 0.06 s old > 0.05 s", "camera: no stereo pair within 0.04 s",
        "watchdog: camera data 0.3 s old > 0.25 s"]
    res = SoakResult(500.0, 4.0, compensate_s=200.0, transient_faults=out)
    assert res.passed() is False   # it never came back from the disconnect
    out[1]["back_in_compensation_s"] = 8.0
    assert res.passed() is True    # two reasons for one frame drop are not a failure
    res.unexplained_faults = ["robot: protective stop"]
    assert res.passed() is False
    with pytest.raises(InputFileError, match="--faults-every"):
        run_soak(1.0, 125.0, config=default_setup_path(), plan=None, session_dir=tmp_path, faults_every_s=5.0)


def test_the_soak_operator_registers_again_when_the_gate_stays_shut(monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.controller.fsm import Event, State
    from hil.controller.operator_input import OperatorView

    now = [100.0]
    monkeypatch.setattr("hil.soak.soak.time", SimpleNamespace(monotonic=lambda: now[0],
                                                              monotonic_ns=lambda: round(now[0] * 1e9)))
    op = SoakOperator(600.0, 60.0, lambda: None, reregister_after_s=30.0)

    def poll(state: State, t_s: float) -> Event | None:
        now[0] = 100.0 + t_s
        return op.poll(OperatorView(state=state, pending=None, last_reason="", t_s=t_s, started=True))

    assert poll(State.IDLE, 0.0) is Event.START_REQUESTED
    assert poll(State.GATE, 1.0) is None
    assert poll(State.GATE, 30.9) is None                  # 29.9 s shut
    assert poll(State.GATE, 31.0) is Event.PAUSE_REQUESTED  # 30 s shut: pause to register again
    assert op.reregistrations == 1
    assert poll(State.PAUSED, 31.1) is None                # let the robot stop
    assert poll(State.PAUSED, 31.7) is Event.START_REQUESTED   # PAUSED -> REGISTER, not a resume
    assert op.resumes == 0
    assert poll(State.GATE, 40.0) is None                  # a new stay in GATE counts from its start
    assert poll(State.COMPENSATE, 41.0) is None
    assert poll(State.GATE, 42.0) is None
    assert poll(State.GATE, 71.9) is None
    assert poll(State.PAUSED, 72.0) is None                # paused by something else: a plain resume
    assert poll(State.PAUSED, 72.6) is Event.RESUME_REQUESTED
    assert (op.reregistrations, op.resumes) == (1, 1)
    assert poll(State.GATE, 80.0) is None
    assert poll(State.GATE, 110.0) is Event.PAUSE_REQUESTED
    assert poll(State.COMPENSATE, 110.1) is None           # the gate opened before the pause landed
    assert poll(State.PAUSED, 120.0) is None
    assert poll(State.PAUSED, 120.6) is Event.RESUME_REQUESTED   # a later pause is resumed
    assert (op.reregistrations, op.resumes) == (2, 2)


def test_late_intervals_count_only_where_the_host_left_the_loops_cpu_alone(tmp_path: Path) -> None:
    path = tmp_path / "stat"
    counts = [0, 0]          # the loop's cumulative (late, intervals)

    def window(steal_ticks: int, late: int, intervals: int) -> None:
        path.write_text(f"cpu  1 0 1 1 0 0 0 {steal_ticks} 0 0\ncpu1 1 0 1 1 0 0 0 {steal_ticks} 0 0\n")
        counts[0] += late
        counts[1] += intervals
        free.sample()

    free = StealFreeLate(1, lambda: (counts[0], counts[1]), window_s=0.0, stat_path=path)
    window(100, 0, 0)
    free.start()
    window(100, 1, 50)       # 0: clean
    window(100, 0, 50)       # 1: clean
    window(100, 4, 50)       # 2: next to the steal: left out (the late intervals it caused)
    window(102, 0, 50)       # 3: steal
    window(102, 0, 50)       # 4: next to the steal
    window(102, 2, 50)       # 5: clean
    assert free.figures() == StealFreeFigures(intervals=150, late=3, late_fraction=0.02, windows=7,
                                              clean_windows=4)   # 0, 1, 5 and the empty one figures() closed
    assert StealFreeLate(None, lambda: (0, 0), stat_path=tmp_path / "missing").figures() == \
        StealFreeFigures(0, 0, 0.0, 0, 0)   # no /proc/stat: no windows, no figure


def test_the_soaks_camera_clock_is_off_the_hosts_unless_told(tmp_path: Path) -> None:
    """50 ppm by default (a free-running camera's pairs sweep the servo periods' phase), the
    setup's own rate error when it has one, exactly what ``camera_clock_ppm`` says (0: the host's
    clock); a value the config refuses is an InputFileError naming the option."""
    from hil.soak.soak import SOAK_CAMERA_CLOCK_PPM

    def ppm(setup: Any) -> float:
        return float(setup.simulation.rig_errors.camera_clock_rate_error_ppm)

    base = load_setup(default_setup_path())
    assert ppm(base) == 0.0
    assert SOAK_CAMERA_CLOCK_PPM == 50.0
    assert ppm(soak_setup(base, 500.0, 1.0)) == 50.0
    assert ppm(soak_setup(base, 500.0, 1.0, camera_clock_ppm=0.0)) == 0.0
    assert ppm(soak_setup(base, 500.0, 1.0, camera_clock_ppm=-20.0)) == -20.0
    errors = base.simulation.rig_errors.model_copy(update={"camera_clock_rate_error_ppm": 12.5})
    own = base.model_copy(update={"simulation": base.simulation.model_copy(update={"rig_errors": errors})})
    assert ppm(soak_setup(own, 500.0, 1.0)) == 12.5
    with pytest.raises(InputFileError, match="--camera-clock-ppm"):
        soak_setup(base, 500.0, 1.0, camera_clock_ppm=5000.0)
    with pytest.raises(InputFileError, match="--camera-clock-ppm"):
        run_soak(0.1, 500.0, config=default_setup_path(), plan=None, session_dir=tmp_path,
                 camera_clock_ppm=float("nan"))


@pytest.mark.parametrize(("perception_process", "mode"), [(False, "off"), (True, "on")])
def test_soak_setup_asks_for_the_perception_process_on_any_machine(
        perception_process: bool, mode: str) -> None:
    """``--perception-process`` is "on", not "auto" (which needs 2 CPUs): the soak runs it where
    it was asked for; the servo loop always has its own process, on the wall clock."""
    setup = soak_setup(load_setup(default_setup_path()), 500.0, 1.0, perception_process=perception_process)
    assert setup.perception.process == mode
    assert setup.servo.process == "on"
    assert setup.simulation.real_time is True
    assert setup.robot.control_rate_hz == 500.0


def test_the_text_output_s_memory_lines() -> None:
    """``hil soak``'s memory lines: the trims, the cycle collections and each process's RSS, with
    the perception process's only when it ran."""
    res = SoakResult(rate_hz=500.0, minutes=60.0)
    res.heap_trim = {"trims": 358, "released": 357, "max_ms": 0.83, "collections": 358, "collected": 550,
                     "collect_max_ms": 0.72, "frozen_objects": 90958}
    res.rss_mb = {"after_warmup": 233.21, "end": 234.8, "growth": 2.04, "slope_mb_per_min": 0.0186}
    res.servo_rss_mb = {"after_warmup": 519.79, "end": 519.79, "growth": 0.0, "slope_mb_per_min": 0.0}
    out = io.StringIO()
    _print_memory(out, res)
    assert out.getvalue().splitlines() == [
        "heap trims           358 (357 gave memory back; longest 0.83 ms; [procedure] heap_trim_every_s)",
        "cycle collections    358 (550 objects freed; longest 0.72 ms; 90958 start-up objects frozen)",
        "memory supervisor    233.21 -> 234.8 MB, growth 2.04 MB, slope 0.0186 MB/min",
        "memory servo proc.   519.79 -> 519.79 MB, growth 0.0 MB, slope 0.0 MB/min",
    ]
    res.perception_rss_mb = {"after_warmup": 300.0, "end": 300.5, "growth": 0.5, "slope_mb_per_min": 0.01}
    out = io.StringIO()
    _print_memory(out, res)
    assert out.getvalue().splitlines()[-1] == ("memory perception    300.0 -> 300.5 MB, growth 0.5 MB, "
                                               "slope 0.01 MB/min")
    res.file_rss_growth = [{"file": "/usr/lib/libpython3.11.so.1.0", "kb": 1536, "first_grew_min": 4.9},
                           {"file": "/venv/cv2/cv2.abi3.so", "kb": 512, "first_grew_min": 4.9}]
    out = io.StringIO()
    _print_memory(out, res)
    assert out.getvalue().splitlines()[-1] == ("file pages grown     libpython3.11.so.1.0 +1536 kB "
                                               "(minute 4.9), cv2.abi3.so +512 kB (minute 4.9)")
