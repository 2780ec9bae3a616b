"""What the built-in plugin registers for the UR arm over RTDE: the driver factory.

The top of the package: it imports the config (:mod:`drivers.ur_rtde.config`, a leaf) and builds
the driver, whose module (and the ur-rtde library) is imported when the device is built.
"""

from __future__ import annotations

from drivers.interfaces.robot import Robot
from drivers.ur_rtde.config import UrRtdeConfig, UrRtdeRobotConfig
from plugins.registry import DriverContext

__all__ = ["UrRtdeConfig", "UrRtdeRobotConfig", "factory"]


def factory(config: UrRtdeRobotConfig, ctx: DriverContext) -> Robot:
    """Registered as robot driver ``ur_rtde``: the arm, CONFIGURED (``open()`` connects)."""
    from drivers.ur_rtde.robot import UrRtdeRobot

    return UrRtdeRobot(ctx.role, ctx.limits, config, ctx.clock)
