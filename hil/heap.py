"""Keep freed memory out of the resident set: one malloc arena; reference cycles collected and the C
heap trimmed now and then.

Why (docs/benchmarks.md "Supervisor memory", issue 45): the supervisor's resident size stepped up
~10-14 MB at the first fault of a soak and stayed there. Nothing leaked: the first full-frame
re-acquisition after a fault allocates image-sized buffers (a 1920x1080 grey image is 2 MB) and
frees them. glibc serves buffers that large with ``mmap`` until one is freed, then raises its
dynamic mmap threshold above that size (and its trim threshold to twice that), and from then on
such buffers come from the heap. A thread other than the main one (the supervisor's camera and
worker threads) gets an arena of its own (glibc creates one when the main arena's lock is taken);
buffers such a thread frees stay as the free top of its arena, below the raised trim threshold.
``malloc_trim`` returns the free pages inside every arena and the main arena's top, but not the
top of a thread's arena: the step stayed (measured: one thread arena, the 64 MB-aligned mapping
at ``0x7f..44000000``, went from 14 to 24 MB resident at the first fault; the process's free heap
from 22.7 to 35.1 MB, in use unchanged). Fixing the thresholds instead
(``MALLOC_MMAP_THRESHOLD_``) maps and unmaps every image-sized buffer and slowed the pair path
(same section).

The policy, three parts:

1. :func:`use_one_arena` (``mallopt(M_ARENA_MAX, 1)``), first thing in a process that runs a
   supervisor or the perception worker, before it starts a thread: every thread allocates from
   the main arena, whose top ``malloc_trim`` does return. Threads then share the arena's lock;
   they hold it for a few hundred nanoseconds per allocation, and the supervisor's threads take
   turns on the GIL anyway.
2. :class:`HeapTrimmer`: the controller calls :meth:`HeapTrimmer.after_tick` after every tick, and
   the perception process (when it runs) after every pair it publishes; at most once per
   ``every_s`` (``[procedure] heap_trim_every_s``, the caller's clock) it calls
   ``malloc_trim(0)``, which returns every whole free page of every arena to the system
   (``madvise``) and shrinks the main arena's top. When nothing is free it costs ~10-15 µs;
   releasing 16 MB took 1.2 ms on the development machine. It runs after the tick's setpoint is
   out and never in the servo process (its own process, memory locked, no heap traffic).

Where the C library is not glibc (no ``mallopt`` / ``malloc_trim``) neither does anything, and
each says so (:func:`use_one_arena` returns False; :attr:`HeapTrimmer.unavailable`).

3. Reference cycles are collected at the trim's period, before the trim (:meth:`HeapTrimmer.start`
   to :meth:`HeapTrimmer.stop`, which :meth:`hil.controller.controller.Controller.run` and the
   perception process bracket their loops with). Why (docs/benchmarks.md "The held pairs were
   cyclic garbage", issue 45): later faults of the hour's soak left 4-8 MB each, held for up to
   25 minutes. They were stereo pairs held by the frames of exceptions' tracebacks (a grab that
   timed out during a frame drop, with the dropped pair in a local): cyclic garbage, which only
   CPython's cyclic collector frees. The supervisor allocates so few containers in steady state
   that a generation-0 collection came every ~30 s and a full one almost never (one in four minutes
   of a soak: the one at start-up), and a full collection of its objects took 49 ms. So
   :meth:`HeapTrimmer.start` freezes the objects the process has by then (``gc.freeze``: start-up
   objects, modules, the devices, the plan; they live for the whole run, and the cyclic collector
   no longer walks them) and every period ``gc.collect()`` walks only what the run created since:
   garbage cycles live at most one period, and the collection costs ~1 ms, not 49.
   :meth:`HeapTrimmer.stop` unfreezes them (when the last started trimmer stops), so a process
   that runs many procedures (the test suite, a campaign worker) frees what each left.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["M_ARENA_MAX", "HeapTrimFigures", "HeapTrimmer", "glibc_malloc_trim", "use_one_arena"]

#: glibc's ``mallopt`` parameter for the most arenas a process may have (malloc.h)
M_ARENA_MAX = -8


def _libc() -> ctypes.CDLL | None:
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def use_one_arena() -> bool:
    """``mallopt(M_ARENA_MAX, 1)``: threads started from now on allocate from the main arena
    (module doc); call it before the process starts a thread (a thread that already has an arena
    keeps it). True when glibc took the setting; False where the C library is not glibc."""
    libc = _libc()
    fn = getattr(libc, "mallopt", None)
    if fn is None:
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_int]
    fn.restype = ctypes.c_int
    return bool(fn(M_ARENA_MAX, 1))


def glibc_malloc_trim() -> Callable[[], int] | None:
    """``malloc_trim(0)`` of the process's C library (returns 1 when memory went back to the
    system), or None where the library has none (not glibc). ctypes releases the GIL in the call."""
    fn = getattr(_libc(), "malloc_trim", None)
    if fn is None:
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return lambda: int(fn(0))


@dataclass(frozen=True)
class HeapTrimFigures:
    """What the trimmer did: trims called, how many returned memory, the longest and total time of
    a trim (ms, wall clock); cycle collections done, the objects they freed, their longest and
    total time (ms, wall clock), and the objects frozen at :meth:`HeapTrimmer.start` (0 when not
    started)."""

    trims: int
    released: int
    max_ms: float
    total_ms: float
    collections: int = 0
    collected: int = 0
    collect_max_ms: float = 0.0
    collect_total_ms: float = 0.0
    frozen_objects: int = 0

    def to_dict(self) -> dict[str, float | int]:
        return {"trims": self.trims, "released": self.released, "max_ms": round(self.max_ms, 3),
                "total_ms": round(self.total_ms, 3), "collections": self.collections,
                "collected": self.collected, "collect_max_ms": round(self.collect_max_ms, 3),
                "collect_total_ms": round(self.collect_total_ms, 3),
                "frozen_objects": self.frozen_objects}


class _Freezes:
    """The process's ``gc.freeze`` held while any started trimmer runs (module doc, part 3)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._holders = 0

    def take(self) -> int:
        """Freeze (the first holder) and return the objects frozen."""
        with self._lock:
            if self._holders == 0:
                gc.freeze()
            self._holders += 1
            return gc.get_freeze_count()

    def give(self) -> None:
        with self._lock:
            self._holders -= 1
            if self._holders == 0:
                gc.unfreeze()


