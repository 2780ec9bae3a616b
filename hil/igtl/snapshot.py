"""What the OpenIGTLink stream carries, computed from the controller's state.

Transform names follow the SlicerIGT convention ``<From>To<To>`` (a ``GuideToImage`` transform
maps points from the guide frame into the image frame, i.e. our ``T_image_from_guide``), so a
Slicer scene built with "OpenIGTLinkIF" shows them with no extra code:

- ``GuideToImage``: the needle guide in the CT frame, where the controller believes it is —
  the robot's reported TCP pose, the closed-loop optical bias, the robot and patient
  registrations and the live rigid change of the patient since registration (seed 000 eq 12
  and section 3): ``T_image_from_guide = T_optical_from_image^-1 @ T_change^-1 @
  T_robot_from_optical^-1 @ T_bias^-1 @ T_robot_from_tcp @ T_tcp_from_guide``.
- ``ImageToOptical``: the patient registration (``T_optical_from_image``, at registration time).
- ``PatientToOptical``: the live patient (``T_change @ T_optical_from_image``).
- ``<Sensor>ToTracker``: each magnetic-tracker sensor that has a pose (``T_tracker_from_sensor``).

Plus a ``Status`` STRING (state, pending confirmation, last reason), a ``Deformation`` STRING
(the body against its registered state, issue 41: the change estimator, the change fit's
rigid residual, the gate's shape residual, each marker's deviation from its reference and its
residual to the rigid fit; :func:`deformation_text`) and a ``Plan`` POINT list (entry and
target, image frame). Units: millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from hil.geometry.transform import RigidTransform

if TYPE_CHECKING:
    from hil.controller.plan_file import ProcedurePlan
    from hil.controller.snapshot import ControllerSnapshot

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class IgtlSnapshot:
    """One set of messages: ``transforms`` (device name -> 4x4 matrix, mm), a status line, and
    named points (image frame, mm)."""

    transforms: dict[str, FloatArray] = field(default_factory=dict)
    status: str = ""
    points: dict[str, FloatArray] = field(default_factory=dict)
    deformation: str = ""


def _sensor_device_name(sensor: str) -> str:
    clean = "".join(ch for ch in sensor.title() if ch.isalnum()) or "Sensor"
    return f"{clean}ToTracker"


def _mm_list(values: FloatArray | None) -> str:
    """Comma-separated millimetres to 2 decimals; ``-`` for an unseen marker (NaN)."""
    if values is None:
        return "-"
    return ",".join(f"{v:.2f}" if np.isfinite(v) else "-" for v in np.asarray(values, dtype=np.float64))


def _mm(value: float | None) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.2f}"


def deformation_text(snap: ControllerSnapshot) -> str:
    """The ``Deformation`` STRING: ``estimator=<name> change_fre_mm=<x> shape_mm=<x>
    deviations_mm=<m0>,<m1>,... residuals_mm=<m0>,...`` — per-marker lists in the registration's
    marker order, ``-`` where a value is unknown (before registration, an unseen marker) — then
    ``target_model=<rigid|surrogate> target_shift_mm=<x> target_turn_deg=<x>`` (the surrogate
    model's last pair; ``-`` without it, or when the pair kept the rigid direction) and
    ``target_source=<sensor|model|->`` (what the path pointed at; only with a target sensor). Empty before
    the patient is registered."""
    if snap.T_optical_from_image is None:
        return ""
    return (f"estimator={snap.change_estimator or '-'} change_fre_mm={_mm(snap.change_fre_mm)} "
            f"shape_mm={_mm(snap.gate_shape_mm)} deviations_mm={_mm_list(snap.marker_deviations_mm)} "
            f"residuals_mm={_mm_list(snap.marker_residuals_mm)} target_model={snap.target_model} "
            f"target_shift_mm={_mm(None if snap.target_fallback else snap.target_shift_mm)} "
            f"target_turn_deg={_mm(None if snap.target_fallback else snap.target_turn_deg)}"
            + ("" if snap.target_source is None else f" target_source={snap.target_source or '-'}"))


def igtl_snapshot(snap: ControllerSnapshot, plan: ProcedurePlan) -> IgtlSnapshot:
    """The messages for one controller snapshot (module doc). ``plan`` gives the Plan points."""
    tf: dict[str, FloatArray] = {}
    if snap.T_image_from_guide is not None:
        tf["GuideToImage"] = snap.T_image_from_guide.as_matrix()
    if snap.T_optical_from_image is not None:
        tf["ImageToOptical"] = snap.T_optical_from_image.as_matrix()
        T_change = snap.T_change_meas if snap.T_change_meas is not None else RigidTransform.identity()
        tf["PatientToOptical"] = (T_change @ snap.T_optical_from_image).as_matrix()
    for name, sample in sorted(snap.tracker.items()):
        if not sample.missing and sample.T_tracker_from_sensor is not None:
            tf[_sensor_device_name(name)] = sample.T_tracker_from_sensor.as_matrix()
    status = f"state={snap.state}"
    if snap.pending:
        status += f" pending={snap.pending}"
    if snap.last_reason:
        status += f" reason={snap.last_reason}"
    points = {"entry": np.asarray(plan.entry_mm, dtype=np.float64).reshape(3),
              "target": np.asarray(plan.target_mm, dtype=np.float64).reshape(3)}
    return IgtlSnapshot(tf, status, points, deformation_text(snap))
