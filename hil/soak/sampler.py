"""The soak's sampler: memory of the supervisor, servo and perception processes once a second,
and, from the first entry into COMPENSATE, the servo process's CPU use and the host's steal
(hil/soak/host.py). Reads Linux's /proc; figures it cannot read are None or empty, never guessed.
"""

from __future__ import annotations

import os
import time
from array import array
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from hil.servo.client import ServoRobot
from hil.servo.figures import StatsCopy
from hil.servo.shm import Stat
from hil.soak.heapmap import HeapBreakdown, read_heap_breakdown
from hil.soak.host import StealFreeLate, StealSample, sample_steal, steal_percent

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def rss_mb(pid: int | None = None) -> float:
    """Resident set size of this process (or ``pid``), MB (Linux /proc; 0 where unavailable)."""
    try:
        with open(f"/proc/{pid or 'self'}/statm") as fh:
            return int(fh.read().split()[1]) * _PAGE / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


def cpu_s(pid: int) -> float | None:
    """CPU time (user + system) the process ``pid`` used so far, s (Linux /proc; None where
    unavailable)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


@dataclass(frozen=True)
class SamplerEnd:
    """What :meth:`Sampler.finish` read at the end of the run.

    Attributes:
        stats: the loop's statistics.
        cpu_percent: the servo process's CPU use in compensation, % of one CPU (None: unknown).
        steal: the host's steal in compensation, % (``SoakResult.host_steal_percent``).
        steal_free: :class:`~hil.soak.host.StealFreeFigures` as a dict; empty when none was read.
    """

    stats: StatsCopy
    cpu_percent: float | None
    steal: dict[str, float | None]
    steal_free: dict[str, Any]


class Sampler:
    """Called by the soak operator every tick: once a second the RSS of the supervisor, the servo
    process and the perception process; once a minute where the supervisor's memory is
    (:attr:`heap`); when compensation first starts (:meth:`on_compensate`)
    the loop's counters, the servo process's CPU time and the host's steal counters; and from
    then the steal-free windows (:class:`~hil.soak.host.StealFreeLate`)."""

    def __init__(self, robot: ServoRobot, perception_pid: Callable[[], int | None] | None) -> None:
        self.robot, self.perception_pid = robot, perception_pid
        # once a second for the whole soak, so flat arrays (8 bytes a value, not ~150 bytes a
        # tuple: the supervisor's memory is what the soak measures): :attr:`rss` reads them
        self._rss_t = array("d")
        self._rss_sup_mb = array("d")
        self._rss_servo_mb = array("d")
        self._perc_t = array("d")
        self._perc_mb = array("d")
        #: (monotonic s, breakdown) of the supervisor's memory, once a minute (hil/soak/heapmap.py)
        self.heap: list[tuple[float, HeapBreakdown]] = []
        self._heap_last: float | None = None
        self.start: StatsCopy | None = None
        self._last = 0.0
        #: (monotonic s, CPU s) of the servo process when compensation first started
        self.servo_cpu_start: tuple[float, float] | None = None
        #: the host's steal counters when compensation first started: the loop's CPU, all CPUs
        self.steal_start: dict[str, StealSample | None] = {}
        self.steal_free: StealFreeLate | None = None

    def sample(self) -> None:
        if self.steal_free is not None:
            self.steal_free.sample()
        now = time.monotonic()
        if now - self._last < 1.0:
            return
        self._last = now
        ready = self.robot.link.ready
        self._rss_t.append(now)
        self._rss_sup_mb.append(rss_mb())
        self._rss_servo_mb.append(rss_mb(ready.pid) if ready is not None else 0.0)
        pid = None if self.perception_pid is None else self.perception_pid()
        if pid is not None:
            self._perc_t.append(now)
            self._perc_mb.append(rss_mb(pid))
        if self._heap_last is None or now - self._heap_last >= 60.0:
            self._heap_last = now
            self.heap.append((now, read_heap_breakdown()))

    @property
    def rss(self) -> list[tuple[float, float, float]]:
        """(monotonic s, supervisor MB, servo process MB), once a second (a new list)."""
        return list(zip(self._rss_t, self._rss_sup_mb, self._rss_servo_mb, strict=True))

    @property
    def perception_rss(self) -> list[tuple[float, float]]:
        """(monotonic s, perception process MB), once a second while it runs (a new list)."""
        return list(zip(self._perc_t, self._perc_mb, strict=True))

    def on_compensate(self) -> None:
        self.start = StatsCopy.of(self.robot.link.regions.stats)
        used = self._servo_cpu_s()
        self.servo_cpu_start = None if used is None else (time.monotonic(), used)
        self.steal_start = self._steal_now()
        rt, stats = self.robot.rt, self.robot.link.regions.stats
        self.steal_free = StealFreeLate(None if rt is None else rt.cpu,
                                        lambda: (stats.get(Stat.LATE), stats.get(Stat.INTERVALS)))
        self.steal_free.start()

    def _steal_now(self) -> dict[str, StealSample | None]:
        rt = self.robot.rt
        out = {"all_cpus": sample_steal(None)}
        if rt is not None and rt.cpu is not None:
            out["loop_cpu"] = sample_steal(rt.cpu)
        return out

    def host_steal_percent(self) -> dict[str, float | None]:
        """The host's steal since compensation first started, % (``SoakResult.host_steal_percent``)."""
        end = self._steal_now()
        out: dict[str, float | None] = {}
        for key, s0 in self.steal_start.items():
            s1 = end.get(key)
            if s0 is not None and s1 is not None:
                out[key] = steal_percent(s0, s1, (os.cpu_count() or 1) if key == "all_cpus" else 1)
        return out

    def finish(self) -> SamplerEnd:
        """The end of the run's figures; call it before the servo process ends."""
        free = None if self.steal_free is None else self.steal_free.figures()
        free_dict = asdict(free) if free is not None and free.windows else {}
        return SamplerEnd(StatsCopy.of(self.robot.link.regions.stats), self.servo_cpu_percent(),
                          self.host_steal_percent(), free_dict)

    def _servo_cpu_s(self) -> float | None:
        ready = self.robot.link.ready
        return None if ready is None else cpu_s(ready.pid)

    def servo_cpu_percent(self) -> float | None:
        """The servo process's CPU use since compensation first started, % of one CPU."""
        used = self._servo_cpu_s()
        if self.servo_cpu_start is None or used is None:
            return None
        t0, c0 = self.servo_cpu_start
        elapsed = time.monotonic() - t0
        return round(100.0 * (used - c0) / elapsed, 1) if elapsed > 0 else None
