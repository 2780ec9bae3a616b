"""Using the tracker in the procedure: the tracked needle tip against the plan, and a patient
reference sensor as a stand-in for (or a check on) the skin-marker motion.

Seed 003 clinical step 5: the needle's sensor is followed in real time and its tip shown against
the target. Everything here is in the optical frame (the plan's entry/target are mapped there by
the registration), mm and rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from hil.errors import GeometryError
from hil.geometry.transform import FloatArray, RigidTransform


@dataclass(frozen=True)
class NeedleTipError:
    """Where the tracked needle tip is relative to the planned path (optical frame).

    Attributes:
        tip_optical_mm: (3,) the tip.
        distance_to_target_mm: ``|target - tip|``.
        lateral_error_mm: distance of the tip from the planned line through entry and target.
        depth_to_target_mm: signed distance from the tip to the target along the path direction
            (positive: the target is still ahead; negative: overshoot).
        direction_error_rad: angle between the needle axis and the planned direction.
    """

    tip_optical_mm: FloatArray
    distance_to_target_mm: float
    lateral_error_mm: float
    depth_to_target_mm: float
    direction_error_rad: float


def needle_tip_error(
    T_tracker_from_sensor: RigidTransform,
    tip_offset_sensor_mm: ArrayLike,
    T_optical_from_tracker: RigidTransform,
    entry_optical_mm: ArrayLike,
    target_optical_mm: ArrayLike,
    axis_sensor: ArrayLike | None = None,
) -> NeedleTipError:
    """Distance and direction error of the tracked needle to the planned target.

    Args:
        T_tracker_from_sensor: the needle sensor's pose.
        tip_offset_sensor_mm: the tip in the sensor frame (pivot calibration).
        T_optical_from_tracker: the tracker registration.
        entry_optical_mm, target_optical_mm: the planned path.
        axis_sensor: the needle direction in the sensor frame (towards the tip); default: the
            direction of the tip offset (a sensor mounted on the shaft).

    Raises:
        GeometryError: entry == target, or a zero axis.
    """
    entry = np.asarray(entry_optical_mm, dtype=np.float64).reshape(3)
    target = np.asarray(target_optical_mm, dtype=np.float64).reshape(3)
    path = target - entry
    length = float(np.linalg.norm(path))
    if length < 1e-9:
        raise GeometryError("entry and target coincide: the planned path has no direction")
    u = path / length
    tip_s = np.asarray(tip_offset_sensor_mm, dtype=np.float64).reshape(3)
    axis = tip_s if axis_sensor is None else np.asarray(axis_sensor, dtype=np.float64).reshape(3)
    if float(np.linalg.norm(axis)) < 1e-9:
        raise GeometryError("needle axis is zero (give axis_sensor when the tip offset is zero)")
    T = T_optical_from_tracker @ T_tracker_from_sensor
    tip = T.apply(tip_s)
    d = T.apply_vector(axis)
    d = d / np.linalg.norm(d)
    rel = tip - entry
    along = float(rel @ u)
    lateral = float(np.linalg.norm(rel - along * u))
    angle = math.acos(max(-1.0, min(1.0, float(d @ u))))
    return NeedleTipError(tip, float(np.linalg.norm(target - tip)), lateral, length - along, angle)


def reference_motion(
    T_optical_from_tracker: RigidTransform,
    T_tracker_from_reference_at_registration: RigidTransform,
    T_tracker_from_reference_now: RigidTransform,
) -> RigidTransform:
    """The patient's rigid motion since registration, in the optical frame, from a reference sensor.

    A sensor fixed on the patient moves with the skin markers, so its change
    ``T_now_from_registration`` (expressed in the optical frame) is the same rigid change the
    controller otherwise estimates from the markers (seed 000 section 3); it maps a point
    planned at registration time to where it is now: ``p_now = M.apply(p_then)``.
    """
    T_ot = T_optical_from_tracker
    change_tracker = T_tracker_from_reference_now @ T_tracker_from_reference_at_registration.inverse()
    return T_ot @ change_tracker @ T_ot.inverse()
