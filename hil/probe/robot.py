"""Driver-level checks of any robot arm (simulated, plugin): built, opened, asked for one state,
closed.

Wire-level checks are the driver's own probe, registered through ``hil_register_probes``; the UR
over RTDE (``drivers.ur_rtde``) replaces these driver-level checks with read-only ones, as opening
its driver would start a control script on the robot.
"""

from __future__ import annotations

from pydantic import BaseModel

from drivers.interfaces.robot import Robot, SafetyStatus
from hil.probe.context import ProbeContext, build_step, close_quietly, open_step
from hil.probe.report import Check, Status
from hil.probe.runner import Checklist, Finding, Outcome
from plugins.registry import DriverInfo

#: What to try when the robot reports a safety stop.
SAFETY_STOP_HINT = ("find what stopped the arm (collision, limit), then press 'unlock protective stop' "
                    "on the teach pendant")


def robot_driver_checks(
    cl: Checklist, ctx: ProbeContext, cfg: BaseModel, info: DriverInfo, role: str,
) -> None:
    device = build_step(cl, ctx, role, cfg, info)
    if device is None:
        return
    if not isinstance(device, Robot):
        cl.report.add(Check("driver_builds", Status.FAIL, f"driver {info.name} did not build a robot"))
        return
    try:
        if not open_step(cl, device, cfg, f"{info.name} robot"):
            return

        def state() -> Outcome:
            s = device.state_now()
            data = {"mode": s.mode.value, "safety": s.safety.value, "control_rate_hz": device.control_rate_hz,
                    "tcp_mm": [round(float(x), 1) for x in s.T_robot_from_tcp.t]}
            text = (f"state: mode {s.mode.value}, safety {s.safety.value}, TCP at {data['tcp_mm']} mm, "
                    f"control rate {device.control_rate_hz:g} Hz")
            if s.safety is not SafetyStatus.NORMAL:
                raise Finding(text, SAFETY_STOP_HINT, data)
            return Outcome(text, data=data)

        cl.step("state", state, what="reading the robot state")
    finally:
        close_quietly(device, cl.timeout_s)