_FREEZES = _Freezes()


class HeapTrimmer:
    """Calls ``trim`` at most once per ``every_s`` of the caller's clock (module doc), and between
    :meth:`start` and :meth:`stop` first ``collect``.

    Args:
        every_s: the period, s (0: never trim, never collect, never freeze).
        trim: the trim call (default: :func:`glibc_malloc_trim`; injected in tests).
        collect: the cycle collection, returning the objects it freed (default ``gc.collect``;
            injected in tests).
    """

    def __init__(self, every_s: float, trim: Callable[[], int] | None = None,
                 collect: Callable[[], int] = gc.collect) -> None:
        if not every_s >= 0:
            raise ValueError(f"heap trim period must be >= 0 s (got {every_s})")
        self.every_ns = round(every_s * 1e9)
        self._trim = trim if trim is not None else glibc_malloc_trim()
        #: why no trim is done (None: trims are done)
        self.unavailable: str | None = (
            "disabled (period 0)" if self.every_ns == 0
            else "the C library has no malloc_trim (not glibc)" if self._trim is None else None)
        self._next_ns: int | None = None
        self._trims = 0
        self._released = 0
        self._max_ns = 0
        self._total_ns = 0
        self._collect = collect
        self._started = False
        self._frozen = 0
        self._collections = 0
        self._collected = 0
        self._collect_max_ns = 0
        self._collect_total_ns = 0

    def start(self) -> None:
        """From now on collect reference cycles every period, and freeze the objects the process
        has now so that the collection walks only newer ones (module doc, part 3). Idempotent; a
        no-op with the period 0. Pair it with :meth:`stop` (``try``/``finally``)."""
        if self._started or self.every_ns == 0:
            return
        self._started = True
        self._frozen = _FREEZES.take()

    def stop(self) -> None:
        """Stop collecting; the process's objects are unfrozen when no other started trimmer runs.
        Idempotent."""
        if not self._started:
            return
        self._started = False
        _FREEZES.give()

    def after_tick(self, now_ns: int) -> None:
        """When the period has passed since the last one (the first call only starts the period):
        collect reference cycles (when started), then trim. Never raises."""
        if self.every_ns == 0 or (self._trim is None and not self._started):
            return
        if self._next_ns is None:
            self._next_ns = now_ns + self.every_ns
            return
        if now_ns < self._next_ns:
            return
        self._next_ns = now_ns + self.every_ns
        if self._started:
            self._collect_now()
        if self._trim is None:
            return
        t0 = time.perf_counter_ns()   # a cost figure, not control
        released = self._trim()
        dt = time.perf_counter_ns() - t0
        self._trims += 1
        self._released += 1 if released else 0
        self._total_ns += dt
        self._max_ns = max(self._max_ns, dt)

    def _collect_now(self) -> None:
        t0 = time.perf_counter_ns()   # a cost figure, not control
        freed = self._collect()
        dt = time.perf_counter_ns() - t0
        self._collections += 1
        self._collected += freed
        self._collect_total_ns += dt
        self._collect_max_ns = max(self._collect_max_ns, dt)

    def figures(self) -> HeapTrimFigures:
        return HeapTrimFigures(self._trims, self._released, self._max_ns / 1e6, self._total_ns / 1e6,
                               self._collections, self._collected, self._collect_max_ns / 1e6,
                               self._collect_total_ns / 1e6, self._frozen)
