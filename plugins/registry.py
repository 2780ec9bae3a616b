"""The driver registry: (kind, name) -> config model + factory, filled by ``hil_register_drivers``.

The core validates each ``[camera]``/``[robot]``/``[tracker]`` section of a setup against the model
registered for its ``driver`` and builds the device with the registered factory; it never imports
a concrete driver. Besides drivers, a plugin may register the *world factory* (the shared
simulated world that simulated drivers observe) and the *fault wrapper* (which decorates any
device with a fault schedule), both provided by the built-in plugin.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

from pydantic import BaseModel

from drivers.interfaces.lifecycle import Device
from drivers.interfaces.robot import MotionLimits
from hil.clock import Clock
from hil.errors import HilError

DriverKind = Literal["camera", "robot", "tracker"]
DRIVER_KINDS: tuple[str, ...] = get_args(DriverKind)

DriverFactory = Callable[[Any, "DriverContext"], Device]
#: (setup, clock) -> the shared simulated world (an opaque object to the core).
WorldFactory = Callable[[Any, Clock], object]
#: (device, role, faults, clock, fault_channel) -> a device with the same interface that injects
#: the faults; ``fault_channel`` is the setup's ``[fault_channel]`` (or None), where faults with
#: ``transport`` go.
FaultWrapper = Callable[[Device, str, Sequence[Any], Clock, Any], Device]


class RegistryError(HilError, ValueError):
    """A plugin registered something invalid (duplicate name, bad model, unknown kind)."""


@dataclass(frozen=True)
class DriverContext:
    """What a driver factory gets besides its own validated config.

    Attributes:
        role: the setup section the device fills (``camera``, ``robot``, ``tracker``); used as
            the device name in errors.
        clock: the clock the controller uses; every timestamp a driver produces is on it.
        limits: the setup's hard motion limits (robots must pass them to ``Robot.__init__``).
        config_dir: directory of the setup file (relative paths are already resolved against it).
        world: the shared simulated world when any simulated device is configured, else None.
        calibration_path: the setup's stereo calibration file (``[calibration] stereo``) or None.
    """

    role: str
    clock: Clock
    limits: MotionLimits
    config_dir: Path
    world: object | None = None
    calibration_path: Path | None = None


@dataclass(frozen=True)
class DriverInfo:
    """One registered driver.

    Attributes:
        kind: ``camera``, ``robot`` or ``tracker``.
        name: the value of ``driver = "..."`` that selects it.
        config_model: pydantic model of its section (has ``driver: Literal[name]``).
        factory: ``(config, ctx) -> Device``; the device is returned CONFIGURED (not opened).
        origin: who registered it (``builtin`` or the plugin's name).
        simulated: True for drivers that observe the shared simulated world.
        description: one line for ``hil drivers``.
    """

    kind: str
    name: str
    config_model: type[BaseModel]
    factory: DriverFactory
    origin: str = "builtin"
    simulated: bool = False
    description: str = ""


@dataclass(frozen=True)
class UnavailableDriver:
    """A driver a plugin knows of but cannot load here (module missing or failing to import)."""

    kind: str
    name: str
    module: str
    reason: str
    origin: str = "builtin"


class DriverRegistry:
    """Drivers by (kind, name). Filled through the ``hil_register_drivers`` hook."""

    def __init__(self) -> None:
        self._drivers: dict[tuple[str, str], DriverInfo] = {}
        self._unavailable: dict[tuple[str, str], UnavailableDriver] = {}
        self.world_factory: WorldFactory | None = None
        self.fault_wrapper: FaultWrapper | None = None

    def add(
        self,
        kind: DriverKind,
        name: str,
        config_model: type[BaseModel],
        factory: DriverFactory,
        origin: str = "builtin",
        *,
        simulated: bool = False,
        description: str = "",
    ) -> None:
        """Register a driver.

        Raises:
            RegistryError: unknown kind, a (kind, name) already registered, or a config model
                without ``driver`` field / not forbidding extra keys.
        """
        if kind not in DRIVER_KINDS:
            raise RegistryError(f"{origin}: unknown driver kind {kind!r}; use one of {DRIVER_KINDS}")
        if not (isinstance(config_model, type) and issubclass(config_model, BaseModel)):  # type: ignore[redundant-expr]
            raise RegistryError(f"{origin}: {kind} driver {name!r}: config_model must be a pydantic model")
        if "driver" not in config_model.model_fields:
            raise RegistryError(f"{origin}: {kind} driver {name!r}: config model has no 'driver' field")
        if config_model.model_config.get("extra") != "forbid":
            raise RegistryError(f"{origin}: {kind} driver {name!r}: config model must set extra='forbid'")
        literal = get_args(config_model.model_fields["driver"].annotation)
        if name not in literal:
            raise RegistryError(
                f"{origin}: {kind} driver {name!r}: config model's driver field must be Literal[{name!r}]")
        key = (kind, name)
        if key in self._drivers:
            raise RegistryError(
                f"{origin}: {kind} driver {name!r} already registered by {self._drivers[key].origin}")
        self._unavailable.pop(key, None)
        self._drivers[key] = DriverInfo(kind, name, config_model, factory, origin, simulated, description)

    def add_unavailable(
        self, kind: str, name: str, module: str, reason: str, origin: str = "builtin",
    ) -> None:
        """Record a driver that could not be loaded (shown by ``hil drivers``; configs naming it
        fail with ``reason``)."""
        if (kind, name) not in self._drivers:
            self._unavailable[(kind, name)] = UnavailableDriver(kind, name, module, reason, origin)

    def set_world_factory(self, factory: WorldFactory) -> None:
        self.world_factory = factory

    def set_fault_wrapper(self, wrapper: FaultWrapper) -> None:
        self.fault_wrapper = wrapper

    def get(self, kind: str, name: str) -> DriverInfo:
        """The driver, or RegistryError naming the known ones (or why it is unavailable)."""
        try:
            return self._drivers[(kind, name)]
        except KeyError:
            pass
        if (kind, name) in self._unavailable:
            u = self._unavailable[(kind, name)]
            raise RegistryError(f"{kind} driver {name!r} is not available here: {u.reason}")
        raise RegistryError(f"unknown {kind} driver {name!r}; known: {self.names(kind)}")

    def names(self, kind: str) -> list[str]:
        return sorted(n for (k, n) in self._drivers if k == kind)

    def drivers(self) -> list[DriverInfo]:
        return [self._drivers[k] for k in sorted(self._drivers)]

    def unavailable(self) -> list[UnavailableDriver]:
        return [self._unavailable[k] for k in sorted(self._unavailable)]
