"""The built-in drivers and their ``hil probe`` checks, registered through the same hooks as
third-party plugins.

Simulated drivers are imported directly. The real drivers (written in their own packages) are
picked up from :data:`REAL_DRIVERS`, a table of dotted paths: each driver package exposes a
``plugin`` module holding the driver's pydantic model (imported from the package's ``config``
module, a leaf) and its factory ``(config, ctx) -> Device``.
A driver whose module or attributes cannot be imported is registered as *unavailable* with the
reason, so ``hil drivers`` shows it and a setup naming it fails with that reason.

The device probes (``hil probe``'s wire-level checks) live in the same driver packages, next to
the protocol code whose constants they use: each ``plugin`` module of :data:`PROBE_MODULES` has a
``register_probes(registry)`` that :func:`hil_register_probes` calls.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any, NamedTuple

from hil.log import get_logger
from plugins.hookspecs import hookimpl
from plugins.registry import DriverKind, DriverRegistry

if TYPE_CHECKING:
    from hil.probe.registry import ProbeRegistry

_log = get_logger(__name__)


class RealDriver(NamedTuple):
    """Where a real driver lives: ``module`` exposes ``model`` (pydantic) and ``factory``."""

    kind: DriverKind
    name: str
    module: str
    model: str
    factory: str
    description: str


REAL_DRIVERS: tuple[RealDriver, ...] = (
    RealDriver("robot", "ur_rtde", "drivers.ur_rtde.plugin", "UrRtdeConfig", "factory",
               "Universal Robots UR3 / UR3e over RTDE (ur-rtde)"),
    RealDriver("tracker", "fob", "drivers.tracker_serial.plugin", "FlockOfBirdsConfig",
               "fob_factory", "Ascension Flock of Birds magnetic tracker over a serial port"),
    RealDriver("tracker", "aurora", "drivers.tracker_serial.plugin", "AuroraConfig",
               "aurora_factory", "NDI Aurora electromagnetic tracker over a serial port"),
    RealDriver("camera", "aravis", "drivers.camera.plugin", "AravisCameraConfig",
               "aravis_factory", "two GigE Vision / USB3 Vision cameras through Aravis"),
    RealDriver("camera", "v4l2", "drivers.camera.plugin", "V4l2CameraConfig",
               "v4l2_factory", "two V4L2 (UVC) cameras through OpenCV"),
    RealDriver("camera", "replay", "drivers.camera.plugin", "ReplayCameraConfig",
               "replay_factory", "replay of a recorded stereo session"),
)


#: Driver packages whose ``plugin`` module registers device probes (``register_probes``).
PROBE_MODULES: tuple[str, ...] = ("drivers.ur_rtde.plugin", "drivers.tracker_serial.plugin",
                                  "drivers.camera.plugin")


def _register_real(registry: DriverRegistry, spec: RealDriver) -> None:
    try:
        module = importlib.import_module(spec.module)
        model: Any = getattr(module, spec.model)
        factory: Any = getattr(module, spec.factory)
    except ImportError as exc:
        registry.add_unavailable(spec.kind, spec.name, spec.module, f"cannot import {spec.module}: {exc}")
        return
    except AttributeError as exc:
        registry.add_unavailable(spec.kind, spec.name, spec.module, f"{spec.module}: {exc}")
        return
    registry.add(spec.kind, spec.name, model, factory, description=spec.description)


@hookimpl
def hil_register_drivers(registry: DriverRegistry) -> None:
    """Register the simulated drivers, the real ones that import here, the simulated world and
    the fault wrapper."""
    from drivers.faults import wrap_device
    from drivers.sim.camera import SimCameraConfig, make_sim_camera
    from drivers.sim.robot import SimRobotConfig, make_sim_robot
    from drivers.sim.tracker import SimTrackerConfig, make_sim_tracker
    from drivers.sim.world import world_from_setup

    registry.add("camera", "sim", SimCameraConfig, make_sim_camera, simulated=True,
                 description="stereo pair rendered from the simulated world (ring markers)")
    registry.add("robot", "sim", SimRobotConfig, make_sim_robot, simulated=True,
                 description="simulated UR3: kinematics, joint/speed limits, servo lag, protective stop")
    registry.add("tracker", "sim", SimTrackerConfig, make_sim_tracker, simulated=True,
                 description="simulated magnetic tracker: sensor poses with noise and field distortion")
    registry.set_world_factory(world_from_setup)
    registry.set_fault_wrapper(wrap_device)
    for spec in REAL_DRIVERS:
        _register_real(registry, spec)


@hookimpl
def hil_register_probes(registry: ProbeRegistry) -> None:
    """Register the device probes of the real driver packages. A package that does not import
    here is skipped (``hil drivers`` already says why its drivers are unavailable)."""
    for name in PROBE_MODULES:
        try:
            module: Any = importlib.import_module(name)
        except ImportError as exc:
            _log.debug("probe_module_unavailable", module=name, error=str(exc))
            continue
        module.register_probes(registry)
