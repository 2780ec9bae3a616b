"""The simulated rig's errors (``[simulation.rig_errors]``): what the true rig is, given what the
controller is told. Pure functions of the configured values and a random stream; all zero knobs
give back exactly the configured values.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from hil.geometry.transform import RigidTransform
from hil.vision.camera_model import StereoCalibration

FloatArray = NDArray[np.float64]


def true_flange_markers(configured_mm: FloatArray, sigma_mm: float, rng: np.random.Generator) -> FloatArray:
    """The true flange-marker layout (flange frame, mm): each configured (CAD) marker moved by
    an independent normal offset of ``sigma_mm`` per axis."""
    if sigma_mm <= 0.0:
        return np.array(configured_mm, dtype=np.float64)
    out: FloatArray = configured_mm + sigma_mm * rng.normal(size=configured_mm.shape)
    return out


def true_calibration(cal: StereoCalibration, sigma_px: float, rng: np.random.Generator) -> StereoCalibration:
    """The true cameras of a rig whose calibration file is ``cal`` and was as good as a real one of
    about ``sigma_px`` reprojection RMS: focal lengths off by N(0, sigma) px, principal points by
    N(0, sigma/2) px, the right camera's rotation by N(0, sigma/(2 f)) rad per axis and its
    translation by N(0, sigma/(2 f) * 1000 mm) per axis (the image shift a point 1 m away sees).
    Over the working volume the projections move by roughly ``sigma_px`` RMS."""
    if sigma_px <= 0.0:
        return cal
    f = float(cal.K_left[0, 0])

    def k(K: FloatArray) -> FloatArray:
        out = np.array(K, dtype=np.float64)
        out[0, 0] += sigma_px * rng.normal()
        out[1, 1] += sigma_px * rng.normal()
        out[0, 2] += 0.5 * sigma_px * rng.normal()
        out[1, 2] += 0.5 * sigma_px * rng.normal()
        return out

    K_left, K_right = k(cal.K_left), k(cal.K_right)
    ang = sigma_px / (2.0 * f)
    dR = RigidTransform.from_rotvec(ang * rng.normal(size=3)).R
    dt = ang * 1000.0 * rng.normal(size=3)
    return dataclasses.replace(cal, K_left=K_left, K_right=K_right,
                               R_right_from_left=dR @ cal.R_right_from_left,
                               t_right_from_left_mm=cal.t_right_from_left_mm + dt)


def joint_offsets(sigma_rad: float, rng: np.random.Generator) -> FloatArray:
    """True joint zero offsets (rad, six joints): the arm is at ``q + offset`` when it reports q."""
    if sigma_rad <= 0.0:
        return np.zeros(6)
    out: FloatArray = sigma_rad * rng.normal(size=6)
    return out


def reception_offset_ns(mean_ms: float, jitter_ms: float, rng: np.random.Generator) -> int:
    """One frame's reception stamp minus its exposure, ns: ``mean_ms`` plus a normal jitter of
    ``jitter_ms`` truncated at 3 sigma, never negative."""
    j = 0.0 if jitter_ms <= 0.0 else float(np.clip(rng.normal(), -3.0, 3.0)) * jitter_ms
    return max(0, round((mean_ms + j) * 1e6))
