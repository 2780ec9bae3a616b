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

Compiled: when the per-pair geometry extension is built and selected (:mod:`hil.geometry.native`,
``HIL_GEOMETRY_KERNEL``), :meth:`ArModel.feed` and :meth:`ArModel.forecast` are one call each into
``ar_feed`` / ``ar_forecast`` (hil/geometry/_native.c) on state arrays this class owns (a ring of
the increments instead of :class:`~hil.prediction._history.History`); the numpy code here is the
reference, and the two agree to rounding (tests/prediction/test_ar_compiled.py). Why: in the
loop, the numpy code's ~100 small calls per pair took 0.24 ms p50 / 0.37 ms p99 of a
supervisor whose CPU the camera thread shares (docs/benchmarks.md, issue 42: at most 0.2 ms p99
more on the pair path). The choice is made when the model is built.
"""

from __future__ import annotations

import math

import numpy as np

from hil.geometry import native
from hil.prediction._history import History
from hil.prediction.base import FloatArray

__all__ = ["MAX_COMPILED_ORDER", "ArModel"]

#: the largest order the compiled code takes (its stack arrays)
MAX_COMPILED_ORDER = 64


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
        #: the compiled module (module doc; None: the numpy code) and its state
        self._k = native.active() if order <= MAX_COMPILED_ORDER else None
        self._ring = np.zeros((window + order + 1, 3))
        self._Af = np.zeros((3, order * order))
        self._yf = np.zeros(3)
        self._meta = np.zeros(4)    # head, increments held, samples seen, rows (ar_feed's doc)
        self._out = np.zeros(3)

    @property
    def compiled(self) -> bool:
        """Whether feed and forecast run compiled (module doc)."""
        return self._k is not None

    @property
    def ready(self) -> bool:
        return (self._meta[3] if self._k is not None else self._rows) >= self.N

    def reset(self) -> None:
        self._y.clear()
        self._d.clear()
        self._A[:] = 0.0
        self._b[:] = 0.0
        self._a[:] = 0.0
        self._rows = 0
        self._ring[:] = 0.0
        self._Af[:] = 0.0
        self._yf[:] = 0.0
        self._meta[:] = 0.0

    def _row(self, k: int) -> tuple[FloatArray, FloatArray]:
        """(regressor (3, p), target (3,)) of the row whose target is the increment ``k`` back."""
        d = self._d.last(self.p + 1 + k)
        block = d[: self.p + 1] if k else d
        return block[: self.p][::-1].T, block[self.p]

    def feed(self, x_mm: FloatArray, steps: float) -> None:
        if self._k is not None:
            if self._k.ar_feed(x_mm, self._ring, self._Af, self._b, self._a, self._yf, self._meta,
                               self.p, self.N, self.ridge) != 0:   # a singular window: numpy says why
                A = self._Af.reshape(3, self.p, self.p) + self.ridge * np.eye(self.p)
                self._a = np.asarray(np.linalg.solve(A, self._b[:, :, None])[:, :, 0], dtype=np.float64)
            return
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
        if self._k is not None:
            self._k.ar_forecast(float(steps), self._ring, self._a, self._yf, self._meta, self.p, self._out)
            return self._out.copy()
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
