"""Sliding-window least-squares autoregressive prediction ("linear prediction" in Sharp, Jiang,
Shimizu and Shirato, "Prediction of respiratory tumour motion for real-time image-guided
radiotherapy", Phys. Med. Biol. 49 (2004) 425-440, their linear predictor: the next sample as a linear
combination of the last p samples, the coefficients the least-squares fit over the recent
history; Ernst et al., Phys. Med. Biol. 58 (2013) 3911, compare it as the plain autoregressive
baseline).

Here on the increments ``d(n) = y(n) - y(n-1)`` (so a baseline drift needs no coefficient):
``d(n+1) = sum_{i=1..p} a_i d(n+1-i)``, ``a`` the ridge-regularised least-squares solution over
the last N increments, ``(Phi^T Phi + lambda I) a = Phi^T d`` (ordinary least squares with a ridge term
lambda against an ill-conditioned window, e.g. a breath hold). The normal equations are kept as
running sums (the newest row added, the one leaving the window subtracted), so one sample costs
O(p^2) plus one p x p solve. A k-step forecast iterates the one-step model (feeding each forecast
increment back); a fractional step interpolates linearly between its two whole neighbours.
Each axis has its own coefficients.
"""

from __future__ import annotations

import math

import numpy as np

from hil.prediction._history import History
from hil.prediction.base import FloatArray

__all__ = ["ArModel"]


class ArModel:
    """Sliding-window least-squares AR(p) on each axis's increments (module docstring).

    Args:
        order: p, increments in the regressor (>= 1).
        window: N, increments in the least-squares window (> order).
        ridge_mm2: lambda, mm^2 (>= 0), added to the normal matrix's diagonal.
    """

    name = "ar-ls"

    def __init__(self, order: int = 6, window: int = 90, ridge_mm2: float = 1e-4) -> None:
        if not (order >= 1 and window > order and ridge_mm2 >= 0):
            raise ValueError(f"ar-ls: order >= 1, window > order, ridge >= 0 "
                             f"(got {order}, {window}, {ridge_mm2})")
        self.p, self.N, self.ridge = order, window, ridge_mm2
        self._y = History(2, (3,))
        self._d = History(window + order + 1, (3,))
        self._A = np.zeros((3, order, order))
        self._b = np.zeros((3, order))
        self._a = np.zeros((3, order))
        self._rows = 0

    @property
    def ready(self) -> bool:
        return self._rows >= self.N

    def reset(self) -> None:
        self._y.clear()
        self._d.clear()
        self._A[:] = 0.0
        self._b[:] = 0.0
        self._a[:] = 0.0
        self._rows = 0

    def _row(self, k: int) -> tuple[FloatArray, FloatArray]:
        """(regressor (3, p), target (3,)) of the row whose target is the increment ``k`` back."""
        d = self._d.last(self.p + 1 + k)
        block = d[: self.p + 1] if k else d
        return block[: self.p][::-1].T, block[self.p]

    def feed(self, x_mm: FloatArray, steps: float) -> None:
        if self._y.count:
            self._d.append(x_mm - self._y.back(0))
        self._y.append(x_mm)
        if self._d.count <= self.p:
            return
        phi, tgt = self._row(0)
        self._A += phi[:, :, None] * phi[:, None, :]
        self._b += phi * tgt[:, None]
        self._rows += 1
        if self._rows > self.N:
            phi, tgt = self._row(self.N)
            self._A -= phi[:, :, None] * phi[:, None, :]
            self._b -= phi * tgt[:, None]
            self._rows = self.N
        if self._rows >= self.N:
            A = self._A + self.ridge * np.eye(self.p)
            self._a = np.asarray(np.linalg.solve(A, self._b[:, :, None])[:, :, 0], dtype=np.float64)

    def forecast(self, steps: float) -> FloatArray:
        y = self._y.back(0).copy()
        s = max(steps, 0.0)
        hi = math.ceil(s)
        reg = self._d.last(self.p)[::-1].T.copy()  # (3, p), newest first
        prev = y.copy()
        for k in range(1, hi + 1):
            inc: FloatArray = np.einsum("ap,ap->a", self._a, reg)
            prev, y = y, y + inc
            reg[:, 1:] = reg[:, :-1]
            reg[:, 0] = inc
            if k == hi and s < hi:
                return prev + (s - (hi - 1)) * inc
        return y
