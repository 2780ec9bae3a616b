"""What the built-in plugin registers for the UR arm over RTDE: the driver factory and the
``hil probe`` device checks.

The top of the package: it imports the config (:mod:`drivers.ur_rtde.config`, a leaf); the driver
(and the ur-rtde library) and the probe are imported when the device is built or probed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.interfaces.robot import Robot
from drivers.ur_rtde.config import UrRtdeConfig, UrRtdeRobotConfig
from plugins.registry import DriverContext

if TYPE_CHECKING:
    from hil.probe.registry import ProbeRegistry

__all__ = ["UrRtdeConfig", "UrRtdeRobotConfig", "factory", "register_probes"]


def factory(config: UrRtdeRobotConfig, ctx: DriverContext) -> Robot:
    """Registered as robot driver ``ur_rtde``: the arm, CONFIGURED (``open()`` connects)."""
    from drivers.ur_rtde.robot import UrRtdeRobot

    return UrRtdeRobot(ctx.role, ctx.limits, config, ctx.clock)


def register_probes(registry: ProbeRegistry) -> None:
    """The ``hil probe`` device checks of the UR (called by the built-in plugin's
    ``hil_register_probes``): read-only RTDE and dashboard checks that replace the driver-level
    ones, since opening the driver would start a control script on the robot."""
    from drivers.ur_rtde.probe import probe_ur

    registry.add("robot", "ur_rtde", probe_ur, driver_checks=False)
