"""Absolute periodic deadlines on the controller clock (COMPENSATE's servo stream at the robot's
rate, the soak's loop)."""

from __future__ import annotations

import math

from hil.clock import Clock


class DeadlineTimer:
    """Absolute periodic deadlines on a clock (a servo stream at the robot's rate).

    After :meth:`start` (``t0_ns``), each :meth:`wait` moves the deadline one period on
    (``next = previous deadline + period``) and sleeps until it, so the time spent working between
    waits does not accumulate into the period. When the caller is already late by more than a
    period, the missed slots are skipped (the grid is kept), ``missed`` is incremented and the wait
    returns at once; late by less than a period it returns at once without counting.

    Args:
        clock: the controller clock (blocking ``sleep``).
        period_s: the period, s (> 0).

    Raises:
        ValueError: the period is not a finite positive number.
    """

    def __init__(self, clock: Clock, period_s: float) -> None:
        if not (math.isfinite(period_s) and period_s > 0):
            raise ValueError(f"deadline period must be > 0 s, got {period_s}")
        self.clock = clock
        self.period_ns = max(1, round(period_s * 1e9))
        self.deadline_ns = clock.now_ns()
        self.missed = 0

    def start(self, t0_ns: int) -> None:
        """Anchor the grid: the first deadline is ``t0_ns`` + one period."""
        self.deadline_ns = t0_ns

    def next_ns(self) -> int:
        """The deadline the next :meth:`wait` will wait for (before any skipping)."""
        return self.deadline_ns + self.period_ns

    def wait(self) -> int:
        """Sleep until the next deadline (blocking on the clock); see the class doc. Returns the
        number of slots skipped (0 when the deadline was met or missed by less than a period)."""
        self.deadline_ns += self.period_ns
        now = self.clock.now_ns()
        late_ns = now - self.deadline_ns
        if late_ns > self.period_ns:
            skipped = late_ns // self.period_ns
            self.deadline_ns += skipped * self.period_ns
            self.missed += 1
            return int(skipped)
        if late_ns < 0:
            self.clock.sleep(-late_ns * 1e-9)
        return 0
