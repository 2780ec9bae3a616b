"""``hil probe``: check each configured device in turn and say in plain words what was found.

:func:`probe_setup` runs every device's checklist (robot, tracker, camera), each step bounded by
a timeout and stopping at the device's first failure, and returns a :class:`ProbeReport`.
Devices are built through the driver registry; the core imports no driver. The wire-level checks
of a device (serial port and baud rate, network ports and controller version, device lists) are
the driver's own probe, registered by its plugin through the ``hil_register_probes`` hook
(:mod:`hil.probe.registry`); this package runs them and the driver-level checks every driver
gets, and reports in plain words.
"""

from __future__ import annotations

from hil.config.build import clock_for
from hil.config.setup import SetupConfig
from hil.log import get_logger
from hil.probe.context import ProbeContext
from hil.probe.device import probe_device
from hil.probe.registry import DeviceProbe, ProbeFunction, ProbeRegistry
from hil.probe.report import (
    EXIT_CONFIG_ERROR,
    EXIT_DEVICE_FAILED,
    EXIT_OK,
    Check,
    DeviceReport,
    ProbeReport,
    Status,
    render_text,
)
from hil.probe.runner import Checklist, Finding, Outcome, StepTimeoutError, WireProblem, call_with_timeout
from plugins.registry import DriverInfo, DriverRegistry, RegistryError

__all__ = [
    "EXIT_CONFIG_ERROR",
    "EXIT_DEVICE_FAILED",
    "EXIT_OK",
    "Check",
    "Checklist",
    "DeviceProbe",
    "DeviceReport",
    "Finding",
    "Outcome",
    "ProbeContext",
    "ProbeFunction",
    "ProbeRegistry",
    "ProbeReport",
    "Status",
    "StepTimeoutError",
    "WireProblem",
    "call_with_timeout",
    "probe_setup",
    "render_text",
]

DEFAULT_TIMEOUT_S = 3.0
DEFAULT_WINDOW_S = 1.0

_log = get_logger(__name__)


def probe_setup(
    setup: SetupConfig, *, config_name: str = "setup", registry: DriverRegistry | None = None,
    probes: ProbeRegistry | None = None, timeout_s: float = DEFAULT_TIMEOUT_S,
    window_s: float = DEFAULT_WINDOW_S,
) -> ProbeReport:
    """Probe every device of ``setup``, one after another (robot, tracker, camera).

    Blocking; bounded: every step has a timeout derived from ``timeout_s`` (plus the waits the
    device's own config asks for while it opens, and ``window_s`` for stream measurements).
    Never raises for a device problem: every finding is a Check in the report.

    Args:
        setup: a validated setup (:func:`hil.config.load_setup`).
        config_name: how the report names the setup (its path).
        registry: the drivers (default: every installed plugin).
        probes: the drivers' own device probes (default: every installed plugin's
            ``hil_register_probes``).
        timeout_s: per-check timeout, s.
        window_s: how long to watch each stream (frames, records, RTDE packages), s.
    """
    if registry is None or probes is None:
        from plugins.manager import HilPlugins

        plugins = HilPlugins()
        registry = registry if registry is not None else plugins.driver_registry()
        probes = probes if probes is not None else plugins.probe_registry()
    sections = setup.device_sections()
    infos: dict[str, DriverInfo] = {}
    report = ProbeReport(config_name, timeout_s)
    for role, cfg in sections.items():
        try:
            infos[role] = registry.get(role, str(getattr(cfg, "driver", "?")))
        except RegistryError as exc:  # load_setup already refuses this; kept for a mapping-built setup
            dev = DeviceReport(role, str(getattr(cfg, "driver", "?")))
            dev.add(Check("driver_available", Status.FAIL, str(exc)))
            report.devices.append(dev)
    clock = clock_for(setup, registry)  # all-simulated setups run on a ManualClock
    world: object | None = None
    world_error = ""
    if any(i.simulated for i in infos.values()):
        try:
            if registry.world_factory is None:
                raise RuntimeError("no plugin provides the simulated world")
            world = registry.world_factory(setup, clock)
        except Exception as exc:  # noqa: BLE001 - reported on each simulated device
            world_error = f"{type(exc).__name__}: {exc}"
    ctx = ProbeContext(setup=setup, registry=registry, clock=clock, world=world, world_error=world_error,
                       timeout_s=timeout_s, window_s=window_s)
    for role in ("robot", "tracker", "camera"):
        if role not in infos:
            continue
        info = infos[role]
        dev = probe_device(ctx, role, sections[role], info, probes.get(role, info.name))
        _log.info("probe_device_done", role=role, driver=dev.driver, status=dev.status.value)
        report.devices.append(dev)
    return report
