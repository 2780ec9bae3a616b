"""Driver-level checks of any tracker (simulated, serial, plugin): the driver is built and
opened, records are read for the stream window, and each configured sensor gets a line: its pose,
quality and record rate, or why it has none.

Wire-level checks (serial port, baud rate, identity, sensors on the bus) are the driver's own
probe, registered through ``hil_register_probes`` (the serial trackers': ``drivers.tracker_serial``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel

from drivers.interfaces.tracker import PoseTracker, TrackerSample
from hil.probe.context import ProbeContext, build_step, close_quietly, field_s, open_step
from hil.probe.report import Check, Status
from hil.probe.runner import Checklist, Outcome
from plugins.registry import DriverInfo


def tracker_driver_checks(
    cl: Checklist, ctx: ProbeContext, cfg: BaseModel, info: DriverInfo, role: str,
) -> None:
    device = build_step(cl, ctx, role, cfg, info)
    if device is None:
        return
    if not isinstance(device, PoseTracker):
        cl.report.add(Check("driver_builds", Status.FAIL, f"driver {info.name} did not build a tracker"))
        return
    try:
        if not open_step(cl, device, cfg, f"{info.name} driver"):
            return
        window_s = max(ctx.window_s, 3.0 / max(field_s(cfg, "update_rate_hz", 40.0), 1.0))

        def stream() -> Outcome:
            seen: dict[str, set[int]] = {s: set() for s in device.sensors}
            last: dict[str, TrackerSample] = {}
            clock = ctx.clock  # a ManualClock (all-simulated setup) advances in sleep()
            t_end_ns = clock.now_ns() + round(window_s * 1e9)
            while clock.now_ns() < t_end_ns:
                for name, sample in device.latest().items():
                    if name in seen:
                        seen[name].add(sample.seq)
                        last[name] = sample
                clock.sleep(0.01)
            return Outcome(f"the driver streams ({sum(len(v) for v in seen.values())} records in "
                           f"{window_s:g} s)", value=(seen, last))

        out = cl.step("streams", stream, timeout_s=window_s + cl.timeout_s, what="reading records")
        if out is None:
            return
        seen, last = out.value
        for name in device.sensors:
            cl.report.add(_sensor_check(name, last.get(name), len(seen[name]), window_s))
    finally:
        close_quietly(device, cl.timeout_s)


def _sensor_check(name: str, sample: TrackerSample | None, n_records: int, window_s: float) -> Check:
    check = f"sensor_{name}"
    if sample is None:
        return Check(check, Status.FAIL, f"sensor {name!r}: no record in {window_s:g} s",
                     "is the sensor plugged in and configured with the right address / port handle?")
    rate = n_records / window_s
    data: dict[str, Any] = {"records": n_records, "rate_hz": round(rate, 1), "flags": list(sample.flags)}
    if sample.missing or sample.T_tracker_from_sensor is None:
        where = "out of the field volume" if "out_of_volume" in sample.flags else "missing"
        return Check(check, Status.WARN, f"sensor {name!r}: {where} "
                                         f"({', '.join(sample.flags) or 'no pose'})",
                     "move the sensor into the field generator's measurement volume; check its cable",
                     data)
    p = np.round(sample.T_tracker_from_sensor.t, 1).tolist()
    data["position_mm"] = p
    if sample.quality is not None:
        data["quality"] = round(float(sample.quality), 3)
    extra = f", quality {sample.quality:.2f}" if sample.quality is not None else ""
    flags = f", flags {', '.join(sample.flags)}" if sample.flags else ""
    status = Status.WARN if "partially_out" in sample.flags else Status.OK
    return Check(check, status, f"sensor {name!r}: pose at {p} mm{extra}{flags}, ~{rate:.0f} records/s",
                 "near the edge of the volume: move it towards the field generator's centre"
                 if status is Status.WARN else "", data)
