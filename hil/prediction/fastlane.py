"""Fast lane: several predictors run side by side and the one with the lowest recent error answers
(Ernst, Schlaefer, Dieterich and Schweikard, "A fast lane approach to LMS prediction of
respiratory motion signals", Biomed. Signal Process. Control 3(4) (2008) 291-299: parallel
competing predictors, the output taken from the one whose recent prediction error is smallest).
There the lanes are LMS filters with different parameters; here they are the other models of this
package (alpha-beta, the least-squares AR, wLMS, the oscillator EKF).

The recent error of each lane is an exponentially weighted mean of its squared one-sample-ahead
error (3-D norm, mm^2), ``E <- (1 - lam) E + lam |forecast(steps) - x|^2`` with
``lam = 1 - exp(-1 / (rate_hz * memory_s))``, updated before the lane is fed each sample; a lane
counts only once it is ready. Until any lane is ready the answer comes from the first lane.
"""

from __future__ import annotations

import math

import numpy as np

from hil.prediction.base import FloatArray, Model

__all__ = ["FastLaneModel"]


class FastLaneModel:
    """The lanes' best by recent one-sample error (module docstring).

    Args:
        lanes: the competing models (fed every sample; owned).
        rate_hz: the nominal sample rate, Hz (> 0).
        memory_s: the error average's time constant, s (> 0).
    """

    name = "fast-lane"

    def __init__(self, lanes: list[Model], rate_hz: float, memory_s: float = 1.0) -> None:
        if not lanes or not (rate_hz > 0 and memory_s > 0):
            raise ValueError("fast-lane: at least one lane, rate and memory > 0")
        self.lanes = lanes
        self.lam = 1.0 - math.exp(-1.0 / (rate_hz * memory_s))
        self._err = np.full(len(lanes), math.inf)
        self._fed = False

    @property
    def ready(self) -> bool:
        return any(lane.ready for lane in self.lanes)

    @property
    def best(self) -> int:
        """Index of the lane that answers now."""
        return int(np.argmin(self._err)) if np.isfinite(self._err).any() else 0

    def reset(self) -> None:
        for lane in self.lanes:
            lane.reset()
        self._err[:] = math.inf
        self._fed = False

    def feed(self, x_mm: FloatArray, steps: float) -> None:
        for k, lane in enumerate(self.lanes):
            if self._fed and lane.ready:
                d = lane.forecast(steps) - x_mm
                e2 = float(d.dot(d))
                e = self._err[k]
                self._err[k] = e2 if math.isinf(e) else (1.0 - self.lam) * e + self.lam * e2
            lane.feed(x_mm, steps)
        self._fed = True

    def forecast(self, steps: float) -> FloatArray:
        lane = self.lanes[self.best]
        if not lane.ready:
            lane = next(m for m in self.lanes if m.ready)
        return lane.forecast(steps)
