"""wLMS: wavelet-based multiscale least-mean-squares prediction (Ernst, Schlaefer and Schweikard,
"Prediction of respiratory motion with wavelet-based multiscale autoregression", MICCAI 2007,
LNCS 4792, 668-675; evaluated in Ernst et al., "Evaluating and comparing algorithms for
respiratory motion prediction", Phys. Med. Biol. 58 (2013) 3911-3929; equation numbers are not
cited, the papers were not at hand here: the equations are written out below).

The signal is split by the a-trous Haar transform (Ernst 2007): ``c_0 = y``,
``c_j(n) = (c_{j-1}(n) + c_{j-1}(n - 2^(j-1))) / 2``, detail bands ``W_j = c_{j-1} - c_j``
(j = 1..J), so ``y = W_1 + ... + W_J + c_J``. The prediction ``delta`` samples ahead is a linear
combination of M taps per band spaced ``2^j`` apart,
``y(n + delta) - y(n) = sum_j sum_i w_(j,i) W_j(n - 2^j i) + sum_i w_(J+1,i) (c_J(n) - c_J(n - 2^J (i+1)))``,
and the weights are trained online by normalised LMS on the samples as they arrive (the
step normalised by the regressor's energy). Two departures, said here: the target and the
approximation band are increments (so a slow baseline drift needs no weight), and one weight
vector is kept per axis and per whole step ``delta = 1..K`` (K covers the longest horizon); a
fractional horizon interpolates linearly between the two neighbouring steps.
"""

from __future__ import annotations

import math

import numpy as np

from hil.prediction._history import History
from hil.prediction.base import FloatArray

__all__ = ["WlmsModel"]


class WlmsModel:
    """wLMS on each axis (module docstring).

    Args:
        max_steps: K, the longest horizon in sample periods (>= 1).
        scales: J, the number of detail bands (>= 1).
        taps: M, taps per band (>= 1).
        mu: NLMS step (0, 2).
        warmup: samples the filters train on before :attr:`ready` (besides the taps' span).
    """

    name = "wlms"

    def __init__(self, max_steps: int, scales: int = 3, taps: int = 3, mu: float = 0.1,
                 warmup: int = 50) -> None:
        if not (max_steps >= 1 and scales >= 1 and taps >= 1 and 0 < mu < 2 and warmup >= 0):
            raise ValueError(f"wlms: max_steps, scales, taps >= 1 and 0 < mu < 2 "
                             f"(got {max_steps}, {scales}, {taps}, {mu})")
        self.K, self.J, self.M, self.mu = max_steps, scales, taps, mu
        self.n_features = (scales + 1) * taps
        self.span = (2 ** scales) * (taps + 1) + 1
        self.warmup = self.span + max_steps + warmup
        keep = max(self.span, max_steps + 1) + 1
        self._c = [History(keep, (3,)) for _ in range(scales + 1)]
        self._y = History(max_steps + 1, (3,))
        self._f = History(max_steps + 1, (3, self.n_features))
        self._w = np.zeros((max_steps, 3, self.n_features))

    @property
    def ready(self) -> bool:
        return bool(self._y.count >= self.warmup)

    def reset(self) -> None:
        for h in self._c:
            h.clear()
        self._y.clear()
        self._f.clear()
        self._w[:] = 0.0

    def _features(self) -> FloatArray:
        f = np.zeros((3, self.n_features))
        n = self._c[0].count
        col = 0
        for j in range(1, self.J + 1):
            step = 2**j
            for i in range(self.M):
                lag = step * i
                if lag < n:
                    f[:, col] = self._c[j - 1].back(lag) - self._c[j].back(lag)
                col += 1
        cj = self._c[self.J]
        for i in range(self.M):
            lag = (2**self.J) * (i + 1)
            if lag < n:
                f[:, col] = cj.back(0) - cj.back(lag)
            col += 1
        return f

    def feed(self, x_mm: FloatArray, steps: float) -> None:
        n = self._c[0].count
        self._c[0].append(x_mm)
        for j in range(1, self.J + 1):
            lag = 2 ** (j - 1)
            prev = self._c[j - 1]
            older = prev.back(lag) if lag < n + 1 else prev.back(n)
            self._c[j].append(0.5 * (prev.back(0) + older))
        self._y.append(x_mm)
        # train each delta-step filter on the regressor delta samples ago
        avail = min(self._f.count, self.K)
        if avail > 0:
            past = self._f.last(avail)[::-1]  # (avail, 3, F): delta = 1..avail
            ys = self._y.last(avail + 1)[::-1]  # ys[0] = y(n), ys[d] = y(n - d)
            target = ys[0][None, :] - ys[1 : avail + 1]  # (avail, 3)
            w = self._w[:avail]
            e = target - np.einsum("daf,daf->da", w, past)
            energy = np.einsum("daf,daf->da", past, past) + 1e-9
            w += (self.mu * e / energy)[:, :, None] * past
        self._f.append(self._features())

    def forecast(self, steps: float) -> FloatArray:
        y = self._y.back(0)
        s = min(max(steps, 0.0), float(self.K))
        lo = math.floor(s)
        f = self._f.back(0)

        def inc(d: int) -> FloatArray:
            return np.zeros(3) if d == 0 else np.einsum("af,af->a", self._w[d - 1], f)

        a = inc(lo)
        if s == lo:
            return y + a
        return y + a + (s - lo) * (inc(lo + 1) - a)
