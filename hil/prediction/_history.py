"""A fixed-capacity history of rows (newest last) without per-sample allocation."""

from __future__ import annotations

import numpy as np

from hil.prediction.base import FloatArray


class History:
    """The last ``keep`` rows of shape ``row_shape`` appended, as a view (oldest first).

    Appends write into a buffer of ``4 * keep`` rows and copy the last ``keep`` rows to its start
    when it is full (amortised O(1) per row).
    """

    def __init__(self, keep: int, row_shape: tuple[int, ...]) -> None:
        self.keep = keep
        self._buf = np.zeros((4 * keep, *row_shape))
        self._n = 0  # rows in the buffer
        self.count = 0  # rows appended since the last clear

    def clear(self) -> None:
        self._n = 0
        self.count = 0

    def append(self, row: FloatArray) -> None:
        if self._n == self._buf.shape[0]:
            self._buf[: self.keep] = self._buf[self._n - self.keep : self._n]
            self._n = self.keep
        self._buf[self._n] = row
        self._n += 1
        self.count += 1

    def last(self, k: int) -> FloatArray:
        """The last ``min(k, available)`` rows, oldest first (a view: read, never keep)."""
        k = min(k, self._n)
        return self._buf[self._n - k : self._n]

    def back(self, i: int) -> FloatArray:
        """The row appended ``i`` appends ago (0 = newest); requires ``i < min(count, keep)``."""
        row: FloatArray = self._buf[self._n - 1 - i]
        return row
