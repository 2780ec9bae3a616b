"""The magnetic tracker in the procedure (issue 7; seed 003 clinical step 5).

Three uses, all in the optical frame (mm, rad), through the tracker registration
``T_optical_from_tracker``:

- the tracked needle tip against the planned target while LOCKed
  (:func:`hil.tracking.needle.needle_tip_error`: distance, lateral and depth error, direction);
- a patient reference sensor: its rigid change since registration
  (:func:`hil.tracking.needle.reference_motion`) is the patient's change the controller otherwise
  estimates from the skin markers (seed 000 section 3); it stands in for them when they cannot
  give it (occluded) and is compared with them when both can;
- a sensor at the target: the target it measures is where the path points
  (:mod:`hil.controller.target_sensor`).

A sensor sample is usable when it is not missing and has a pose. Nothing here blocks or talks
to a device: the controller hands in the samples it read this tick.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from drivers.interfaces.tracker import TrackerSample
from hil.controller.config import TrackingConfig
from hil.controller.target_sensor import TargetSensor
from hil.geometry.transform import FloatArray, RigidTransform
from hil.tracking.needle import NeedleTipError, needle_tip_error, reference_motion


def usable(samples: Mapping[str, TrackerSample], name: str | None) -> TrackerSample | None:
    """The named sensor's sample when it has a pose, else None."""
    if name is None:
        return None
    s = samples.get(name)
    if s is None or s.missing or s.T_tracker_from_sensor is None:
        return None
    return s


@dataclass
class TrackerUse:
    """The tracker configuration of a procedure and the reference pose taken at registration.

    Args:
        cfg: ``[procedure.tracking]``.
        T_optical_from_tracker: the tracker registration (mm).
    """

    cfg: TrackingConfig
    T_optical_from_tracker: RigidTransform
    T_tracker_from_reference_at_registration: RigidTransform | None = None

    @property
    def wanted(self) -> bool:
        """Whether any sensor is configured for use."""
        c = self.cfg
        return c.needle_sensor is not None or c.reference_sensor is not None or c.target_sensor is not None

    def target_sensor(self) -> TargetSensor | None:
        """The target sensor's history (hil/controller/target_sensor.py), or None when none is
        configured."""
        c = self.cfg
        if c.target_sensor is None:
            return None
        return TargetSensor(c.target_sensor, np.asarray(c.target_sensor_offset_mm, dtype=np.float64),
                            c.target_sensor_max_age_ms / 1e3, self.T_optical_from_tracker)

    def record_reference(self, samples: Mapping[str, TrackerSample]) -> bool:
        """Take the reference sensor's pose as the registration-time reference (call when the
        patient registration is made). Returns whether a pose was available."""
        s = usable(samples, self.cfg.reference_sensor)
        self.T_tracker_from_reference_at_registration = None if s is None else s.T_tracker_from_sensor
        return s is not None

    def reference_change(self, samples: Mapping[str, TrackerSample]) -> tuple[RigidTransform, int] | None:
        """(the patient's rigid change since registration from the reference sensor, optical
        frame; the sample time, ns), or None without a registration-time or current pose."""
        ref = self.T_tracker_from_reference_at_registration
        s = usable(samples, self.cfg.reference_sensor)
        if ref is None or s is None or s.T_tracker_from_sensor is None:
            return None
        return reference_motion(self.T_optical_from_tracker, ref, s.T_tracker_from_sensor), s.t_ns

    def needle_error(self, samples: Mapping[str, TrackerSample], entry_optical_mm: FloatArray,
                     target_optical_mm: FloatArray) -> NeedleTipError | None:
        """The tracked needle tip against the path (as it is now, optical frame), or None when
        the needle sensor has no pose.

        Raises:
            GeometryError: entry == target, or a zero needle axis.
        """
        s = usable(samples, self.cfg.needle_sensor)
        if s is None or s.T_tracker_from_sensor is None:
            return None
        c = self.cfg
        return needle_tip_error(s.T_tracker_from_sensor, np.asarray(c.needle_tip_sensor_mm),
                                self.T_optical_from_tracker, entry_optical_mm, target_optical_mm,
                                None if c.needle_axis_sensor is None else np.asarray(c.needle_axis_sensor))


def entry_disagreement_mm(a: RigidTransform, b: RigidTransform, entry_optical_mm: FloatArray) -> float:
    """How differently two rigid changes move the entry point (mm)."""
    p = np.asarray(entry_optical_mm, dtype=np.float64).reshape(1, 3)
    return float(np.linalg.norm(a.apply(p) - b.apply(p)))
