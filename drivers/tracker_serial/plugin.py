"""What the built-in plugin registers for the serial magnetic trackers: the driver factories.

The top of the package: it imports the configs (:mod:`drivers.tracker_serial.config`, a leaf)
and builds the drivers, whose modules are imported when a device is built, so that listing the
drivers (``hil drivers``) does not load them.
"""

from __future__ import annotations

from drivers.interfaces.tracker import PoseTracker
from drivers.tracker_serial.config import AuroraConfig, FlockOfBirdsConfig
from plugins.registry import DriverContext

__all__ = ["AuroraConfig", "FlockOfBirdsConfig", "aurora_factory", "fob_factory"]


def fob_factory(config: FlockOfBirdsConfig, ctx: DriverContext) -> PoseTracker:
    """Registered as tracker driver ``fob``: a :class:`~drivers.tracker_serial.fob.FlockOfBirdsTracker`,
    CONFIGURED (``open()`` resets the Bird and starts reading)."""
    from drivers.tracker_serial.fob import FlockOfBirdsTracker

    return FlockOfBirdsTracker(config, name=ctx.role, clock=ctx.clock)


def aurora_factory(config: AuroraConfig, ctx: DriverContext) -> PoseTracker:
    """Registered as tracker driver ``aurora``: an :class:`~drivers.tracker_serial.aurora.AuroraTracker`,
    CONFIGURED (``open()`` resets the Aurora and starts tracking)."""
    from drivers.tracker_serial.aurora import AuroraTracker

    return AuroraTracker(config, name=ctx.role, clock=ctx.clock)
