"""What a step of the pair path costs, kept in a fixed-size histogram (no growth over a run).

COMPENSATE times its setpoint per pair (the predictor's update for the pair, then the setpoint:
the predictor's secant, or the alpha-beta filter's line) so that ``hil soak`` can say what a
predictor adds to the frame -> command path (issue 42: p99 growth <= 0.2 ms at 500 Hz) without
differencing two runs' end-to-end latencies, whose run-to-run spread is milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

__all__ = ["COST_BINS", "COST_BIN_US", "CostFigures", "CostHistogram", "PairCosts"]

#: bin width, µs, and number of bins (the last counts everything longer: 10 ms and over)
COST_BIN_US = 1
COST_BINS = 10_000


@dataclass(frozen=True)
class CostFigures:
    """p50 / p99 / max of the timed steps, µs (bin resolution: :data:`COST_BIN_US`; ``max_us``
    exact), and how many were timed."""

    count: int
    p50_us: float | None
    p99_us: float | None
    max_us: float | None

    def to_dict(self) -> dict[str, float | int | None]:
        return {"count": self.count, "p50_us": self.p50_us, "p99_us": self.p99_us, "max_us": self.max_us}


class CostHistogram:
    """Durations in 1 µs bins over 0 .. 10 ms, allocated once (80 kB): adding never allocates.
    Not thread-safe: one owner adds (the controller thread), readers take :meth:`figures`."""

    def __init__(self) -> None:
        self._bins = np.zeros(COST_BINS, dtype=np.int64)
        self._count = 0
        self._max_ns = 0

    def add_ns(self, duration_ns: int) -> None:
        """Count one step of ``duration_ns`` (ns; negative counts as 0)."""
        d = max(int(duration_ns), 0)
        self._bins[min(d // (1000 * COST_BIN_US), COST_BINS - 1)] += 1
        self._count += 1
        if d > self._max_ns:
            self._max_ns = d

    def figures(self) -> CostFigures:
        """The figures so far (all None before the first step). A percentile is the upper edge of
        the bin it falls in (capped at the maximum), so it is never below the true value and above
        it by at most one bin; one in the last bin (10 ms and over) is the maximum."""
        if self._count == 0:
            return CostFigures(0, None, None, None)
        cum = np.cumsum(self._bins)

        def edge(q: float) -> float:
            k = int(np.searchsorted(cum, q * self._count, side="left"))
            if k >= COST_BINS - 1:
                return self._max_ns / 1000.0
            return float(min((k + 1) * COST_BIN_US, self._max_ns / 1000.0))

        return CostFigures(self._count, edge(0.5), edge(0.99), round(self._max_ns / 1000.0, 3))


class PairCosts(NamedTuple):
    """What the controller's models cost on the pair path so far (``hil soak``'s figures).

    Attributes:
        setpoint: COMPENSATE's setpoint work per pair (the predictor's update, then the setpoint).
        change_fit: the change estimator and the target model's steering, per registered pair.
        pair_model: per COMPENSATE pair, the two above of the same pair added: what the estimator,
            the target model and the predictor together put on the frame -> command path (the
            sum of the two parts' p99s overstates it: their slow pairs are not the same pairs).
    """

    setpoint: CostFigures
    change_fit: CostFigures
    pair_model: CostFigures
