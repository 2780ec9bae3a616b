"""The controller's RTDE input watchdog, seen from the driver: the rate it is armed at and the
thread that feeds it while no servo command does.

The UR program started by ur-rtde stops the arm when no RTDE input arrives within ``1 / hz`` of
the last (``setWatchdog``). A host that hangs therefore stops the arm; a host that is merely idle
(no motion command) must feed it: :class:`WatchdogKicker` calls the driver's kick every third of
the window.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from drivers.interfaces.robot import MotionLimits
from hil.log import get_logger

_log = get_logger(__name__)

#: structlog event: the configured watchdog rate was lowered to outlast a blocking stop
EV_WATCHDOG_LOWERED = "rtde_watchdog_lowered"


def armed_watchdog_hz(want_hz: float, limits: MotionLimits, device: str) -> float:
    """The watchdog rate armed: ``want_hz`` (``rtde_watchdog_min_hz``; <= 0: none, 0.0), lowered
    when its window would not outlast a blocking stop. A stop (servoStop / stopL) blocks the
    library until the arm is at rest, and the kicker cannot call the library meanwhile; the stop's
    own command write feeds the watchdog, and the kicker's next kick comes at most one kicker
    period (a third of the window) after the stop returns. So the window must be >= 1.5 x the
    longest stop.

    The longest stop: the tool's linear speed at ``max_accel`` (``max_speed / max_accel``) or its
    rotation, whichever takes longer, plus the controller's reply (50 ms here). The driver passes
    stopl one acceleration ``a`` and the controller then decelerates the rotation at ``a`` rad/s^2
    too (URScript ``stopl(a, aRot)``: aRot defaults to a), so a rotation at ``max_angular_speed``
    takes ``max_angular_speed / a`` to stop. (Seen: a servoStop from a 0.17 rad/s rotation at 0.5
    rad/s^2 outlasting a 375 ms window sized for the linear stop alone on the UR emulator, which
    then stopped the program.)"""
    if want_hz <= 0:
        return 0.0
    a_m_s2 = limits.max_accel_mm_s2 / 1000.0
    longest_stop_s = max(limits.max_speed_mm_s / limits.max_accel_mm_s2,
                         limits.max_angular_speed_rad_s / a_m_s2) + 0.05
    hz = min(want_hz, 1.0 / (1.5 * longest_stop_s))
    if hz < want_hz:
        _log.info(EV_WATCHDOG_LOWERED, device=device, configured_hz=want_hz, armed_hz=round(hz, 3),
                  longest_stop_s=round(longest_stop_s, 3))
    return hz


class WatchdogKicker:
    """A daemon thread that calls ``kick(period_s)`` every ``period_s`` = a third of the watchdog
    window until :meth:`stop`. ``kick`` decides whether a kick is due and sends it; it must not
    raise (the thread would end).

    Args:
        name: the thread's name.
        kick: the driver's kick, given the kicker's period (s).
    """

    def __init__(self, name: str, kick: Callable[[float], None]) -> None:
        self.name = name
        self._kick = kick
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()

    def start(self, armed_hz: float) -> None:
        """Start kicking for a watchdog armed at ``armed_hz`` (> 0). Returns at once."""
        self._stopping.clear()
        period_s = 1.0 / (3.0 * armed_hz)

        def run() -> None:
            while not self._stopping.wait(period_s):
                self._kick(period_s)

        self._thread = threading.Thread(target=run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the thread (waits up to 2 s for a kick under way); idempotent."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
