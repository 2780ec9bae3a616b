"""Loop figures from two copies of the statistics: exact on a known interval stream."""

from __future__ import annotations

from hil.servo.figures import StatsCopy, loop_figures
from hil.servo.shm import LoopStats, ShmRegion, Stat, stats_words


def test_figures_of_a_known_window() -> None:
    stats = LoopStats(ShmRegion.local(stats_words()))
    period_ns = 2_000_000
    for _ in range(50):                       # warm-up, left out of the window
        stats.add_interval(9_000_000, period_ns)
    before = StatsCopy.of(stats)
    for iv in [2_000_000] * 97 + [2_100_000, 4_500_000, 30_000_000]:   # 100 intervals
        stats.add_interval(iv, period_ns)
    stats.c[Stat.COMMANDS] += 100
    stats.add_latency(41_230_000)
    stats.add_latency(60_000_000)
    figs = loop_figures(before, StatsCopy.of(stats), 0.002)
    assert figs.intervals == 100
    assert figs.commands == 100
    assert figs.late == 2                      # 4.5 ms and 30 ms are over two periods
    assert figs.late_fraction == 0.02
    assert figs.longest_ms == 30.0             # the overflow bin: the loop's own maximum
    assert figs.period_ms == {"p50": 2.005, "p99": 4.505, "max": 19.995}   # bin centres
    assert figs.jitter_ms == {"p50": 0.005, "p99": 2.505, "max": 17.995}
    assert figs.latency_ms == {"p50": 41.25, "p99": 60.05, "max": 60.05}


def test_an_empty_window_has_no_figures() -> None:
    stats = LoopStats(ShmRegion.local(stats_words()))
    c = StatsCopy.of(stats)
    figs = loop_figures(c, c, 0.008)
    assert figs.intervals == 0
    assert figs.longest_ms is None
    assert figs.period_ms == {"p50": None, "p99": None, "max": None}


def test_one_stats_record_per_second_of_controller_time() -> None:
    from hil.servo.figures import StatsEverySecond

    stats = LoopStats(ShmRegion.local(stats_words()))
    every = StatsEverySecond(lambda: stats)
    assert every.due(0) is None                 # the first call starts the window
    stats.c[Stat.PERIODS] += 125
    stats.c[Stat.COMMANDS] += 120
    stats.add_interval(17_000_000, 8_000_000)   # one late interval
    stats.c[Stat.FOLLOWING_PEAK_UM] = 412
    assert every.due(999_999_999) is None       # not a second yet
    rec = every.due(1_000_000_000)
    assert rec == {"periods": 125, "commands": 120, "late": 1, "stale_periods": 0, "refusals": 0,
                   "read_errors": 0, "command_errors": 0, "following_faults": 0, "late_wakes": 0,
                   "overruns": 0, "overruns_off_cpu": 0, "following_peak_mm": 0.412,
                   "longest_interval_ms": 17.0}
    assert every.due(1_500_000_000) is None
    stats.c[Stat.FOLLOWING_FAULTS] += 1
    stats.c[Stat.LATE_WAKES] += 2
    assert every.due(2_000_000_000) == {"periods": 0, "commands": 0, "late": 0, "stale_periods": 0,
                                        "refusals": 0, "read_errors": 0, "command_errors": 0,
                                        "following_faults": 1, "late_wakes": 2, "overruns": 0,
                                        "overruns_off_cpu": 0,
                                        "following_peak_mm": 0.412,
                                        "longest_interval_ms": 17.0}


def test_the_real_time_host_counts_where_a_late_period_came_from() -> None:
    from hil.servo.process import _count_late_causes

    stats = LoopStats(ShmRegion.local(stats_words()))
    c, period_ns = stats.c, 2_000_000
    _count_late_causes(c, 5_000, 600_000, -1_400_000, period_ns, 590_000)        # on time
    _count_late_causes(c, 2_000_001, 700_000, 700_001, period_ns, 690_000)       # woke 2 ms late
    _count_late_causes(c, 10_000, 4_100_000, 2_100_000, period_ns, 4_000_000)    # ran 4.1 ms on its CPU
    _count_late_causes(c, 20_000, 4_600_000, 2_620_000, period_ns, 600_000)      # 4.0 ms off its CPU
    _count_late_causes(c, 10_000, 4_000_000, 2_010_000, period_ns, 2_000_000)    # exactly a period off
    _count_late_causes(c, 2_000_000, 500_000, 0, period_ns, 500_000)             # exactly a period: not late
    zero = StatsCopy.of(LoopStats(ShmRegion.local(stats_words())))
    figs = loop_figures(zero, StatsCopy.of(stats), 0.002)
    assert (figs.late_wakes, figs.overruns, figs.overruns_off_cpu) == (1, 3, 1)
    assert (figs.wake_late_max_ms, figs.step_max_ms, figs.overrun_max_ms) == (2.0, 4.6, 2.62)
    assert (figs.step_cpu_max_ms, figs.step_off_cpu_max_ms) == (4.0, 4.0)
