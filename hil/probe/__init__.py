"""``hil probe``: check each configured device in turn and say in plain words what was found.

:func:`probe_setup` runs every device's checklist (camera, robot, tracker), each step bounded by
a timeout and stopping at the device's first failure, and returns a :class:`ProbeReport`.
Devices are built through the driver registry; the core imports no driver.
"""

from __future__ import annotations

from hil.config.build import clock_for
from hil.config.setup import SetupConfig
from hil.log import get_logger
from hil.probe.camera import probe_camera
from hil.probe.context import ProbeContext
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
from hil.probe.robot import probe_robot
from hil.probe.runner import Checklist, Finding, Outcome, StepTimeoutError, call_with_timeout
from hil.probe.tracker import probe_tracker
from plugins.registry import DriverInfo, DriverRegistry, RegistryError

__all__ = [
    "EXIT_CONFIG_ERROR",
    "EXIT_DEVICE_FAILED",
    "EXIT_OK",
    "Check",
    "Checklist",
    "DeviceReport",
    "Finding",
    "Outcome",
    "ProbeReport",
    "Status",
    "StepTimeoutError",
    "call_with_timeout",
    "probe_setup",
    "render_text",
]

DEFAULT_TIMEOUT_S = 3.0
DEFAULT_WINDOW_S = 1.0

_log = get_logger(__name__)
_PROBES = {"camera": probe_camera, "robot": probe_robot, "tracker": probe_tracker}


def probe_setup(
    setup: SetupConfig, *, config_name: str = "setup", registry: DriverRegistry | None = None,
    timeout_s: float = DEFAULT_TIMEOUT_S, window_s: float = DEFAULT_WINDOW_S,
) -> ProbeReport:
    """Probe every device of ``setup``, one after another (robot, tracker, camera).

    Blocking; bounded: every step has a timeout derived from ``timeout_s`` (plus the waits the
    device's own config asks for while it opens, and ``window_s`` for stream measurements).
    Never raises for a device problem: every finding is a Check in the report.

    Args:
        setup: a validated setup (:func:`hil.config.load_setup`).
        config_name: how the report names the setup (its path).
        registry: the drivers (default: every installed plugin).
        timeout_s: per-check timeout, s.
        window_s: how long to watch each stream (frames, records, RTDE packages), s.
    """
    if registry is None:
        from plugins.manager import default_registry

        registry = default_registry()
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
        dev = _PROBES[role](ctx, sections[role], infos[role], role)
        _log.info("probe_device_done", role=role, driver=dev.driver, status=dev.status.value)
        report.devices.append(dev)
    return report
