"""A run's samples of one figure in memory that does not grow with the run's length.

The controller keeps per-tick and per-pair figures (latencies, tick work, and in simulation the
truth's errors) to report their percentiles at the end. Kept as growing arrays, a soak's supervisor
grew ~5 MB an hour from them (docs/benchmarks.md "Supervisor memory"), which is what the one-hour
soak's bound (<= 1 MB after the warm-up, issue 45) forbids. :class:`SampleSeries` allocates its
storage once, filled (so its pages are resident from the start, before any warm-up):

- up to ``capacity`` samples it holds every one, in order: every figure of a run that short is
  exactly what a plain array gave (the tests' exact expectations rely on it);
- beyond, it keeps a uniform random sample of ``capacity`` of them (reservoir sampling, Vitter's
  "Algorithm R", ACM TOMS 11(1), 1985), so percentiles are estimates (their standard error at the
  p95 with 32768 samples is ~0.12 percentile points); the count, sum of squares, minimum, maximum
  and last value stay exact. The reservoir's choices depend only on the seed and the
  count, so series appended in lockstep with the same seed stay paired sample for sample.

Not thread-safe: one owner appends (the controller thread).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["SERIES_CAPACITY", "SampleSeries"]

#: samples held exactly (8 bytes each: 256 kB a series)
SERIES_CAPACITY = 1 << 15

_MASK64 = (1 << 64) - 1


class SampleSeries:
    """One figure's samples (module doc).

    Args:
        capacity: samples held (> 0).
        seed: the reservoir's seed (series appended in lockstep with one seed stay paired).
    """

    def __init__(self, capacity: int = SERIES_CAPACITY, seed: int = 0x9E3779B97F4A7C15) -> None:
        if capacity <= 0:
            raise ValueError(f"capacity must be > 0 (got {capacity})")
        self._buf: NDArray[np.float64] = np.full(capacity, np.nan)   # resident now (module doc)
        self._cap = capacity
        self._n = 0
        self._state = (seed & _MASK64) or 1
        self._sumsq = 0.0
        self._min = math.inf
        self._max = -math.inf
        self._last = math.nan

    def _next(self) -> int:
        """xorshift64* (Vigna 2016): the reservoir's random draws, cheap and deterministic."""
        x = self._state
        x ^= x >> 12
        x ^= (x << 25) & _MASK64
        x ^= x >> 27
        self._state = x
        return (x * 0x2545F4914F6CDD1D) & _MASK64

    def append(self, value: float) -> None:
        """Add one sample (a float; NaN is stored as given and poisons sum and RMS, as in an array)."""
        v = float(value)
        n = self._n
        if n < self._cap:
            self._buf[n] = v
        else:
            j = self._next() % (n + 1)
            if j < self._cap:
                self._buf[j] = v
        self._n = n + 1
        self._sumsq += v * v
        if v < self._min:
            self._min = v
        if v > self._max:
            self._max = v
        self._last = v

    def __len__(self) -> int:
        """Samples appended (all of them, held or not)."""
        return self._n

    def __bool__(self) -> bool:
        return self._n > 0

    def held(self) -> NDArray[np.float64]:
        """The samples held: all of them in order while :attr:`exact`, else the reservoir (a
        read-only view; copy to keep)."""
        view = self._buf[:min(self._n, self._cap)]
        view.flags.writeable = False
        return view

    def __iter__(self) -> Iterator[float]:
        return iter(self.held().tolist())

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> NDArray[Any]:
        held = self.held()
        out = held if dtype is None else held.astype(dtype)
        return np.array(out, copy=True) if copy else out

    @property
    def exact(self) -> bool:
        """Every sample is held (percentiles of :meth:`held` are exact)."""
        return self._n <= self._cap

    @property
    def last(self) -> float | None:
        """The last sample appended (None before one)."""
        return None if self._n == 0 else self._last

    @property
    def max(self) -> float | None:
        return None if self._n == 0 else self._max

    @property
    def min(self) -> float | None:
        return None if self._n == 0 else self._min

    @property
    def rms(self) -> float | None:
        """Root mean square of every sample appended (None before one): while :attr:`exact`,
        numpy's over the held samples (bit for bit what an array gave), else the running sum's."""
        if self._n == 0:
            return None
        if self.exact:
            return float(np.sqrt(np.mean(np.square(self.held()))))
        return math.sqrt(self._sumsq / self._n)
