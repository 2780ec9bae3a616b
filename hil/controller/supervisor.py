"""Supervision: the watchdogs, the robot's safety and mode checks, the robot-recovery policy and
the delivery of stops.

The supervisor decides nothing about the procedure's progress; it reports faults (plain-words
reasons the controller turns into FAULT_DETECTED) and owns the one path a stop takes to the arm.
A stop that cannot be delivered (the link is down) stays owed and is re-sent every tick until one
is delivered or a later state entry supersedes it.
"""

from __future__ import annotations

import re

from drivers.interfaces.errors import DriverError
from drivers.interfaces.robot import Robot, RobotMode, RobotState, SafetyStatus
from hil.controller import events as ev
from hil.controller.fsm import Event, State
from hil.log import get_logger
from hil.safety.layer import SafetyLayer
from hil.safety.watchdog import WatchdogSet
from hil.session.log import SessionLog

_log = get_logger(__name__)

_FIGURE = re.compile(r"\d+(?:\.\d+)?(?:e-?\d+)?")


def fault_kind(reason: str) -> str:
    """``reason`` with its figures replaced by ``#`` (``watchdog: camera data # s old > # s``):
    what stays the same while a fault persists."""
    return _FIGURE.sub("#", reason)


#: States in which the arm must be able to execute commands (or hold under control).
ROBOT_COMMANDED_STATES = frozenset({State.APPROACH, State.GATE, State.COMPENSATE, State.LOCK, State.RETRACT})


class Supervisor:
    """Watchdogs, robot checks, recovery and stops (module doc)."""

    def __init__(self, robot: Robot, safety: SafetyLayer, watchdogs: WatchdogSet,
                 session: SessionLog) -> None:
        self.robot, self.safety, self.watchdogs, self.session = robot, safety, watchdogs, session
        self.faults: list[str] = []
        self._kinds_in_fault: set[str] = set()   # fault_kind of each fault recorded since FAULT
        self._stop_owed: tuple[str, int] | None = None   # (reason, attempts) of an undelivered stop

    # ------------------------------------------------------------------ faults
    def record_fault(self, reason: str, state: State) -> bool:
        """Record a fault (``fault_detected``). Returns False for a fault of a kind already
        recorded since the controller entered FAULT (the same reason but for its figures, as a
        watchdog's growing age while the camera stays silent: recorded once)."""
        kind = fault_kind(reason)
        if state is State.FAULT:
            if kind in self._kinds_in_fault:
                return False
        else:
            self._kinds_in_fault = set()
        self._kinds_in_fault.add(kind)
        self.faults.append(reason)
        self.session.write(ev.FAULT_DETECTED, reason=reason, state=state)
        _log.warning(ev.FAULT_DETECTED, reason=reason, state=state.value)
        return True

    def check(self, now_ns: int, st: RobotState | None, state: State,
              skip: frozenset[str] = frozenset()) -> str | None:
        """After the devices were read: the first watchdog that expired (but those named in
        ``skip``: not read yet, checked by :meth:`check_watchdog` once read), a robot safety
        status other than normal (outside FAULT), or a stopped robot program in a state that
        commands the arm; None when all is well."""
        for reason in self.watchdogs.check(now_ns, skip):
            return reason
        if st is not None and st.safety is not SafetyStatus.NORMAL and state is not State.FAULT:
            return f"robot: {st.safety.value}"
        if st is not None and st.mode is RobotMode.STOPPED and state in ROBOT_COMMANDED_STATES:
            # Safety normal but the arm's program is not running (a UR script stopped by its RTDE
            # watchdog, by the pendant, ...): it cannot execute or correct anything, so the
            # procedure must not wait on it. recover() (operator `recover`) restarts the program.
            return f"robot: program not running in {state.value} (mode stopped)"
        return None

    def check_watchdog(self, name: str, now_ns: int) -> str | None:
        """One watchdog's verdict (the reason, or None); None for a stream without one."""
        dog = self.watchdogs.dogs.get(name)
        return None if dog is None else dog.check(now_ns)

    # ------------------------------------------------------------------ stops
    def stop_robot(self, reason: str) -> None:
        """Send a stop. When it cannot be delivered (``stop_failed``: the connection is down) it
        stays owed and :meth:`retry_stop` re-sends it (``stop_delivered`` with the number of
        attempts once one is delivered). Never raises for a device error."""
        attempts = 1 if self._stop_owed is None else self._stop_owed[1] + 1
        try:
            self.safety.stop(reason)
        except DriverError as exc:
            self._stop_owed = (reason, attempts)
            self.session.write(ev.STOP_FAILED, reason=str(exc), stop_reason=reason, attempt=attempts)
            _log.error(ev.STOP_FAILED, reason=str(exc), attempt=attempts)
            return
        self._stop_owed = None
        if attempts > 1:
            self.session.write(ev.STOP_DELIVERED, reason=reason, attempts=attempts)
            _log.warning(ev.STOP_DELIVERED, reason=reason, attempts=attempts)

    def retry_stop(self) -> None:
        """Re-send a stop that could not be delivered (once per tick)."""
        if self._stop_owed is not None:
            self.stop_robot(self._stop_owed[0])

    def supersede_stop(self) -> None:
        """A new state's entry action commands the robot itself: no stop is owed any more."""
        self._stop_owed = None

    # ------------------------------------------------------------------ recovery policy
    def robot_ready_for(self, cmd: Event, state: State) -> str:
        """Before an accepted RESET or START: when the robot needs recovering - a protective stop,
        a stopped program with normal safety (an e-stop released, a script stopped by its
        watchdog or the pendant), or a state that cannot be read (a dropped link) - try
        ``robot.recover()`` (``robot_recover_attempted`` with the outcome). Returns "" when
        ``cmd`` may proceed, else why START is refused (``start_refused`` is logged): the robot
        is still not in normal safety status with its program running, or its state cannot be
        read. RESET always proceeds (IDLE stops the robot). Never raises."""
        why = ""
        try:
            st: RobotState | None = self.robot.state_now()
            read_error = ""
        except DriverError as exc:
            st, read_error = None, str(exc)
        if st is None or st.safety is SafetyStatus.PROTECTIVE_STOP or (
                st.safety is SafetyStatus.NORMAL and st.mode is RobotMode.STOPPED):
            error = ""
            try:
                self.robot.recover()
            except DriverError as exc:
                error = str(exc)
            try:
                st = self.robot.state_now()
            except DriverError as exc:
                st, error = None, error or str(exc)
            ok = st is not None and st.safety is SafetyStatus.NORMAL and st.mode is not RobotMode.STOPPED
            self.session.write(ev.ROBOT_RECOVER_ATTEMPTED, input=cmd, ok=ok,
                               safety=None if st is None else st.safety,
                               mode=None if st is None else st.mode, error=error, state_error=read_error)
            (_log.info if ok else _log.warning)(ev.ROBOT_RECOVER_ATTEMPTED, input=cmd.value, ok=ok,
                                                error=error)
            if not ok:
                why = ("robot state unavailable after recover()" if st is None
                       else f"robot still {st.safety.value} / {st.mode.value} after recover()")
                why += f": {error}" if error else ""
        elif st.safety is not SafetyStatus.NORMAL:
            why = f"robot in {st.safety.value}"
        if not why or cmd is Event.RESET_REQUESTED:
            return ""
        self.session.write(ev.START_REFUSED, reason=why, state=state)
        _log.warning(ev.START_REFUSED, reason=why, state=state.value)
        return why
