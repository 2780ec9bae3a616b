"""The OpenIGTLink stream as a runtime plugin: ``hil_on_tick`` publishes every snapshot to the
server (which rate-limits and never blocks). Registered for a run by ``hil run`` and the console
when ``[igtl] enabled``."""

from __future__ import annotations

from typing import TYPE_CHECKING

from hil.igtl.snapshot import igtl_snapshot
from plugins.hookspecs import hookimpl

if TYPE_CHECKING:
    from hil.controller.plan_file import ProcedurePlan
    from hil.controller.snapshot import ControllerSnapshot
    from hil.igtl.server import IgtlServer

#: The plugin's name in the run's plugin manager.
PLUGIN_NAME = "openigtlink"


class IgtlPlugin:
    """Streams each tick's snapshot through ``server`` (a started :class:`IgtlServer`)."""

    def __init__(self, server: IgtlServer, plan: ProcedurePlan) -> None:
        self.server, self.plan = server, plan

    @hookimpl
    def hil_on_tick(self, snapshot: ControllerSnapshot) -> None:
        self.server.publish(igtl_snapshot(snapshot, self.plan), snapshot.t_ns)
