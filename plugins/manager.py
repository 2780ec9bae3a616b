"""The plugin manager: built-ins and third-party plugins, loaded the same way.

``HilPlugins()`` creates ``pluggy.PluginManager("hil")``, adds :mod:`plugins.hookspecs`, loads
every plugin of the entry-point group ``hil`` (the built-ins are declared there too:
``builtin = "plugins.builtin"``), falls back to importing ``plugins.builtin`` by name when the
distribution metadata is missing (running from a source tree that was never installed), then
runs ``check_pending()`` so that a misspelt hook fails at start-up. The typed facade
(:meth:`HilPlugins.driver_registry`, :meth:`HilPlugins.probe_registry`) is what the rest of the
code calls.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

import pluggy

from hil.errors import HilError
from hil.log import get_logger
from plugins import hookspecs
from plugins.registry import DriverRegistry

if TYPE_CHECKING:
    from hil.probe.registry import ProbeRegistry

BUILTIN_PLUGIN_NAME = "builtin"
BUILTIN_PLUGIN_MODULE = "plugins.builtin"  # loaded by name: the core must not import it statically

_log = get_logger(__name__)


class PluginError(HilError):
    """A plugin could not be loaded or implements an unknown hook."""


class HilPlugins:
    """Typed facade over the ``hil`` plugin manager.

    Args:
        load_entry_points: load the entry-point group ``hil`` (built-ins and third parties).
        plugins: extra plugin objects registered after the entry points, as ``(name, plugin)``
            (tests use this for a third-party plugin that is not installed).

    Raises:
        PluginError: an entry point fails to import, or a plugin defines an unknown ``hil_`` hook.
    """

    def __init__(
        self, *, load_entry_points: bool = True, plugins: Iterable[tuple[str, object]] = (),
    ) -> None:
        self.manager = pluggy.PluginManager(hookspecs.PROJECT_NAME)
        self.manager.add_hookspecs(hookspecs)
        if load_entry_points:
            try:
                self.manager.load_setuptools_entrypoints(hookspecs.PROJECT_NAME)
            except Exception as exc:
                raise PluginError(f"loading entry points of group 'hil' failed: {exc!r}") from exc
        if self.manager.get_plugin(BUILTIN_PLUGIN_NAME) is None:
            builtin = importlib.import_module(BUILTIN_PLUGIN_MODULE)
            if not self.manager.is_registered(builtin):
                self.manager.register(builtin, name=BUILTIN_PLUGIN_NAME)
        for name, plugin in plugins:
            self.register(plugin, name)
        self._check()

    def register(self, plugin: object, name: str) -> None:
        """Register one more plugin and re-validate the hooks."""
        try:
            self.manager.register(plugin, name=name)
        except ValueError as exc:
            raise PluginError(f"plugin {name!r}: {exc}") from exc
        self._check()

    def _check(self) -> None:
        try:
            self.manager.check_pending()
        except pluggy.PluginValidationError as exc:
            raise PluginError(f"plugin {exc.plugin!r}: {exc}") from exc

    def plugin_names(self) -> list[str]:
        """Names of the registered plugins (entry-point names, ``builtin`` …)."""
        return sorted(str(n) for n, _ in self.manager.list_name_plugin())

    def origin_of(self, plugin: object) -> str:
        name = self.manager.get_name(plugin)
        return name if name is not None else repr(plugin)

    def driver_registry(self) -> DriverRegistry:
        """A fresh registry filled by every plugin's ``hil_register_drivers``."""
        registry = DriverRegistry()
        self.manager.hook.hil_register_drivers(registry=registry)
        _log.debug("drivers_registered", count=len(registry.drivers()),
                   unavailable=len(registry.unavailable()))
        return registry

    def probe_registry(self) -> ProbeRegistry:
        """A fresh registry of device probes filled by every plugin's ``hil_register_probes``."""
        from hil.probe.registry import ProbeRegistry

        registry = ProbeRegistry()
        self.manager.hook.hil_register_probes(registry=registry)
        _log.debug("probes_registered", count=len(registry.probes()))
        return registry


    def implementations(self, hook: str) -> list[tuple[str, Callable[..., Any]]]:
        """Each plugin's implementation of ``hook``, as ``(plugin name, function)``, in pluggy's
        call order (for callers that isolate every plugin's call, e.g. the runtime observers)."""
        caller = getattr(self.manager.hook, hook)
        return [(impl.plugin_name, impl.function) for impl in reversed(caller.get_hookimpls())]


def default_registry() -> DriverRegistry:
    """The registry of every installed plugin (entry points, built-in fallback)."""
    return HilPlugins().driver_registry()
