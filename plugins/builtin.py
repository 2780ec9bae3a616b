"""The built-in drivers, registered through the same hook as third-party plugins.

Simulated drivers are imported directly. The real drivers (written in their own packages) are
picked up from :data:`REAL_DRIVERS`, a table of dotted paths: each driver package exposes a
``plugin`` module holding the driver's pydantic model (imported from the package's ``config``
module, a leaf) and its factory ``(config, ctx) -> Device``.
A driver whose module or attributes cannot be imported is registered as *unavailable* with the
reason, so ``hil drivers`` shows it and a setup naming it fails with that reason.
"""

from __future__ import annotations

import importlib
from typing import Any, NamedTuple

from plugins.hookspecs import hookimpl
from plugins.registry import DriverKind, DriverRegistry


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
