"""Poses from the simulated world: the sensors of a setup's ``[tracker] driver = "sim"``.

The emulator reports, for each device id (FBB address / port handle), the ground-truth pose
``T_tracker_from_sensor`` of a simulated sensor (patient-attached sensors breathe and drift with
the phantom; transmitter-fixed ones stay; flange-attached ones are missing: no robot runs here).
Device ids map to the sim sensors in order, or as given (``--world-sensor 1=reference``).

The simulated world and tracker are built through the driver registry (the plugins' simulated
tracker and world factory), as the core builds them: the emulator imports no driver.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

from hil.clock import MonotonicClock
from hil.config import load_setup
from hil.errors import InputFileError
from hil.geometry.transform import RigidTransform
from plugins.manager import default_registry
from plugins.registry import DriverContext


@runtime_checkable
class _TruthSource(Protocol):
    """A simulated tracker that knows the true pose of its ``sensor_index``-th sensor."""

    def true_pose(self, sensor_index: int, t_ns: int) -> RigidTransform | None: ...


class WorldPoses:
    """A :class:`~emulators.trackersim.poses.PoseSource` backed by the simulated world.

    Raises:
        InputFileError: the setup's tracker is not the simulated one, or a mapped sensor name is
            not one of its sensors.
    """

    def __init__(self, setup_path: str | Path, device_ids: Sequence[str],
                 mapping: Mapping[str, str] | None = None) -> None:
        registry = default_registry()
        setup = load_setup(setup_path, registry=registry)
        info = None if setup.tracker is None else registry.get("tracker", str(setup.tracker.driver))
        if info is None or not info.simulated or registry.world_factory is None:
            raise InputFileError(str(setup_path), 'tracker: needs driver = "sim" (its sensors are what '
                                                  "the emulator reports)")
        self.clock = MonotonicClock()
        ctx = DriverContext(role="tracker", clock=self.clock, limits=setup.safety.motion_limits(),
                            config_dir=setup.config_dir, world=registry.world_factory(setup, self.clock),
                            calibration_path=setup.calibration.stereo)
        tracker = info.factory(setup.tracker, ctx)
        if not isinstance(tracker, _TruthSource):
            raise InputFileError(str(setup_path), f"tracker: driver {info.name!r} gives no true poses")
        self.tracker = tracker
        names = [str(s.name) for s in setup.tracker.sensors]
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
