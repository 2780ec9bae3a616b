"""Registration of the tracker (transmitter) frame to the optical frame with stylus touches.

Seed 003 section 4.2: a stylus carrying a sensor touches predefined markers; their positions
``P_T`` in the transmitter frame come from the stylus (sensor pose + pivot-calibrated tip
offset), their positions ``P_V`` in the stereo ("optical") frame from the cameras, and the
transform ``M`` with ``P_V = M P_T`` is solved from the pairs — here with the SVD method
(:func:`hil.geometry.registration.register_svd`, Arun/Umeyama with the reflection guard).
Several samples per touch are averaged; their spread is reported, and a touch whose stylus
moved more than ``max_touch_spread_mm`` is refused.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from hil.errors import CalibrationError, GeometryError
from hil.geometry.registration import register_svd
from hil.geometry.transform import FloatArray, RigidTransform, as_points

MAX_TOUCH_SPREAD_MM = 1.0


@dataclass(frozen=True)
class StylusTouch:
    """One marker touched with the stylus: the sensor poses sampled while touching it."""

    label: str
    poses: tuple[RigidTransform, ...]


@dataclass(frozen=True)
class TrackerRegistration:
    """Result of :func:`register_tracker_to_optical`.

    Attributes:
        T_optical_from_tracker: maps tracker-frame points into the optical frame.
        labels: the markers, in order.
        tracker_points_mm: (N, 3) touched tip positions, tracker frame.
        optical_points_mm: (N, 3) the same markers in the optical frame.
        residuals_mm: (N,) ``|T P_T - P_V|``.
        fre_rms_mm: RMS of the residuals.
        touch_spread_mm: (N,) RMS spread of the tip over each touch's samples.
    """

    T_optical_from_tracker: RigidTransform
    labels: tuple[str, ...]
    tracker_points_mm: FloatArray
    optical_points_mm: FloatArray
    residuals_mm: FloatArray
    fre_rms_mm: float
    touch_spread_mm: FloatArray

    def to_dict(self) -> dict[str, object]:
        return {
            "T_optical_from_tracker": self.T_optical_from_tracker.to_dict(),
            "fre_rms_mm": self.fre_rms_mm,
            "markers": [
                {"label": lab, "tracker_mm": [float(v) for v in p], "optical_mm": [float(v) for v in q],
                 "residual_mm": float(r), "touch_spread_mm": float(s)}
                for lab, p, q, r, s in zip(self.labels, self.tracker_points_mm, self.optical_points_mm,
                                           self.residuals_mm, self.touch_spread_mm, strict=True)
            ],
        }


def touched_point(touch: StylusTouch, tip_offset_sensor_mm: ArrayLike,
                  max_spread_mm: float = MAX_TOUCH_SPREAD_MM) -> tuple[FloatArray, float]:
    """Mean tip position (tracker frame) over a touch's samples and its RMS spread, mm.

    Raises:
        CalibrationError: no samples, or the tip moved more than ``max_spread_mm`` (RMS).
    """
    if not touch.poses:
        raise CalibrationError(f"marker {touch.label}: no stylus samples")
    tip = np.asarray(tip_offset_sensor_mm, dtype=np.float64).reshape(3)
    pts = np.stack([p.apply(tip) for p in touch.poses])
    mean = pts.mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((pts - mean) ** 2, axis=1))))
    if spread > max_spread_mm:
        raise CalibrationError(
            f"marker {touch.label}: the stylus tip moved {spread:.2f} mm RMS while touching "
            f"(limit {max_spread_mm:g} mm); hold it still and touch again")
    return mean, spread


def register_tracker_to_optical(
    touches: Sequence[StylusTouch],
    optical_points_mm: ArrayLike,
    tip_offset_sensor_mm: ArrayLike,
    *,
    max_touch_spread_mm: float = MAX_TOUCH_SPREAD_MM,
) -> TrackerRegistration:
    """Solve ``T_optical_from_tracker`` from stylus touches of markers with known optical positions.

    Args:
        touches: one per marker, in the order of ``optical_points_mm``.
        optical_points_mm: (N, 3) marker centres in the optical frame (mm), N >= 3, not collinear.
        tip_offset_sensor_mm: the stylus tip in its sensor frame (pivot calibration).
        max_touch_spread_mm: refuse a touch whose samples spread more (RMS).

    Raises:
        CalibrationError: count mismatch, a shaky touch, or a degenerate marker layout.
    """
    try:
        optical = as_points(optical_points_mm, "optical_points_mm")
    except GeometryError as exc:
        raise CalibrationError(str(exc)) from exc
    if len(touches) != optical.shape[0]:
        raise CalibrationError(f"{len(touches)} touches for {optical.shape[0]} markers")
    results = [touched_point(t, tip_offset_sensor_mm, max_touch_spread_mm) for t in touches]
    tracker_pts = np.stack([r[0] for r in results])
    try:
        reg = register_svd(fixed=optical, moving=tracker_pts)
    except GeometryError as exc:
        raise CalibrationError(f"tracker registration: {exc}") from exc
    return TrackerRegistration(
        T_optical_from_tracker=reg.T_fixed_from_moving,
        labels=tuple(t.label for t in touches),
        tracker_points_mm=tracker_pts,
        optical_points_mm=optical,
        residuals_mm=np.asarray(reg.residuals_mm, dtype=np.float64),
        fre_rms_mm=float(reg.fre_rms_mm),
        touch_spread_mm=np.array([r[1] for r in results]),
    )
