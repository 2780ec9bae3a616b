"""Hook specifications of the ``hil`` project (pluggy).

Every hook is named ``hil_*`` and called with keyword arguments only. A plugin is a module or
object with functions decorated by :data:`hookimpl`; third-party packages expose it through the
entry-point group ``hil`` (``[project.entry-points.hil] myname = "mypkg.hil_plugin"``). The
built-in drivers register through the very same hook (``plugins.builtin``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import pluggy

from plugins.registry import DriverRegistry

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
