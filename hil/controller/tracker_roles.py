"""The magnetic tracker's roles during the procedure (``[procedure.tracking]``, issue 7), as the
controller applies them each pair: the patient reference sensor backs up and checks the skin
markers' rigid change, while LOCKed the tracked needle tip is measured against the target, and a
sensor at the target gives the target the path points at (issue 41).

The maths is :mod:`hil.controller.tracker_use` and :mod:`hil.controller.target_sensor`; this module
decides when it applies and writes the session-log records (``reference_*``, ``needle_tracked``,
``target_sensor_*``).
"""

from __future__ import annotations

import math

from hil.controller import events as ev
from hil.controller.estimate import Estimate
from hil.controller.fsm import State
from hil.controller.tracker_use import TrackerUse, entry_disagreement_mm
from hil.session.log import SessionLog


class TrackerRoles:
    """Reference-sensor backup/check and needle tracking (module doc)."""

    def __init__(self, tracker_use: TrackerUse | None, session: SessionLog) -> None:
        self.use = tracker_use
        self.session = session
        self.tracked_needle: dict[str, float] | None = None
        self._reference_in_use = False
        self._reference_disagrees = False
        self._target_sensor_used: bool | None = None

    @property
    def feeds_markers(self) -> bool:
        """Whether a tracker sample takes part in the marker update (a reference sensor backs up
        and checks the skin markers' change; a target sensor's sample around the pair's exposure
        gives the target): then the tracker is read before it."""
        c = None if self.use is None else self.use.cfg
        return c is not None and (c.reference_sensor is not None or c.target_sensor is not None)

    def reference_sensor(self, est: Estimate, state: State) -> None:
        """When the skin markers give no rigid change this pair, the reference sensor's stands in
        (``reference_in_use``); when both give one, a difference at the entry beyond the configured
        bound is logged (``reference_disagreement`` / ``reference_agrees`` on change)."""
        tu = self.use
        if tu is None or tu.cfg.reference_sensor is None or est.patient_reg is None:
            return
        got = tu.reference_change(est.tracker_samples)
        if got is None:
            return
        M, t_ns = got
        entry = est.patient_reg.T_optical_from_image.apply(est.plan.entry_mm).reshape(3)
        if est.T_change_meas is None:
            if tu.cfg.reference_backup:
                est.T_change_meas, est.change_t_ns = M, t_ns
                if not self._reference_in_use:
                    self.session.write(ev.REFERENCE_IN_USE, sensor=tu.cfg.reference_sensor, state=state,
                                       reason="skin markers give no rigid change", sample_t_ns=t_ns)
                self._reference_in_use = True
            return
        if self._reference_in_use:
            self.session.write(ev.REFERENCE_RELEASED, sensor=tu.cfg.reference_sensor, state=state)
            self._reference_in_use = False
        d = entry_disagreement_mm(M, est.T_change_meas, entry)
        disagrees = d > tu.cfg.reference_disagreement_mm
        if disagrees != self._reference_disagrees:
            self._reference_disagrees = disagrees
            self.session.write(ev.REFERENCE_DISAGREEMENT if disagrees else ev.REFERENCE_AGREES,
                               sensor=tu.cfg.reference_sensor, entry_difference_mm=d,
                               limit_mm=tu.cfg.reference_disagreement_mm, state=state)

    def target_sensor(self, est: Estimate, state: State) -> None:
        """With a target sensor, after a pair's change: when the path comes to point at the sensor's
        target, or stops, say so (``target_sensor_in_use``; ``target_sensor_lost`` with why and
        what the path points at instead: the model's target, or the rigid direction)."""
        sensor, steer = est.target_sensor, est.target_steer
        if sensor is None or steer is None:
            return
        used = steer.source == "sensor"
        if used == self._target_sensor_used:
            return
        self._target_sensor_used = used
        if used:
            self.session.write(ev.TARGET_SENSOR_IN_USE, sensor=sensor.name, state=state)
        else:
            instead = "the model's target" if steer.source == "model" else "the rigid direction"
            self.session.write(ev.TARGET_SENSOR_LOST, sensor=sensor.name, state=state,
                               reason=steer.sensor_why_not or steer.fallback, instead=instead)

    def record_reference(self, est: Estimate) -> None:
        """At registration: the reference sensor's pose becomes its reference
        (``reference_sensor_recorded`` with whether it was available)."""
        tu = self.use
        if tu is not None and tu.cfg.reference_sensor is not None:
            ok = tu.record_reference(est.tracker_samples)
            self.session.write(ev.REFERENCE_SENSOR_RECORDED, sensor=tu.cfg.reference_sensor, available=ok)

    def track_needle(self, est: Estimate) -> None:
        """While locked: the tracked needle tip against the planned target as it is now
        (``needle_tracked``); the last sample is kept for the summary."""
        tu = self.use
        path = est.path_optical_now()
        if tu is None or tu.cfg.needle_sensor is None or path is None:
            return
        e = tu.needle_error(est.tracker_samples, path[0], path[1])
        if e is None:
            self.session.write(ev.NEEDLE_TRACKED, sensor=tu.cfg.needle_sensor, available=False)
            return
        self.tracked_needle = {
            "distance_to_target_mm": e.distance_to_target_mm, "lateral_error_mm": e.lateral_error_mm,
            "depth_to_target_mm": e.depth_to_target_mm,
            "direction_error_deg": math.degrees(e.direction_error_rad)}
        self.session.write(ev.NEEDLE_TRACKED, sensor=tu.cfg.needle_sensor, available=True,
                           tip_optical_mm=e.tip_optical_mm, **self.tracked_needle)
