"""Typed errors shared by all drivers. Each names the device and says what happened."""

from __future__ import annotations

from hil.errors import HilError


class DriverError(HilError):
    """Base of every device error. ``device`` is the configured device name (e.g. ``robot``)."""

    def __init__(self, device: str, message: str) -> None:
        self.device = device
        self.message = message
        super().__init__(f"{device}: {message}")


class DeviceTimeoutError(DriverError, TimeoutError):
    """The device did not answer (or deliver data) within the allowed time."""


class DisconnectedError(DriverError, ConnectionError):
    """The transport to the device is gone (or could not be opened)."""


class ProtocolError(DriverError):
    """The device sent bytes that do not parse (bad framing, checksum, unexpected reply)."""


class DeviceFaultError(DriverError):
    """The device reports a fault of its own (error code, bad-quality flag it cannot recover)."""


class SafetyStopError(DriverError):
    """The robot is in a protective stop or an emergency stop; it will not move."""


class LifecycleError(DriverError):
    """A command was given in a lifecycle state that does not allow it (e.g. move before connect)."""


class LimitViolationError(DriverError):
    """A motion command breaks a configured limit; it was refused before reaching the device.

    Attributes:
        limit: which limit (``workspace``, ``speed``, ``acceleration``, ``step``).
    """

    def __init__(self, device: str, limit: str, message: str) -> None:
        self.limit = limit
        super().__init__(device, f"refused ({limit} limit): {message}")
