"""Pivot calibration of a tracked stylus or needle.

The tip rests in a divot (the pivot) while the tool is swivelled about it. With the sensor
pose ``T_tracker_from_sensor_i = (R_i, t_i)`` of each sample, the tip offset ``p_tip`` (sensor
frame) and the pivot ``p_pivot`` (tracker frame) satisfy ``R_i p_tip + t_i = p_pivot`` for
every i. Stacked, ``[R_i  -I] [p_tip; p_pivot] = -t_i`` is a 3N x 6 linear system solved by
least squares (the standard algebraic pivot calibration, e.g. Yaniv, "Which pivot calibration?",
SPIE 2015). The residual ``|R_i p_tip + t_i - p_pivot|`` of each pose and their RMS measure the
quality. The system is well posed only when the rotations span at least two axes; a
near-singular system is refused rather than answered.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hil.errors import CalibrationError
from hil.geometry.transform import FloatArray, RigidTransform

#: Smallest rotation between the most different poses (deg) accepted for a calibration.
MIN_ROTATION_SPREAD_DEG = 10.0
#: Largest condition number of the stacked system accepted.
MAX_CONDITION = 1e4


@dataclass(frozen=True)
class PivotCalibration:
    """Result of :func:`pivot_calibration`.

    Attributes:
        tip_offset_sensor_mm: (3,) the tip in the sensor frame, mm.
        pivot_tracker_mm: (3,) the pivot point in the tracker (transmitter) frame, mm (in the
            reference sensor's frame when a reference was used).
        residuals_mm: (N,) per-pose distance of the computed tip from the pivot, mm.
        rms_mm: RMS of the residuals, mm.
        rotation_spread_deg: largest rotation angle between any pose and the first, deg.
    """

    tip_offset_sensor_mm: FloatArray
    pivot_tracker_mm: FloatArray
    residuals_mm: FloatArray
    rms_mm: float
    rotation_spread_deg: float

    @property
    def n_poses(self) -> int:
        return int(self.residuals_mm.shape[0])

    def to_dict(self) -> dict[str, object]:
        return {
            "tip_offset_sensor_mm": [float(v) for v in self.tip_offset_sensor_mm],
            "pivot_tracker_mm": [float(v) for v in self.pivot_tracker_mm],
            "rms_mm": self.rms_mm,
            "max_residual_mm": float(np.max(self.residuals_mm)),
            "n_poses": self.n_poses,
            "rotation_spread_deg": self.rotation_spread_deg,
        }


def pivot_calibration(
    poses: Sequence[RigidTransform],
    *,
    references: Sequence[RigidTransform] | None = None,
    min_rotation_spread_deg: float = MIN_ROTATION_SPREAD_DEG,
) -> PivotCalibration:
    """Solve the tip offset and the pivot point from N >= 4 poses of the pivoting sensor.

    Args:
        poses: ``T_tracker_from_sensor`` of each sample (mm).
        references: optional ``T_tracker_from_reference`` of a reference sensor fixed to the
            pivot base at the same instants; the poses are then taken relative to it
            (``T_reference_from_sensor``), so the base may move during the calibration.
        min_rotation_spread_deg: refuse poses that rotate less than this.

    Raises:
        CalibrationError: fewer than 4 poses, reference count mismatch, too little rotation,
            or an ill-conditioned system (rotation about one axis only).
    """
    n = len(poses)
    if n < 4:
        raise CalibrationError(f"pivot calibration needs at least 4 poses, got {n}")
    if references is not None:
        if len(references) != n:
            raise CalibrationError(f"{len(references)} reference poses for {n} sensor poses")
        poses = [ref.inverse() @ p for ref, p in zip(references, poses, strict=True)]
    Rs = np.stack([p.R for p in poses])
    ts = np.stack([p.t for p in poses])
    spread = max(math.degrees(RigidTransform(Rs[0].T @ R, np.zeros(3)).rotation_angle_rad()) for R in Rs)
    if spread < min_rotation_spread_deg:
        raise CalibrationError(
            f"the poses rotate by at most {spread:.1f} deg; swivel the tool more "
            f"(at least {min_rotation_spread_deg:g} deg) about the pivot")
    A = np.zeros((3 * n, 6))
    A[:, :3] = Rs.reshape(3 * n, 3)
    A[:, 3:] = -np.tile(np.eye(3), (n, 1))
    b = -ts.reshape(3 * n)
    sv = np.linalg.svd(A, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    if cond > MAX_CONDITION:
        raise CalibrationError(
            f"pivot system is ill-conditioned (condition {cond:.3g}): the tool was rotated about one "
            "axis only; swivel it in two directions")
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    x: FloatArray = np.asarray(sol, dtype=np.float64)
    tip, pivot = x[:3], x[3:]
    residuals = np.linalg.norm(np.einsum("nij,j->ni", Rs, tip) + ts - pivot, axis=1)
    return PivotCalibration(tip, pivot, residuals, float(np.sqrt(np.mean(residuals**2))), spread)


def tip_in_tracker(T_tracker_from_sensor: RigidTransform, tip_offset_sensor_mm: FloatArray) -> FloatArray:
    """The tool tip in the tracker frame for one sensor pose (mm)."""
    return T_tracker_from_sensor.apply(np.asarray(tip_offset_sensor_mm, dtype=np.float64))
