"""Hook specifications of the ``hil`` project (pluggy).

Every hook is named ``hil_*`` and called with keyword arguments only. A plugin is a module or
object with functions decorated by :data:`hookimpl`; third-party packages expose it through the
entry-point group ``hil`` (``[project.entry-points.hil] myname = "mypkg.hil_plugin"``). The
built-in drivers register through the very same hook (``plugins.builtin``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

import pluggy

from plugins.registry import DriverRegistry

if TYPE_CHECKING:  # not imported at run time: loading the plugin manager must not load the probe
    from hil.controller.fsm import FireResult
    from hil.controller.snapshot import ControllerSnapshot
    from hil.probe.registry import ProbeRegistry

PROJECT_NAME = "hil"

_F = TypeVar("_F", bound=Callable[..., Any])

hookspec: Callable[[_F], _F] = pluggy.HookspecMarker(PROJECT_NAME)
hookimpl: Callable[[_F], _F] = pluggy.HookimplMarker(PROJECT_NAME)


# ---------------------------------------------------------------- driver registration
@hookspec
def hil_register_drivers(registry: DriverRegistry) -> None:
    """Add drivers to ``registry`` with ``registry.add(kind, name, config_model, factory, origin)``.

    Called once per registry, for every plugin (built-ins included); results are ignored. A
    plugin that knows of a driver it cannot load here calls ``registry.add_unavailable(...)`` so
    that ``hil drivers`` can say why. The config model must be a pydantic model with
    ``driver: Literal["<name>"]``, ``extra="forbid"``, frozen; the factory returns the device in
    the CONFIGURED state and must not open it.
    """


# ---------------------------------------------------------------- device probes (hil probe)
@hookspec
def hil_register_probes(registry: ProbeRegistry) -> None:
    """Add wire-level device checks for ``hil probe`` with ``registry.add(kind, driver, run)``.

    Called once per probe registry, for every plugin; results are ignored. ``run(checklist,
    config, ctx)`` adds its steps with ``checklist.step(...)`` and closes what it opened (the
    contract is in :mod:`hil.probe.registry`; docs/probe.md shows an example). A driver without a
    probe still gets the driver-level checks (build, open, stream). Wire constants belong to the
    driver package that registers the probe, next to its protocol code.
    """


# ---------------------------------------------------------------- runtime observers
@hookspec
def hil_on_tick(snapshot: ControllerSnapshot) -> None:
    """Called in the controller's thread after every control tick with a frozen snapshot.

    Contract: return quickly (a few ms at most: the next tick waits), never command a device
    and never block on I/O (hand work to your own thread). An exception is logged
    (``observer_failed``, once per distinct error) and never reaches the control loop; the other
    plugins are still called. The built-in OpenIGTLink stream is a plugin on this hook.
    """


@hookspec
def hil_on_transition(transition: FireResult, snapshot: ControllerSnapshot) -> None:
    """Called in the controller's thread after every applied state transition (the new state's
    entry action has run) with the transition and a frozen snapshot. Same contract as
    :func:`hil_on_tick`."""
