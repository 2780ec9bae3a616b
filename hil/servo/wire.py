"""Driver errors across the process boundary: sent as (class name, device, message), raised again
on the other side as the same class."""

from __future__ import annotations

from drivers.interfaces.errors import (
    DeviceFaultError,
    DeviceTimeoutError,
    DisconnectedError,
    DriverError,
    LifecycleError,
    LimitViolationError,
    ProtocolError,
    SafetyStopError,
)

_ERRORS: dict[str, type[DriverError]] = {c.__name__: c for c in (
    DriverError, DeviceTimeoutError, DisconnectedError, ProtocolError, DeviceFaultError,
    SafetyStopError, LifecycleError)}


def error_to_wire(exc: DriverError) -> tuple[str, str, str]:
    """``(class name, device, message)`` of a driver error, to send over the channel."""
    if isinstance(exc, LimitViolationError):
        return ("LimitViolationError", exc.device, f"{exc.limit}\x00{exc.message}")
    return (type(exc).__name__, exc.device, exc.message)


def error_from_wire(kind: str, device: str, message: str) -> DriverError:
    """The driver error :func:`error_to_wire` described (an unknown class: DeviceFaultError)."""
    if kind == "LimitViolationError":
        limit, _, msg = message.partition("\x00")
        return LimitViolationError(device, limit, msg)
    return _ERRORS.get(kind, DeviceFaultError)(device, message)
