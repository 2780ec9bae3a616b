"""Respiratory-motion predictors: online models that forecast a measured 3-D position over the
latency, each behind the same safety guard (bounded output, innovation check with a counted
fallback, gaps, NaN refused, warm-up). docs/prediction.md."""

from hil.prediction.base import FloatArray, GuardedPredictor, PredictionError, Predictor, SafetyLimits
from hil.prediction.catalog import PREDICTOR_NAMES, make_predictor

__all__ = ["PREDICTOR_NAMES", "FloatArray", "GuardedPredictor", "PredictionError", "Predictor",
           "SafetyLimits", "make_predictor"]
