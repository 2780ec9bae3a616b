"""Clocks: the controller and every simulated device take a :class:`Clock` and never call ``time``.

A :class:`ManualClock` makes simulated procedures deterministic and faster than real time;
a :class:`MonotonicClock` runs the same code at real time against hardware.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """A monotonic time source in nanoseconds, with a sleep that respects the clock's own time."""

    def now_ns(self) -> int:
        """Monotonic time, ns. Never decreases."""
        ...

    def sleep(self, duration_s: float) -> None:
        """Block until ``duration_s`` of this clock's time has passed (no-op for <= 0)."""
        ...


class MonotonicClock:
    """Real time: ``time.monotonic_ns`` and ``time.sleep``."""

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep(self, duration_s: float) -> None:
        if duration_s > 0:
            time.sleep(duration_s)

    def now_s(self) -> float:
        return self.now_ns() * 1e-9


class ManualClock:
    """Simulated time that moves only when told: ``advance`` or ``sleep`` (which advances).

    Thread-safe. ``sleep`` advances the clock instead of blocking, so a simulated procedure runs
    as fast as the CPU allows and reproduces exactly.
    """

    def __init__(self, start_ns: int = 0) -> None:
        if start_ns < 0:
            raise ValueError(f"start_ns must be >= 0, got {start_ns}")
        self._now_ns = start_ns
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        with self._lock:
            return self._now_ns

    def now_s(self) -> float:
        return self.now_ns() * 1e-9

    def advance(self, duration_s: float) -> None:
        """Move time forward by ``duration_s`` seconds (must be >= 0)."""
        if duration_s < 0:
            raise ValueError(f"a clock cannot go back: advance({duration_s})")
        with self._lock:
            self._now_ns += round(duration_s * 1e9)

    def sleep(self, duration_s: float) -> None:
        if duration_s > 0:
            self.advance(duration_s)
