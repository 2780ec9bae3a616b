"""Poses from the simulated world: the sensors of a setup's ``[tracker] driver = "sim"``.

The emulator reports, for each device id (FBB address / port handle), the ground-truth pose
``T_tracker_from_sensor`` of a simulated sensor (patient-attached sensors breathe and drift with
the phantom; transmitter-fixed ones stay; flange-attached ones are missing: no robot runs here).
Device ids map to the sim sensors in order, or as given (``--world-sensor 1=reference``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from drivers.sim.tracker import SimTracker, SimTrackerConfig
from drivers.sim.world import world_from_setup
from hil.clock import MonotonicClock
from hil.config import load_setup
from hil.errors import InputFileError
from hil.geometry.transform import RigidTransform


class WorldPoses:
    """A :class:`~emulators.trackersim.poses.PoseSource` backed by the simulated world."""

    def __init__(self, setup_path: str | Path, device_ids: Sequence[str],
                 mapping: Mapping[str, str] | None = None) -> None:
        setup = load_setup(setup_path)
        if not isinstance(setup.tracker, SimTrackerConfig):
            raise InputFileError(str(setup_path), 'tracker: needs driver = "sim" (its sensors are what '
                                                  "the emulator reports)")
        self.clock = MonotonicClock()
        self.tracker = SimTracker("tracker", setup.tracker, self.clock, world_from_setup(setup, self.clock))
        names = [s.name for s in setup.tracker.sensors]
        pairs = dict(mapping) if mapping else dict(zip(device_ids, names, strict=False))
        self.index: dict[str, int] = {}
        for device_id, name in pairs.items():
            if name not in names:
                raise InputFileError(str(setup_path), f"tracker.sensors: no sensor {name!r} (have {names})")
            self.index[device_id] = names.index(name)

    def pose(self, sensor: str, t_s: float) -> RigidTransform | None:
        k = self.index.get(sensor)
        if k is None:
            return None
        return self.tracker.true_pose(k, self.clock.now_ns())
