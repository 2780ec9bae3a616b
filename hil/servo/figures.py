"""Figures of the servo loop over a window: from two copies of its statistics (start and end of
the window), so a soak leaves its warm-up out without touching the loop's own counters.

Definitions (the loop's own clock readings, each period's wake-up time):

- *interval*: time between two consecutive periods' wake-ups; nominal ``T`` = the robot's period.
- *jitter*: ``|interval - T|``; its percentiles come from the 10 µs interval histogram (a value is
  the centre of its bin, so figures are good to ±5 µs).
- *late*: intervals over ``2 T`` (a period passed without the loop running).
- *latency*: a stereo pair's exposure -> the driver took the first servo command the loop
  computed from the setpoint of that pair (0.1 ms bins; the following supervision after it is not
  counted).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from hil.servo.shm import INTERVAL_BIN_NS, LATENCY_BIN_NS, LoopStats, Stat


@dataclass(frozen=True)
class StatsCopy:
    """A copy of the loop statistics at one moment."""

    counters: tuple[int, ...]
    interval_hist: Any   # np.ndarray (int64)
    latency_hist: Any

    @classmethod
    def of(cls, stats: LoopStats) -> StatsCopy:
        return cls(tuple(int(x) for x in stats.c), stats.interval_hist.copy(), stats.latency_hist.copy())

    def get(self, stat: Stat) -> int:
        return self.counters[stat]


@dataclass(frozen=True)
class LoopFigures:
    """What the loop did in a window (module doc). Durations in ms, rounded to the µs."""

    periods: int
    commands: int
    intervals: int
    late: int
    late_fraction: float
    longest_ms: float | None
    period_ms: dict[str, float | None]
    jitter_ms: dict[str, float | None]
    latency_ms: dict[str, float | None]
    refusals: int
    stale_periods: int
    read_errors: int
    command_errors: int
    stops_sent: int
    following_faults: int = 0
    #: the largest following error (hil.safety.following) seen since the counters were reset, mm
    following_peak_mm: float = 0.0
    #: where late periods came from (the real-time host's words, hil/servo/shm.py ``Stat``):
    #: periods woken more than a period after their deadline, periods whose work ran more than a
    #: period past the next deadline (both in the window); the longest wake-up delay, step and
    #: overrun, ms (maxima since the loop's warm-up, not of the window); the overruns during whose
    #: work the loop thread was off its CPU for more than a period (the host or the OS took it, or
    #: a driver call blocked),
    #: and the longest step in the thread's own CPU time and off its CPU, ms
    late_wakes: int = 0
    overruns: int = 0
    overruns_off_cpu: int = 0
    #: periods the setpoint block was being written for the whole read (the loop went on with its
    #: last copy; hil/servo/shm.py), in the window
    setpoint_busy: int = 0
    wake_late_max_ms: float = 0.0
    step_max_ms: float = 0.0
    overrun_max_ms: float = 0.0
    step_cpu_max_ms: float = 0.0
    step_off_cpu_max_ms: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _weighted_stats(values_ms: Any, counts: Any) -> dict[str, float | None]:
    total = int(counts.sum())
    if total == 0:
        return {"p50": None, "p99": None, "max": None}
    order = np.argsort(values_ms, kind="stable")
    v, c = values_ms[order], np.cumsum(counts[order])

    def pct(q: float) -> float:
        k = int(np.searchsorted(c, q / 100.0 * total, side="left"))
        return round(float(v[min(k, v.size - 1)]), 3)

    nz = counts[order] > 0
    return {"p50": pct(50), "p99": pct(99), "max": round(float(v[nz].max()), 3)}


def loop_figures(before: StatsCopy, after: StatsCopy, period_s: float) -> LoopFigures:
    """The figures of the window between two copies (module doc)."""
    d = [a - b for a, b in zip(after.counters, before.counters, strict=True)]
    hist = after.interval_hist - before.interval_hist
    lat = after.latency_hist - before.latency_hist
    centres_ms = (np.arange(hist.size) + 0.5) * INTERVAL_BIN_NS * 1e-6
    period_ms = period_s * 1e3
    intervals = int(hist.sum())
    top = int(np.nonzero(hist)[0].max()) if intervals else -1
    longest: float | None = None
    if top == hist.size - 1:   # the overflow bin: the loop's own maximum is the best figure
        longest = after.get(Stat.MAX_INTERVAL_NS) * 1e-6
    elif top >= 0:
        longest = (top + 1) * INTERVAL_BIN_NS * 1e-6
    period_stats = _weighted_stats(centres_ms, hist)
    jitter_stats = _weighted_stats(np.abs(centres_ms - period_ms), hist)
    lat_centres = (np.arange(lat.size) + 0.5) * LATENCY_BIN_NS * 1e-6
    late = d[Stat.LATE]
    return LoopFigures(
        periods=d[Stat.PERIODS], commands=d[Stat.COMMANDS], intervals=intervals, late=late,
        late_fraction=round(late / intervals, 6) if intervals else 0.0,
        longest_ms=None if longest is None else round(longest, 3),
        period_ms=period_stats, jitter_ms=jitter_stats, latency_ms=_weighted_stats(lat_centres, lat),
        refusals=d[Stat.REFUSALS], stale_periods=d[Stat.STALE], read_errors=d[Stat.READ_ERRORS],
        command_errors=d[Stat.COMMAND_ERRORS], stops_sent=d[Stat.STOPS_SENT],
        following_faults=d[Stat.FOLLOWING_FAULTS], following_peak_mm=after.get(Stat.FOLLOWING_PEAK_UM) * 1e-3,
        late_wakes=d[Stat.LATE_WAKES], overruns=d[Stat.OVERRUNS], setpoint_busy=d[Stat.SETPOINT_BUSY],
        wake_late_max_ms=round(after.get(Stat.WAKE_LATE_MAX_NS) * 1e-6, 3),
        step_max_ms=round(after.get(Stat.STEP_NS_MAX) * 1e-6, 3),
        overrun_max_ms=round(after.get(Stat.WORST_OVERRUN_NS) * 1e-6, 3),
        overruns_off_cpu=d[Stat.OVERRUNS_OFF_CPU],
        step_cpu_max_ms=round(after.get(Stat.STEP_CPU_NS_MAX) * 1e-6, 3),
        step_off_cpu_max_ms=round(after.get(Stat.STEP_OFF_CPU_NS_MAX) * 1e-6, 3))


class StatsEverySecond:
    """The loop's counters as one aggregated session-log record per second of controller time
    (``servo_stats``): the audit trail of the periods without a record per period.

    :meth:`due` returns the record's fields when a second has passed since the last one (else
    None): periods, commands, late, stale periods, refusals, read / command errors, following
    faults, and the late periods' causes (woken late, overran, of those overruns the ones with the
    loop off its CPU for more than a period) in that second; the following peak
    and the longest interval so far (ms).
    """

    def __init__(self, stats: Callable[[], LoopStats], every_s: float = 1.0) -> None:
        self.stats = stats   # read when due: the servo process creates its regions when it starts
        self.every_ns = round(every_s * 1e9)
        self._last: tuple[int, ...] | None = None
        self._last_ns: int | None = None

    def due(self, now_ns: int) -> dict[str, Any] | None:
        if self._last_ns is not None and now_ns - self._last_ns < self.every_ns:
            return None
        c = tuple(int(x) for x in self.stats().c)
        prev, self._last, first = self._last, c, self._last_ns is None
        self._last_ns = now_ns
        if first or prev is None:
            return None

        def d(stat: Stat) -> int:
            return c[stat] - prev[stat]
        return {"periods": d(Stat.PERIODS), "commands": d(Stat.COMMANDS), "late": d(Stat.LATE),
                "stale_periods": d(Stat.STALE), "refusals": d(Stat.REFUSALS),
                "read_errors": d(Stat.READ_ERRORS), "command_errors": d(Stat.COMMAND_ERRORS),
                "following_faults": d(Stat.FOLLOWING_FAULTS), "late_wakes": d(Stat.LATE_WAKES),
                "overruns": d(Stat.OVERRUNS), "overruns_off_cpu": d(Stat.OVERRUNS_OFF_CPU),
                "following_peak_mm": round(c[Stat.FOLLOWING_PEAK_UM] * 1e-3, 3),
                "longest_interval_ms": round(c[Stat.MAX_INTERVAL_NS] * 1e-6, 3)}
