"""What every device probe gets, and the driver-level steps they share: build the device through
the registry (never importing a driver), open it, close it — each bounded by a timeout."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

from pydantic import BaseModel

from drivers.interfaces.lifecycle import Device
from hil.clock import Clock
from hil.config.setup import SetupConfig
from hil.probe.runner import Checklist, Outcome, StepTimeoutError, call_with_timeout
from plugins.registry import DriverContext, DriverInfo, DriverRegistry

#: Config fields (seconds) a driver spends waiting while it opens, added to the open timeout.
_OPEN_WAIT_FIELDS = ("reset_hold_s", "reset_settle_s", "auto_config_wait_s", "reset_timeout_s",
                     "connect_timeout_s", "ready_timeout_s")


@dataclass(frozen=True)
class ProbeContext:
    """Shared by the device probes.

    Attributes:
        setup: the validated setup.
        registry: the drivers.
        clock: the clock devices are built with (the wall clock: probes run in real time).
        world: the simulated world when a simulated driver is configured (else None).
        world_error: why building the simulated world failed ("" when it did not).
        timeout_s: the per-check timeout (``--timeout-s``).
        window_s: how long to watch a stream (camera frames, tracker records, RTDE packages), s.
    """

    setup: SetupConfig
    registry: DriverRegistry
    clock: Clock
    world: object | None
    world_error: str
    timeout_s: float
    window_s: float


def field_s(cfg: BaseModel, name: str, default: float) -> float:
    value = getattr(cfg, name, None)
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else default


def open_budget_s(cfg: BaseModel, timeout_s: float) -> float:
    """The open() timeout: the per-check timeout plus the waits the config itself asks for."""
    waits = sum(field_s(cfg, name, 0.0) for name in _OPEN_WAIT_FIELDS)
    return timeout_s + waits + 4.0 * field_s(cfg, "response_timeout_s", 0.0)


def build_step(
    cl: Checklist, ctx: ProbeContext, role: str, cfg: BaseModel, info: DriverInfo,
) -> Device | None:
    """Build the device (CONFIGURED) with the registered factory; no fault injection."""

    def build() -> Outcome:
        if info.simulated and ctx.world is None:
            raise RuntimeError(f"the simulated world could not be built: {ctx.world_error}")
        dctx = DriverContext(role=role, clock=ctx.clock, limits=ctx.setup.safety.motion_limits(),
                             config_dir=ctx.setup.config_dir, world=ctx.world,
                             calibration_path=ctx.setup.calibration.stereo)
        device = info.factory(cfg, dctx)
        return Outcome(f"driver {info.name} ({info.origin}) builds the device", value=device)

    out = cl.step("driver_builds", build, what=f"building the {info.name} driver")
    return None if out is None else out.value


def open_step(cl: Checklist, device: Device, cfg: BaseModel, what: str, timeout_hint: str = "") -> bool:
    """Open the device within :func:`open_budget_s`. True when it opened."""
    budget = open_budget_s(cfg, cl.timeout_s)

    def do_open() -> Outcome:
        device.open()
        data = device.describe()
        detail = ", ".join(f"{k} {v}" for k, v in data.items())
        return Outcome(f"{what} opens" + (f" ({detail})" if detail else ""), data=data)

    return cl.step("driver_opens", do_open, timeout_s=budget, what=f"opening the {what}",
                   timeout_hint=timeout_hint) is not None


def close_quietly(device: Device, timeout_s: float) -> None:
    """Close the device; a hang or an error here is not the user's problem."""
    with contextlib.suppress(StepTimeoutError, Exception):
        call_with_timeout(device.close, timeout_s, "probe-close")
