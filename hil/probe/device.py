"""One device's checklist: the driver's own probe (if a plugin registered one), then the
driver-level checks of its kind, unless the probe failed or replaces them.

The probe is looked up by (role, driver name) in the :class:`~hil.probe.registry.ProbeRegistry`;
the core knows no driver. A simulated device gets no probe: it is said to be simulated, then
started, asked and closed like any other.
"""

from __future__ import annotations

from collections.abc import Callable

from pydantic import BaseModel

from hil.probe.camera import camera_driver_checks
from hil.probe.context import ProbeContext
from hil.probe.registry import DeviceProbe
from hil.probe.report import DeviceReport
from hil.probe.robot import robot_driver_checks
from hil.probe.runner import Checklist, Outcome
from hil.probe.tracker import tracker_driver_checks
from plugins.registry import DriverInfo

DriverChecks = Callable[[Checklist, ProbeContext, BaseModel, DriverInfo, str], None]

_DRIVER_CHECKS: dict[str, DriverChecks] = {
    "camera": camera_driver_checks, "robot": robot_driver_checks, "tracker": tracker_driver_checks,
}
_NOUN = {"camera": "stereo camera", "robot": "robot", "tracker": "tracker"}


def probe_device(ctx: ProbeContext, role: str, cfg: BaseModel, info: DriverInfo,
                 probe: DeviceProbe | None) -> DeviceReport:
    """The checklist of the ``role`` device (camera / robot / tracker).

    Blocking; every step bounded by its timeout; never raises for a device problem.
    """
    report = DeviceReport(role, info.name, info.simulated)
    cl = Checklist(report, ctx.timeout_s)
    if info.simulated:
        noun = _NOUN[role]
        cl.step("simulated", lambda: Outcome(f"simulated {noun}: no hardware, checking that it starts"))
    elif probe is not None:
        probe.run(cl, cfg, ctx)
        if not probe.driver_checks:
            return report
    if not cl.failed:
        _DRIVER_CHECKS[role](cl, ctx, cfg, info, role)
    return report
