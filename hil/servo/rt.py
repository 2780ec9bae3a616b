"""Real-time set-up of the servo process, and its period wait.

:func:`apply_realtime` asks the OS for what a hard period needs and reports what it granted
(:class:`RtGranted`): ``SCHED_FIFO`` at a priority, one pinned CPU, ``mlockall(MCL_CURRENT |
MCL_FUTURE)`` (no page faults on the hot path), and the garbage collector frozen and disabled
(no collection pauses; the loop builds no reference cycles). Without root (or without
``CAP_SYS_NICE`` / ``CAP_IPC_LOCK``) each request fails on its own: the report says which and why,
and the loop runs anyway on the normal scheduler.

:func:`wait_until` sleeps until shortly before the deadline and spins the rest on the monotonic
clock: ``time.sleep`` alone wakes up 50-100 µs late under load, a spin alone burns the CPU.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

#: mlockall flags (linux/mman.h)
_MCL_CURRENT, _MCL_FUTURE = 1, 2
#: the final stretch before a deadline spent spinning, ns
SPIN_NS = 200_000


@dataclass
class RtGranted:
    """What the OS granted the servo process (``requested`` False: not asked for).

    Attributes:
        fifo_priority: the SCHED_FIFO priority granted, else None.
        cpu: the CPU the process is pinned to, else None.
        mlockall: whether memory is locked.
        gc_frozen: whether the garbage collector was frozen and disabled.
        errors: what was refused, by request (``{"fifo": "PermissionError: ..."}``).
        rt_cpu_cap: the share of each CPU the kernel lets real-time tasks use per period
            (``/proc/sys/kernel/sched_rt_runtime_us`` / ``sched_rt_period_us``; Linux's default
            0.95: a FIFO loop busier than that is paused for the rest of each second, "RT
            throttling"); None when uncapped or unknown.
    """

    requested: bool = False
    fifo_priority: int | None = None
    cpu: int | None = None
    mlockall: bool = False
    gc_frozen: bool = False
    errors: dict[str, str] = field(default_factory=dict)
    rt_cpu_cap: float | None = None

    @property
    def realtime(self) -> bool:
        """SCHED_FIFO and a pinned CPU were both granted."""
        return self.fifo_priority is not None and self.cpu is not None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["realtime"] = self.realtime
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RtGranted:
        return cls(bool(d.get("requested", False)), d.get("fifo_priority"), d.get("cpu"),
                   bool(d.get("mlockall", False)), bool(d.get("gc_frozen", False)),
                   dict(d.get("errors", {})), d.get("rt_cpu_cap"))

    def summary(self) -> str:
        """One line: what was granted and what was not."""
        if not self.requested:
            return "real-time scheduling not requested"
        parts = [f"SCHED_FIFO {self.fifo_priority}" if self.fifo_priority is not None else "no SCHED_FIFO",
                 f"CPU {self.cpu}" if self.cpu is not None else "not pinned",
                 "memory locked" if self.mlockall else "memory not locked",
                 "GC frozen" if self.gc_frozen else "GC running"]
        if self.fifo_priority is not None and self.rt_cpu_cap is not None:
            parts.append(f"RT tasks capped at {100 * self.rt_cpu_cap:.0f} % of a CPU")
        refused = "; ".join(f"{k}: {v}" for k, v in self.errors.items())
        return ", ".join(parts) + (f" (refused: {refused})" if refused else "")


def default_cpu() -> int:
    """The CPU the servo process is pinned to by default: the last one this process may use."""
    return max(os.sched_getaffinity(0))


def apply_realtime(priority: int, cpu: int | None) -> RtGranted:
    """Ask for SCHED_FIFO ``priority`` (1-99) and pin to ``cpu`` (None: :func:`default_cpu`) for
    the *calling thread* (on Linux both are per thread: threads started before keep theirs, threads
    it starts later inherit them); lock the process's memory and freeze its GC. Never raises: see
    :class:`RtGranted`."""
    g = RtGranted(requested=True)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        g.fifo_priority = priority
    except (OSError, ValueError) as exc:
        g.errors["fifo"] = f"{type(exc).__name__}: {exc}"
    try:
        target = default_cpu() if cpu is None else cpu
        os.sched_setaffinity(0, {target})
        g.cpu = target
    except (OSError, ValueError) as exc:
        g.errors["affinity"] = f"{type(exc).__name__}: {exc}"
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6", use_errno=True)
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0:
            g.mlockall = True
        else:
            err = ctypes.get_errno()
            g.errors["mlockall"] = f"errno {err}: {os.strerror(err)}"
    except OSError as exc:
        g.errors["mlockall"] = f"{type(exc).__name__}: {exc}"
    gc.collect()
    gc.freeze()
    gc.disable()
    g.gc_frozen = True
    g.rt_cpu_cap = rt_cpu_cap()
    return g


def rt_cpu_cap() -> float | None:
    """The kernel's cap on real-time tasks' share of a CPU (:class:`RtGranted`), None when
    uncapped (runtime -1) or unreadable."""
    try:
        runtime_us = int(Path("/proc/sys/kernel/sched_rt_runtime_us").read_text())
        period_us = int(Path("/proc/sys/kernel/sched_rt_period_us").read_text())
    except (OSError, ValueError):
        return None
    if runtime_us < 0 or period_us <= 0:
        return None
    return round(runtime_us / period_us, 4)


def wait_until(deadline_ns: int, spin_ns: int = SPIN_NS) -> int:
    """Block until the monotonic clock reaches ``deadline_ns`` (sleep, then spin the last
    ``spin_ns``). Returns the time it woke, ns."""
    now = time.monotonic_ns()
    remaining = deadline_ns - now - spin_ns
    if remaining > 0:
        time.sleep(remaining * 1e-9)
    now = time.monotonic_ns()
    while now < deadline_ns:
        now = time.monotonic_ns()
    return now
