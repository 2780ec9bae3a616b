"""The predictors by name: :func:`make_predictor` builds one, guarded (hil/prediction/base.py)."""

from __future__ import annotations

import math

from hil.prediction.ar import ArModel
from hil.prediction.base import GuardedPredictor, Model, PredictionError, SafetyLimits
from hil.prediction.kalman import OscillatorKalmanModel
from hil.prediction.linear import AlphaBetaModel, NoneModel
from hil.prediction.wlms import WlmsModel

__all__ = ["PREDICTOR_NAMES", "make_predictor"]

#: Every predictor, baselines first.
PREDICTOR_NAMES: tuple[str, ...] = ("none", "alpha-beta", "wlms", "ar-ls", "kalman-osc")


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
    model: Model
    if name == "none":
        return GuardedPredictor(NoneModel(), rate_hz, lim, check_innovation=False)
    if name == "alpha-beta":
        model = AlphaBetaModel(alpha, beta)
    elif name == "wlms":
        model = WlmsModel(max_steps=max(1, math.ceil(lim.max_horizon_s * rate_hz)),
                          warmup=max(50, round(5 * rate_hz)))
    elif name == "ar-ls":
        model = ArModel(order=6, window=max(30, round(8 * rate_hz)))
    elif name == "kalman-osc":
        model = OscillatorKalmanModel(1.0 / rate_hz, noise_mm=max(noise_mm, 0.05),
                                      warmup=max(10, round(3 * rate_hz)))
    else:
        raise PredictionError(f"unknown predictor {name!r} (known: {', '.join(PREDICTOR_NAMES)})")
    return GuardedPredictor(model, rate_hz, lim)
