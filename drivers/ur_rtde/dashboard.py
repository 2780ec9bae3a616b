"""The UR dashboard server (TCP 29999) of one arm, through ``ur-rtde``'s ``DashboardClient``: the
PolyScope version at connect, and what recovery needs — power on, brake release, closing the safety
pop-up and unlocking a protective stop (facts in reference/ur-rtde.md).

:class:`UrDashboard` owns the client; every call goes through the driver's I/O lock (the one lock
of :mod:`drivers.ur_rtde.robot`), and the library's ``RuntimeError`` becomes the project's typed
errors naming the device and the call.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Any, TypeVar

from drivers.interfaces.errors import DeviceFaultError, DeviceTimeoutError, DisconnectedError
from drivers.ur_rtde.config import UrRtdeRobotConfig
from drivers.ur_rtde.wire import RobotModeCode
from hil.clock import Clock

T = TypeVar("T")
#: how often a wait polls its condition, s
POLL_S = 0.02
#: pause between unlock attempts while the controller refuses them, s (a CB3 refuses an unlock in
#: the first 5 s after the stop)
UNLOCK_RETRY_S = 0.5


def wait_until(clock: Clock, device: str, timeout_s: float, what: str, cond: Callable[[], bool]) -> None:
    """Poll ``cond`` every :data:`POLL_S` on ``clock`` until it holds (blocks up to ``timeout_s``).

    Raises:
        DeviceTimeoutError: ``what`` not reached within ``timeout_s``.
    """
    deadline = clock.now_ns() + int(timeout_s * 1e9)
    while not cond():
        if clock.now_ns() > deadline:
            raise DeviceTimeoutError(device, f"{what} not reached within {timeout_s} s")
        clock.sleep(POLL_S)


class UrDashboard:
    """The dashboard client of the arm ``name`` (module doc).

    Args:
        name: the robot's role name (errors). cfg: its config (host, timeouts). clock: the
            controller's clock (waits). io: the driver's I/O lock.
    """

    def __init__(self, name: str, cfg: UrRtdeRobotConfig, clock: Clock, io: threading.RLock) -> None:
        self.name, self.cfg, self.clock, self._io = name, cfg, clock, io
        self.client: Any = None

    def connect(self) -> str:
        """Connect (blocks up to ``connect_timeout_s``) and return the PolyScope version.

        Raises:
            RuntimeError: the library's, for the caller to map (it tears down all clients).
        """
        import dashboard_client

        with self._io:
            dash = dashboard_client.DashboardClient(self.cfg.host)
            dash.connect(int(self.cfg.connect_timeout_s * 1000))
            self.client = dash
            return str(dash.polyscopeVersion())

    def disconnect(self) -> None:
        """Disconnect and drop the client (never raises)."""
        with self._io:
            if self.client is not None:
                with contextlib.suppress(RuntimeError):
                    self.client.disconnect()
            self.client = None

    def call(self, what: str, fn: Callable[[Any], T]) -> T:
        """``fn(client)`` under the I/O lock, reconnecting the client first when it dropped.

        Raises:
            DisconnectedError: the dashboard server cannot be reached.
            DeviceFaultError: the call failed (``what`` and the controller's answer).
        """
        with self._io:
            if self.client is None or not self.client.isConnected():
                import dashboard_client

                self.client = dashboard_client.DashboardClient(self.cfg.host)
                try:
                    self.client.connect(int(self.cfg.connect_timeout_s * 1000))
                except RuntimeError as exc:
                    raise DisconnectedError(self.name, f"dashboard: {exc}") from exc
            try:
                return fn(self.client)
            except RuntimeError as exc:  # includes std::logic_error from unlockProtectiveStop
                raise DeviceFaultError(self.name, f"dashboard {what}: {exc}") from exc

    def power_on(self, robot_mode: Callable[[], int]) -> None:
        """Power the arm and release its brakes unless ``robot_mode()`` (RTDE's robot mode code) is
        already RUNNING; blocks until it is, up to ``ready_timeout_s``.

        Raises:
            DisconnectedError / DeviceFaultError: as :meth:`call`. DeviceTimeoutError: not RUNNING in time.
        """
        mode = robot_mode()
        if mode == RobotModeCode.RUNNING:
            return
        if mode <= RobotModeCode.POWER_OFF:
            self.call("power on", lambda d: d.powerOn())
        self.call("brake release", lambda d: d.brakeRelease())
        wait_until(self.clock, self.name, self.cfg.ready_timeout_s, "robot mode RUNNING",
                   lambda: robot_mode() == RobotModeCode.RUNNING)

    def unlock_protective_stop(self, cleared: Callable[[], bool]) -> None:
        """Close the safety pop-up and unlock the protective stop, retrying while the controller
        refuses (every :data:`UNLOCK_RETRY_S` until ``ready_timeout_s``), then wait until
        ``cleared()``.

        Raises:
            DeviceFaultError: still refused at the deadline. DeviceTimeoutError: not cleared in time.
        """
        deadline = self.clock.now_ns() + int(self.cfg.ready_timeout_s * 1e9)
        while True:
            try:
                self.call("close safety popup", lambda d: d.closeSafetyPopup())
                self.call("unlock protective stop", lambda d: d.unlockProtectiveStop())
                break
            except DeviceFaultError:
                if self.clock.now_ns() > deadline:
                    raise
                self.clock.sleep(UNLOCK_RETRY_S)
        wait_until(self.clock, self.name, self.cfg.ready_timeout_s, "protective stop cleared", cleared)
