"""What the host took from a CPU: *steal* time, from Linux's ``/proc/stat``.

On a virtual machine the hypervisor runs other guests on the physical CPU behind a virtual one;
the time a runnable virtual CPU waited for it is that CPU's *steal* (the eighth value of its
``cpuN`` line, in ``USER_HZ`` ticks). No priority inside the guest reaches it: a SCHED_FIFO loop on
a CPU the host takes away for 10 ms misses five 2 ms periods. The soak reports the steal of the
loop's CPU over its compensation window (``host_steal_percent``) beside the late periods, so a run
on a busy host is told apart from a loop that misses its deadlines by itself. Measured on this
project's 2-core VM (docs/benchmarks.md): 10 s soaks at 500 Hz with 0.01-0.06 s of steal on the
loop's CPU missed 0-3 periods; with 0.8-5.9 s of steal, 41-193.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

PROC_STAT = Path("/proc/stat")
#: index of the steal value among a ``cpuN`` line's numbers (user nice system idle iowait irq
#: softirq steal ...)
_STEAL_FIELD = 7


@dataclass(frozen=True)
class StealSample:
    """The steal counter of one CPU (``cpu`` None: all CPUs summed) at a monotonic time."""

    cpu: int | None
    t_s: float
    steal_s: float


def parse_steal_s(stat_text: str, cpu: int | None) -> float:
    """The steal time of ``cpu`` (None: the ``cpu`` line summing all CPUs) in ``/proc/stat`` text,
    s.

    Raises:
        ValueError: no line for that CPU, or a line too short to carry steal (a kernel before
            2.6.11), or a value that is not a count.
    """
    label = "cpu" if cpu is None else f"cpu{cpu}"
    for line in stat_text.splitlines():
        parts = line.split()
        if parts and parts[0] == label:
            if len(parts) <= _STEAL_FIELD + 1:
                raise ValueError(f"/proc/stat line {label!r} has no steal value: {line!r}")
            return int(parts[_STEAL_FIELD + 1]) / os.sysconf("SC_CLK_TCK")
    raise ValueError(f"/proc/stat has no line {label!r}")


def sample_steal(cpu: int | None, path: Path = PROC_STAT) -> StealSample | None:
    """The steal counter of ``cpu`` now; None where ``/proc/stat`` cannot be read or parsed (not
    Linux): the soak then reports no steal figure rather than a wrong one."""
    try:
        return StealSample(cpu, time.monotonic(), parse_steal_s(path.read_text(), cpu))
    except (OSError, ValueError):
        return None


def steal_percent(start: StealSample, end: StealSample, n_cpus: int = 1) -> float | None:
    """Steal between two samples of the same CPU, % of the wall time between them (of ``n_cpus``
    times it: the mean over the CPUs summed by the ``cpu`` line), rounded to 0.1 % (the counter's
    own resolution is one tick, 10 ms); None when no time passed.

    Raises:
        ValueError: samples of different CPUs.
    """
    if start.cpu != end.cpu:
        raise ValueError(f"steal samples of different CPUs: {start.cpu} and {end.cpu}")
    elapsed_s = end.t_s - start.t_s
    if elapsed_s <= 0:
        return None
    return round(100.0 * (end.steal_s - start.steal_s) / (elapsed_s * n_cpus), 1)


#: How often the soak reads the loop CPU's steal and the loop's counters together, s: short enough
#: to keep most of a run when the host takes the CPU now and then, long enough for the 10 ms steal
#: counter to resolve
STEAL_WINDOW_S = 0.1


@dataclass(frozen=True)
class StealFreeFigures:
    """Late intervals over the windows the host left the loop's CPU alone (:class:`StealFreeLate`).

    Attributes:
        intervals, late: the loop's intervals and late intervals (> two periods) in those windows.
        late_fraction: ``late / intervals`` rounded to 1e-6 (0 without intervals).
        windows: windows read; ``clean_windows``: those counted (no steal in it or its neighbours).
    """

    intervals: int
    late: int
    late_fraction: float
    windows: int
    clean_windows: int


class StealFreeLate:
    """Counts the servo loop's late intervals only over windows in which the host took none of the
    loop's CPU: what the loop and the guest's kernel did, without the hypervisor's share.

    Every :data:`STEAL_WINDOW_S` (:meth:`sample`, called as often as convenient; not a thread) it
    reads the loop CPU's steal counter and the loop's (late, intervals) counters. A window counts
    when neither it nor its neighbours saw steal: the loop records a late interval when it runs
    again, the guest books the steal at its next tick on that CPU, and the two can fall either side
    of a window's edge. Steal shorter than the counter's 10 ms tick can go unseen; a window
    stretched by a busy reader only gets longer.
    """

    def __init__(self, cpu: int | None, read_counts: Callable[[], tuple[int, int]],
                 window_s: float = STEAL_WINDOW_S, stat_path: Path = PROC_STAT) -> None:
        """``cpu``: the loop's CPU (None: not pinned, any CPU's steal counts); ``read_counts``
        returns the loop's cumulative (late, intervals) counters. Memory stays constant however
        long the run: a window is settled when the next one closes."""
        self.cpu, self.read_counts, self.window_s, self.stat_path = cpu, read_counts, window_s, stat_path
        self._last: tuple[StealSample, int, int] | None = None
        self._reset()

    def _reset(self) -> None:
        #: the last closed window, not settled until its successor closes: (late, intervals, stolen)
        self._pending: tuple[int, int, bool] | None = None
        self._before_pending_stolen = False
        self._windows = self._clean_windows = self._late = self._intervals = 0

    def start(self) -> None:
        """Begin counting now (the soak: when compensation first starts)."""
        self._last = None
        self._reset()
        self._read()

    def sample(self) -> None:
        """Close the current window when it is :data:`STEAL_WINDOW_S` old (else nothing)."""
        if self._last is not None and time.monotonic() - self._last[0].t_s >= self.window_s:
            self._read()

    def _read(self) -> None:
        steal = sample_steal(self.cpu, self.stat_path)
        if steal is None:
            return
        late, intervals = self.read_counts()
        if self._last is not None:
            s0, late0, intervals0 = self._last
            self._close((late - late0, intervals - intervals0, steal.steal_s > s0.steal_s))
        self._last = (steal, late, intervals)

    def _close(self, window: tuple[int, int, bool]) -> None:
        self._windows += 1
        if self._pending is not None:
            if not (self._before_pending_stolen or self._pending[2] or window[2]):
                self._count(self._pending)
            self._before_pending_stolen = self._pending[2]
        self._pending = window

    def _count(self, window: tuple[int, int, bool]) -> None:
        self._clean_windows += 1
        self._late += window[0]
        self._intervals += window[1]

    def figures(self) -> StealFreeFigures:
        """The counts so far, closing the current window first (the last one has no successor:
        it counts when neither it nor its predecessor saw steal)."""
        self._read()
        late, intervals, clean = self._late, self._intervals, self._clean_windows
        w = self._pending
        if w is not None and not (self._before_pending_stolen or w[2]):
            late, intervals, clean = late + w[0], intervals + w[1], clean + 1
        return StealFreeFigures(intervals, late, round(late / intervals, 6) if intervals else 0.0,
                                self._windows, clean)
