"""Shared synthetic-scene helpers for the seed-004 tests (and the benchmark)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def project(K: FloatArray, pts: FloatArray) -> FloatArray:
    h = np.asarray(pts, dtype=np.float64).reshape(-1, 3) @ K.T
    return np.asarray(h[:, :2] / h[:, 2:3])


def random_axis(rng: np.random.Generator, distance_mm: float = 600.0) -> tuple[FloatArray, FloatArray]:
    """An axis origin in front of the camera and a unit direction at least 20 deg off the view ray."""
    origin = np.array([rng.uniform(-100, 100), rng.uniform(-80, 80), distance_mm * rng.uniform(0.7, 1.3)])
    while True:
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        if abs(d @ origin) / np.linalg.norm(origin) < np.cos(np.deg2rad(20)):
            return origin, d
