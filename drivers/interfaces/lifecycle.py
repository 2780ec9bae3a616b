"""Device lifecycle: CONFIGURED -> ACTIVE -> CLOSED (ros2_control's discipline, simplified).

A device refuses every command outside the state that allows it, with a
:class:`~drivers.interfaces.errors.LifecycleError`. ``close`` is idempotent.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from enum import StrEnum

from drivers.interfaces.errors import LifecycleError


class DeviceState(StrEnum):
    CONFIGURED = "configured"  # built from its config; no connection yet
    ACTIVE = "active"          # connected, streaming, commandable
    CLOSED = "closed"          # released; cannot be reopened (build a new one)


class Device(ABC):
    """Base of every device. Subclasses implement ``_open`` and ``_close``.

    Args:
        name: the role name in the setup (``camera``, ``robot``, ``tracker``), used in errors.
    """

    kind: str = "device"

    def __init__(self, name: str) -> None:
        self.name = name
        self._state = DeviceState.CONFIGURED
        self._lifecycle_lock = threading.RLock()

    @property
    def state(self) -> DeviceState:
        return self._state

    def open(self) -> None:
        """Connect/start the device. Blocks until ready.

        Raises:
            LifecycleError: not in CONFIGURED.
            DisconnectedError, DeviceTimeoutError, ProtocolError: the device could not be reached.
        """
        with self._lifecycle_lock:
            if self._state is not DeviceState.CONFIGURED:
                raise LifecycleError(self.name, f"open() needs state configured, is {self._state}")
            self._open()
            self._state = DeviceState.ACTIVE

    def close(self) -> None:
        """Release the device. Idempotent; never raises for a device already closed."""
        with self._lifecycle_lock:
            if self._state is DeviceState.CLOSED:
                return
            was_active = self._state is DeviceState.ACTIVE
            self._state = DeviceState.CLOSED
            if was_active:
                self._close()

    def require_active(self, operation: str) -> None:
        """Raise :class:`LifecycleError` unless ACTIVE."""
        if self._state is not DeviceState.ACTIVE:
            raise LifecycleError(self.name, f"{operation}() needs state active, is {self._state}")

    def describe(self) -> dict[str, str]:
        """What the open device says about itself, for ``hil probe``'s "opens" line (model,
        serial, firmware, format: whatever the driver learnt while opening). Never blocks and
        never raises; the default says nothing."""
        return {}

    def __enter__(self) -> Device:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _close(self) -> None: ...
