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
