"""The predictor interface and the safety guard every predictor runs inside.

A *predictor* is fed measured 3-D positions (mm, any fixed frame) one sample at a time and
answers "where will it be ``horizon_s`` after the last sample". It learns online, from the samples
it was fed only. Each model (:class:`Model`) is wrapped in a :class:`GuardedPredictor`, which
owns the rules that make any model safe to put in front of a servo loop (docs/prediction.md):

* **bad samples are refused**: a non-finite position or time, a wrong shape, or a time that does
  not go forward raises :class:`PredictionError` (the caller skips the sample: a marker dropout);
* **gaps and wrong rates reset**: a sample interval outside ``[0.5, 1.5]`` nominal periods
  resets the model (counted fallback, reason ``"gap ..."``/``"rate ..."``);
* **warm-up**: until the model has the samples it needs, the prediction is the last sample
  ("none"); not counted as a fallback;
* **innovation check**: on each sample the model's forecast for that sample (made from the
  previous state) is compared with it; beyond ``innovation_bound_mm`` (3-D norm) the model is
  reset and the prediction is the last sample for ``hold_s`` (counted fallback);
* **bounded output**: the prediction's departure from the last sample is clamped (3-D norm) to
  ``min(max_departure_mm, max_speed_mm_s * horizon)``; a non-finite model output is a fallback;
* the horizon is clamped to ``[0, max_horizon_s]``; a negative horizon is refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from hil.errors import HilError

__all__ = ["FloatArray", "GuardedPredictor", "Model", "PredictionError", "Predictor", "SafetyLimits"]

FloatArray = NDArray[np.float64]

#: A sample interval outside [GAP_LOW, GAP_HIGH] nominal periods resets the model.
GAP_LOW = 0.5
GAP_HIGH = 1.5


class PredictionError(HilError, ValueError):
    """A sample or a request a predictor refuses (NaN, wrong shape, time not increasing, a
    negative horizon, a prediction before any sample)."""


class Predictor(Protocol):
    """What the bench and the controller use. ``fallbacks`` counts the times the predictor fell
    back to the last sample because it was wrong or its input was (gap, rate, innovation, output
    not finite); ``last_fallback_reason`` says why the last time."""

    name: str
    fallbacks: int
    last_fallback_reason: str | None

    def reset(self) -> None: ...

    def update(self, t_s: float, position_mm: FloatArray) -> None: ...

    def predict(self, horizon_s: float) -> FloatArray: ...


class Model(Protocol):
    """A bare prediction model on uniformly sampled data (sample period ``1/rate_hz``).

    ``feed`` takes one checked sample (finite, (3,), mm) ``steps`` sample periods after the
    previous one (1.0 nominally; within [0.5, 1.5]); ``forecast(steps)`` is the position
    ``steps`` sample periods (a float >= 0) after the last fed sample; ``ready`` is True once
    ``forecast`` is meaningful. The guard calls ``forecast`` only when ``ready``.
    """

    name: str

    @property
    def ready(self) -> bool: ...

    def reset(self) -> None: ...

    def feed(self, x_mm: FloatArray, steps: float) -> None: ...

    def forecast(self, steps: float) -> FloatArray: ...


@dataclass(frozen=True)
class SafetyLimits:
    """The guard's bounds (docs/prediction.md "Safety").

    Attributes:
        max_horizon_s: horizons beyond this are clamped to it, s (the controller's
            ``max_prediction_s``).
        max_departure_mm: the prediction never departs further than this from the last sample, mm.
        max_speed_mm_s: nor further than this speed times the horizon, mm/s.
        innovation_bound_mm: a forecast error (3-D norm) beyond this is a fallback, mm.
        hold_s: after an innovation fallback the prediction is the last sample for this long, s.
    """

    max_horizon_s: float = 0.2
    max_departure_mm: float = 5.0
    max_speed_mm_s: float = 60.0
    innovation_bound_mm: float = 2.0
    hold_s: float = 1.0


def _norm3(v: FloatArray) -> float:
    """The Euclidean norm of a 3-vector (inf or NaN when a component is): ``math.hypot`` on its
    items, a tenth of ``np.linalg.norm``'s time on the pair path."""
    a, b, c = v.tolist()
    return math.hypot(a, b, c)


