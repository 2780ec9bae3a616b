"""Keeping the supervisor's process off the real-time servo loop's CPU (``[servo] reserve_cpu``).

The servo loop runs pinned to one CPU at SCHED_FIFO (:mod:`hil.servo.rt`). Any other thread the
scheduler puts on that CPU runs only in the loop's gaps and is preempted by every period: on a
2-CPU machine the supervisor's frame path (pair -> markers -> setpoint) and the perception
process's grab were cut into pieces there, which put milliseconds on the frame -> command
latency's tail. :func:`reserve_cpu` moves every thread of this process to the other CPUs while a
loop runs (threads started later inherit it, and so does a process started from here: the
perception process); :func:`release_cpu` gives the CPU back when the loop ends.

Reservations are counted per CPU (two loops of one process on the same CPU release it once both
ended); the mask this process had before the first reservation is restored after the last. Linux
only (``/proc/self/task``); never raises: a refused request leaves the affinity as it was.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections import Counter

_lock = threading.Lock()
_reserved: Counter[int] = Counter()
_base: set[int] | None = None   # this process's CPUs before the first reservation


def _set_all_threads(cpus: set[int]) -> bool:
    """Every thread of this process to ``cpus``; False when the calling thread was refused."""
    try:
        os.sched_setaffinity(0, cpus)
    except OSError:
        return False
    with contextlib.suppress(OSError):
        for tid in os.listdir("/proc/self/task"):
            with contextlib.suppress(OSError, ValueError):   # a thread that ended meanwhile
                os.sched_setaffinity(int(tid), cpus)
    return True


def reserve_cpu(cpu: int) -> frozenset[int] | None:
    """Move this process off ``cpu`` (module doc). Returns the CPUs it now runs on, or None when
    it stays where it was: no other CPU is left to it, or the OS refused."""
    global _base
    with _lock:
        base = set(os.sched_getaffinity(0)) if _base is None else _base
        others = base - set(_reserved) - {cpu}
        if not others:
            return None
        if not _set_all_threads(others):
            return None
        _base = base
        _reserved[cpu] += 1
        return frozenset(others)


def release_cpu(cpu: int) -> None:
    """End one reservation of ``cpu`` (made by :func:`reserve_cpu`); after the last one, this
    process's CPUs are what they were before the first. Nothing happens for a CPU not reserved."""
    global _base
    with _lock:
        if _reserved[cpu] <= 0 or _base is None:
            return
        _reserved[cpu] -= 1
        if _reserved[cpu] == 0:
            del _reserved[cpu]
        _set_all_threads(_base - set(_reserved) or _base)
        if not _reserved:
            _base = None


def reserved_cpus() -> frozenset[int]:
    """The CPUs this process keeps off now."""
    with _lock:
        return frozenset(_reserved)
