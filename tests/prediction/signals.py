"""Synthetic breathing-like signals for the predictor tests (mm, s)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
PERIOD_S = 4.0
AMPLITUDE_MM = np.array([10.0, 3.0, 1.0])
PHASE_RAD = np.array([0.0, 0.5, 1.0])


def sinusoid(t_s: FloatArray | float) -> FloatArray:
    """A pure 4-s breathing sinusoid, (N, 3) mm (or (3,) for a scalar time)."""
    t = np.asarray(t_s, dtype=np.float64)
    out: FloatArray = AMPLITUDE_MM * np.sin(2 * np.pi * t[..., None] / PERIOD_S + PHASE_RAD)
    return out
