"""Device probes by (kind, driver): the wire-level checks ``hil probe`` runs for a driver.

Filled through the plugin hook ``hil_register_probes(registry)`` (:mod:`plugins.hookspecs`): the
built-in plugin registers the probes the real driver packages define next to their protocol code
(``drivers.<package>.plugin.register_probes``), and a third-party driver registers its own the
same way. The core never imports a driver: it looks the probe up here by the ``driver`` name of
the setup section.

A probe is a function ``run(checklist, config, ctx) -> None`` that adds its steps with
``checklist.step(name, fn, ...)`` (each bounded by a timeout, stopping at the first failure; see
:class:`hil.probe.runner.Checklist`), where ``config`` is the device section validated against the
driver's own model and ``ctx`` the :class:`hil.probe.context.ProbeContext`. It must not raise for
a device problem (a step raising :class:`hil.probe.runner.Finding` is how a check fails); it must
close whatever it opened before it returns. After it, unless it failed or was registered with
``driver_checks=False``, the core builds and opens the driver and checks its stream.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from plugins.registry import DRIVER_KINDS, RegistryError

if TYPE_CHECKING:
    from hil.probe.context import ProbeContext
    from hil.probe.runner import Checklist

#: ``(checklist, config, ctx) -> None``: adds the device's wire-level steps to ``checklist``.
ProbeFunction = Callable[["Checklist", Any, "ProbeContext"], None]


@dataclass(frozen=True)
class DeviceProbe:
    """One registered probe.

    Attributes:
        kind: ``camera``, ``robot`` or ``tracker``.
        driver: the ``driver = "..."`` name it probes.
        run: the probe function (see the module doc).
        driver_checks: after ``run``, also build and open the driver and check its stream (False
            when opening the driver would do what a probe must not, e.g. take control of a robot).
        origin: who registered it (``builtin`` or the plugin's name).
    """

    kind: str
    driver: str
    run: ProbeFunction
    driver_checks: bool = True
    origin: str = "builtin"


class ProbeRegistry:
    """Device probes by (kind, driver name). Filled through ``hil_register_probes``."""

    def __init__(self) -> None:
        self._probes: dict[tuple[str, str], DeviceProbe] = {}

    def add(self, kind: str, driver: str, run: ProbeFunction, *, driver_checks: bool = True,
            origin: str = "builtin") -> None:
        """Register the probe of ``kind`` driver ``driver``.

        Raises:
            RegistryError: unknown kind, ``run`` not callable, or a probe already registered for
                (kind, driver).
        """
        if kind not in DRIVER_KINDS:
            raise RegistryError(
                f"{origin}: unknown driver kind {kind!r} for a probe; use one of {DRIVER_KINDS}")
        if not callable(run):
            raise RegistryError(f"{origin}: the probe of {kind} driver {driver!r} is not callable")
        key = (kind, driver)
        if key in self._probes:
            raise RegistryError(
                f"{origin}: a probe of {kind} driver {driver!r} is already registered by "
                f"{self._probes[key].origin}")
        self._probes[key] = DeviceProbe(kind, driver, run, driver_checks, origin)

    def get(self, kind: str, driver: str) -> DeviceProbe | None:
        """The probe of (kind, driver), or None: the driver then gets the driver-level checks only."""
        return self._probes.get((kind, driver))

    def probes(self) -> list[DeviceProbe]:
        return [self._probes[k] for k in sorted(self._probes)]
