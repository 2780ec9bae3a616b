"""The two baselines: no prediction, and today's COMPENSATE alpha-beta filter.

"none" answers the last sample for any horizon. "alpha-beta" is the same filter as
:class:`hil.controller.compensation.MotionFilter` on the translation (position gain alpha,
velocity gain beta; the first sample sets the position with zero velocity) with the servo loop's
straight-line extrapolation along the filtered velocity, ``x + v * h`` (Kalata, "The tracking
index", IEEE Trans. AES 20(2), 1984: the alpha-beta update with the constant-velocity
prediction; the project's defaults are ``[procedure.compensation] filter_alpha/filter_beta``).
Here the velocity is kept per sample period; tests/prediction/test_predictors.py checks that the
two agree.
"""

from __future__ import annotations

import numpy as np

from hil.prediction.base import FloatArray

__all__ = ["AlphaBetaModel", "NoneModel"]


class NoneModel:
    """No prediction: the last sample."""

    name = "none"

    def __init__(self) -> None:
        self._x: FloatArray | None = None

    @property
    def ready(self) -> bool:
        return self._x is not None

    def reset(self) -> None:
        self._x = None

    def feed(self, x_mm: FloatArray, steps: float) -> None:
        self._x = x_mm

    def forecast(self, steps: float) -> FloatArray:
        assert self._x is not None
        return self._x.copy()


class AlphaBetaModel:
    """Alpha-beta filter and straight-line extrapolation, as MotionFilter (module docstring).

    Args:
        alpha: position gain (0, 1].
        beta: velocity gain [0, 2].
    """

    name = "alpha-beta"

    def __init__(self, alpha: float = 0.9, beta: float = 0.7) -> None:
        if not (0 < alpha <= 1 and 0 <= beta <= 2):
            raise ValueError(f"alpha-beta: alpha in (0, 1] and beta in [0, 2] (got {alpha}, {beta})")
        self.alpha = alpha
        self.beta = beta
        self._x: FloatArray | None = None
        self._v: FloatArray = np.zeros(3)  # mm per sample period

    @property
    def ready(self) -> bool:
        return self._x is not None

    def reset(self) -> None:
        self._x = None
        self._v = np.zeros(3)

    def feed(self, x_mm: FloatArray, steps: float) -> None:
        if self._x is None:
            self._x, self._v = x_mm.copy(), np.zeros(3)
            return
        x_pred = self._x + self._v * steps
        r = x_mm - x_pred
        self._x = x_pred + self.alpha * r
        self._v = self._v + (self.beta / steps) * r

    def forecast(self, steps: float) -> FloatArray:
        assert self._x is not None
        return self._x + self._v * steps
