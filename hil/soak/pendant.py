"""What the soak's operator reads and presses on the robot's own pendant: whether the arm is in a
protective stop, and the "unlock protective stop" button (on a UR, the pendant's pop-up; on the
simulator and the fault layer, :meth:`~drivers.interfaces.robot.Robot.recover`).

An operator unlocks a protective stop at the pendant before resuming the procedure: a resume while
the arm is still locked (the stop's cause not gone yet) is refused by the arm and faults the
procedure a second time (issue 45 item 3).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from drivers.interfaces.errors import DriverError
from drivers.interfaces.robot import Robot, SafetyStatus


class Pendant(Protocol):
    """The robot's pendant as an operator uses it. Called from the controller's thread (the
    operator's ``poll``), never while the controller commands the arm."""

    def protective_stop(self) -> bool:
        """Whether the arm reports a protective stop (False when its state cannot be read)."""
        ...

    def unlock(self) -> str:
        """Press "unlock protective stop": "" when the arm was unlocked, else why not (the
        stop cannot be cleared yet, the link is down)."""
        ...


class RobotPendant:
    """:class:`Pendant` on a robot driver: ``state`` reads the arm's status without taking what
    the controller is owed (the servo robot's :meth:`~hil.servo.client.ServoRobot.state_view`: a
    pending error stays the controller's to raise), ``unlock`` is the driver's ``recover`` (it
    raises DriverError while the arm refuses, e.g. ``SafetyStopError`` "protective stop cannot be
    cleared yet")."""

    def __init__(self, state: Robot, unlock: Callable[[], None]) -> None:
        self.state, self._unlock = state, unlock

    def protective_stop(self) -> bool:
        try:
            return self.state.state_now().safety is SafetyStatus.PROTECTIVE_STOP
        except DriverError:
            return False

    def unlock(self) -> str:
        try:
            self._unlock()
        except DriverError as exc:
            return str(exc) or type(exc).__name__
        return ""   # (the status read back may still be the stop's: the loop reads the arm next period)