class GuardedPredictor:
    """A :class:`Model` behind the safety rules of this module's docstring; a :class:`Predictor`.

    Args:
        model: the model (owned: reset with the guard).
        rate_hz: the nominal sample rate the model is set up for, Hz (> 0).
        limits: the bounds.
        check_innovation: False for the "none" model (its own fallback).
    """

    def __init__(self, model: Model, rate_hz: float, limits: SafetyLimits | None = None,
                 check_innovation: bool = True) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise PredictionError(f"predictor {model.name}: rate must be a finite number > 0 Hz "
                                  f"(got {rate_hz})")
        self.model = model
        self.name = model.name
        self.rate_hz = float(rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self.limits = limits or SafetyLimits()
        self.check_innovation = check_innovation
        self.fallbacks = 0
        self.last_fallback_reason: str | None = None
        self._t_s: float | None = None
        self._x: FloatArray = np.zeros(3)
        self._hold_until_s = -math.inf

    def reset(self) -> None:
        """Forget every sample (the counters stay)."""
        self.model.reset()
        self._t_s = None
        self._x = np.zeros(3)
        self._hold_until_s = -math.inf

    @property
    def predicting(self) -> bool:
        """True when :meth:`predict` uses the model (warm and not holding after a fallback)."""
        return self._t_s is not None and self._t_s >= self._hold_until_s and self.model.ready

    def _fallback(self, reason: str, hold: bool) -> None:
        self.fallbacks += 1
        self.last_fallback_reason = reason
        self.model.reset()
        if hold and self._t_s is not None:
            self._hold_until_s = self._t_s + self.limits.hold_s

    def update(self, t_s: float, position_mm: FloatArray) -> None:
        """Feed one measured sample: time ``t_s`` (s, increasing) and position (3,) mm.

        Raises:
            PredictionError: a non-finite time or position, a wrong shape, or a time not after
                the previous sample's (the sample is not taken; the state is unchanged).
        """
        x = np.asarray(position_mm, dtype=np.float64)
        if x.shape != (3,):
            raise PredictionError(f"predictor {self.name}: a position is 3 values (got shape {x.shape})")
        if not (math.isfinite(t_s) and math.isfinite(_norm3(x))):
            raise PredictionError(f"predictor {self.name}: sample at t={t_s} s is not finite ({x.tolist()}); "
                                  "skip it (a dropout) instead of feeding it")
        if self._t_s is not None:
            dt = t_s - self._t_s
            if dt <= 0:
                raise PredictionError(f"predictor {self.name}: time went from {self._t_s} s to {t_s} s "
                                      "(samples must be fed in increasing time)")
            steps = dt * self.rate_hz
            if steps > GAP_HIGH:
                self._fallback(f"gap of {dt * 1e3:.0f} ms (rate {self.rate_hz:g} Hz)", hold=False)
            elif steps < GAP_LOW:
                self._fallback(f"rate: sample interval {dt * 1e3:.1f} ms is too short for "
                               f"{self.rate_hz:g} Hz", hold=False)
            elif self.check_innovation and self.predicting:
                err = _norm3(self.model.forecast(steps) - x)
                if not err <= self.limits.innovation_bound_mm:
                    self._t_s = t_s
                    bound = self.limits.innovation_bound_mm
                    self._fallback(f"innovation {err:.2f} mm > {bound:g} mm", hold=True)
        else:
            steps = 1.0
        self._t_s = float(t_s)
        self._x = x.copy()
        self.model.feed(self._x, steps if GAP_LOW <= steps <= GAP_HIGH else 1.0)

    def predict(self, horizon_s: float) -> FloatArray:
        """The position (3,) mm at the last sample's time plus ``horizon_s`` (clamped to
        ``[0, max_horizon_s]``), its departure from the last sample clamped as the module says.

        Raises:
            PredictionError: nothing fed yet, or a negative or non-finite horizon.
        """
        if self._t_s is None:
            raise PredictionError(f"predictor {self.name}: no sample yet")
        if not (math.isfinite(horizon_s) and horizon_s >= 0):
            raise PredictionError(f"predictor {self.name}: horizon must be finite and >= 0 s "
                                  f"(got {horizon_s})")
        h = min(horizon_s, self.limits.max_horizon_s)
        if h == 0.0 or not self.predicting:
            return self._x.copy()
        p = self.model.forecast(h * self.rate_hz)
        d = p - self._x
        n = _norm3(d)
        if not math.isfinite(n):
            self._fallback("model output not finite", hold=True)
            return self._x.copy()
        cap = min(self.limits.max_departure_mm, self.limits.max_speed_mm_s * h)
        if n > cap:
            d = d * (cap / n)
        return self._x + d
