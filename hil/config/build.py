"""Build the devices of a setup through the driver registry (never importing a driver)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from drivers.interfaces.camera import StereoCamera
from drivers.interfaces.lifecycle import Device
from drivers.interfaces.robot import Robot
from drivers.interfaces.tracker import PoseTracker
from hil.clock import Clock, ManualClock, MonotonicClock
from hil.config.setup import SetupConfig
from hil.errors import ConfigError
from hil.log import get_logger
from plugins.registry import DriverContext, DriverRegistry

_log = get_logger(__name__)


@runtime_checkable
class ScenarioWorld(Protocol):
    """What the core may ask of a simulated world (``Devices.world``) without importing it."""

    def request_breath_hold(
        self, duration_s: float, level: float = 0.0, delay_s: float | None = None,
    ) -> float:
        """Ask the simulated patient to hold breath; returns the world time (s) it starts."""
        ...


@runtime_checkable
class RobotFollower(Protocol):
    """A simulated world that can take its robot pose from a non-simulated robot driver (a real
    driver on an emulator, in a mixed setup): the builder attaches the configured robot."""

    def follow_robot(self, robot: Robot) -> None: ...


@dataclass
class Devices:
    """The devices of one setup, CONFIGURED (not opened). ``world`` is the simulated world when
    a simulated driver is used (for scenario requests such as breath-holds), else None."""

    camera: StereoCamera
    robot: Robot
    tracker: PoseTracker | None
    world: object | None = None

    def __iter__(self) -> Iterator[Device]:
        yield self.camera
        yield self.robot
        if self.tracker is not None:
            yield self.tracker

    def open_all(self) -> None:
        """Open every device; on a failure close the ones already opened and re-raise."""
        opened: list[Device] = []
        try:
            for d in self:
                d.open()
                opened.append(d)
        except BaseException:
            for d in reversed(opened):
                d.close()
            raise

    def close_all(self) -> None:
        """Close every device (idempotent), robot first."""
        self.robot.close()
        self.camera.close()
        if self.tracker is not None:
            self.tracker.close()


_EXPECTED: dict[str, type] = {"camera": StereoCamera, "robot": Robot, "tracker": PoseTracker}


def build_devices(
    setup: SetupConfig, clock: Clock, registry: DriverRegistry | None = None, *,
    allow_faults_on_real_robot: bool = False,
) -> Devices:
    """Create the configured devices (not opened), wrapped with the setup's fault schedule.

    Args:
        setup: a validated setup.
        clock: the clock every device timestamps with (ManualClock for fast simulation).
        registry: the drivers (default: every installed plugin).
        allow_faults_on_real_robot: fault injection on a real robot is refused unless True.

    Raises:
        ConfigError: a driver is unknown/unavailable, a factory returned the wrong kind of device,
            faults target a real robot without permission, or patient faults a
            setup with no simulated device.
    """
    if registry is None:
        from plugins.manager import default_registry

        registry = default_registry()
    sections = setup.device_sections()
    infos = {role: registry.get(role, str(cfg.driver)) for role, cfg in sections.items()}  # type: ignore[attr-defined]
    world: object | None = None
    if any(i.simulated for i in infos.values()):
        if registry.world_factory is None:
            raise ConfigError("setup", ["simulation: no plugin provides the simulated world"])
        world = registry.world_factory(setup, clock)
    patient = sorted({f.kind.value for f in setup.faults if f.device == "patient"})
    if patient and world is None:
        raise ConfigError("setup", [f"faults: {', '.join(patient)} happen to the patient, which only the "
                                    "simulated world can play; this setup has no simulated device"])
    cal = setup.calibration.stereo
    built: dict[str, Any] = {}
    for role, cfg in sections.items():
        info = infos[role]
        ctx = DriverContext(role=role, clock=clock, limits=setup.safety.motion_limits(),
                            config_dir=setup.config_dir,
                            world=world, calibration_path=cal)
        try:
            device = info.factory(cfg, ctx)
        except ImportError as exc:
            raise ConfigError("setup", [f"{role}.driver: {info.name} ({info.origin}) cannot be built "
                                        f"here: {exc}"]) from exc
        if not isinstance(device, _EXPECTED[role]):
            raise ConfigError("setup", [f"{role}.driver: {info.name} factory returned "
                                        f"{type(device).__name__}, not a {_EXPECTED[role].__name__}"])
        unwrapped = device
        faults = [f for f in setup.faults if f.device == role]
        if faults:
            # transport faults go to an emulator's fault channel (the wrapper refuses them without one)
            wrapped = [f for f in faults if f.transport_command is None]
            if role == "robot" and not info.simulated and wrapped and not allow_faults_on_real_robot:
                raise ConfigError("setup", ["faults: fault injection on a real robot needs "
                                            "allow_faults_on_real_robot"])
            if role == "robot" and info.simulated and len(wrapped) < len(faults):
                raise ConfigError("setup", ["faults: transport faults need a robot driver on the UR "
                                            "emulator (tools/ursim); robot driver "
                                            f"{info.name!r} is simulated"])
            if registry.fault_wrapper is None:
                raise ConfigError("setup", ["faults: no plugin provides fault injection"])
            device = registry.fault_wrapper(device, role, faults, clock, setup.fault_channel)
        _log.info("device_built", role=role, driver=info.name, origin=info.origin, faults=len(faults))
        built[role] = device
        if (role == "robot" and not info.simulated and isinstance(world, RobotFollower)
                and isinstance(unwrapped, Robot)):
            world.follow_robot(unwrapped)  # the simulated camera sees the real arm's flange markers
    return Devices(camera=built["camera"], robot=built["robot"], tracker=built.get("tracker"), world=world)



def clock_for(setup: SetupConfig, registry: DriverRegistry | None = None) -> Clock:
    """The clock a setup runs on: a :class:`ManualClock` when every device is simulated and
    ``[simulation] real_time`` is false (faster than real time, reproducible), else the wall
    clock (:class:`MonotonicClock`)."""
    if registry is None:
        from plugins.manager import default_registry

        registry = default_registry()
    all_sim = all(registry.get(role, str(cfg.driver)).simulated  # type: ignore[attr-defined]
                  for role, cfg in setup.device_sections().items())
    if all_sim and not setup.simulation.real_time:
        return ManualClock()
    return MonotonicClock()
