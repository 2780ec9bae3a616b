"""What the built-in plugin registers for the serial magnetic trackers: the driver factories and
the ``hil probe`` device checks.

The top of the package: it imports the configs (:mod:`drivers.tracker_serial.config`, a leaf);
the driver and probe modules are imported when a device is built or probed, so that listing the
drivers (``hil drivers``) does not load them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.interfaces.tracker import PoseTracker
from drivers.tracker_serial.config import AuroraConfig, FlockOfBirdsConfig
from plugins.registry import DriverContext

if TYPE_CHECKING:
    from hil.probe.registry import ProbeRegistry

__all__ = ["AuroraConfig", "FlockOfBirdsConfig", "aurora_factory", "fob_factory", "register_probes"]


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


def register_probes(registry: ProbeRegistry) -> None:
    """The ``hil probe`` device checks of both trackers (called by the built-in plugin's
    ``hil_register_probes``): serial port, baud rate, identity, sensors on the bus."""
    from drivers.tracker_serial.probe_aurora import probe_aurora
    from drivers.tracker_serial.probe_fob import probe_fob

    registry.add("tracker", "fob", probe_fob)
    registry.add("tracker", "aurora", probe_aurora)
