"""The predictors by name: :func:`make_predictor` builds one, guarded (hil/prediction/base.py)."""

from __future__ import annotations

import math

from hil.prediction.ar import ArModel
from hil.prediction.base import GuardedPredictor, Model, PredictionError, SafetyLimits
from hil.prediction.fastlane import FastLaneModel
from hil.prediction.kalman import OscillatorKalmanModel
from hil.prediction.linear import AlphaBetaModel, NoneModel
from hil.prediction.wlms import WlmsModel

__all__ = ["PREDICTOR_NAMES", "make_predictor"]

#: The AR model's order (increments) and window (s of samples): tools/bench prediction's figures.
AR_ORDER = 6
AR_WINDOW_S = 4.0

#: Every predictor, baselines first.
PREDICTOR_NAMES: tuple[str, ...] = ("none", "alpha-beta", "wlms", "ar-ls", "kalman-osc", "fast-lane")


def make_predictor(name: str, rate_hz: float, limits: SafetyLimits | None = None, *, alpha: float = 0.9,
                   beta: float = 0.7, noise_mm: float = 0.05) -> GuardedPredictor:
    """The predictor ``name`` for samples at ``rate_hz`` (Hz), with its default parameters
    (docs/prediction.md) and the safety ``limits``; ``alpha``/``beta`` are the alpha-beta
    filter's gains (the project's ``[procedure.compensation] filter_alpha/filter_beta``),
    ``noise_mm`` the measurement noise per axis the Kalman filter assumes (mm, floored at 0.05).

    Raises:
        PredictionError: an unknown name or a rate that is not a finite number > 0.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise PredictionError(f"predictor {name}: rate must be a finite number > 0 Hz (got {rate_hz})")
    lim = limits or SafetyLimits()
    if name == "none":
        return GuardedPredictor(NoneModel(), rate_hz, lim, check_innovation=False)
    if name == "fast-lane":
        lanes = [_model(n, rate_hz, lim, alpha, beta, noise_mm) for n in PREDICTOR_NAMES[1:-1]]
        return GuardedPredictor(FastLaneModel(lanes, rate_hz), rate_hz, lim)
    if name not in PREDICTOR_NAMES:
        raise PredictionError(f"unknown predictor {name!r} (known: {', '.join(PREDICTOR_NAMES)})")
    model = _model(name, rate_hz, lim, alpha, beta, noise_mm)
    return GuardedPredictor(model, rate_hz, lim)


def _model(name: str, rate_hz: float, lim: SafetyLimits, alpha: float, beta: float, noise_mm: float) -> Model:
    """One of the single models with its default parameters (docs/prediction.md)."""
    if name == "alpha-beta":
        return AlphaBetaModel(alpha, beta)
    if name == "wlms":
        return WlmsModel(max_steps=max(1, math.ceil(lim.max_horizon_s * rate_hz)),
                         warmup=max(50, round(5 * rate_hz)))
    if name == "ar-ls":
        return ArModel(order=AR_ORDER, window=max(AR_ORDER + 10, round(AR_WINDOW_S * rate_hz)))
    assert name == "kalman-osc", name
    return OscillatorKalmanModel(1.0 / rate_hz, noise_mm=max(noise_mm, 0.05),
                                 warmup=max(10, round(3 * rate_hz)))
