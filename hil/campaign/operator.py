"""The campaign's operator: confirms everything, and after a fault (once the injected fault is
over and the robot had time to stop) recovers — resume from FAULT / SAFE_STOP / PAUSED, or reset
and restart when there is no plan to resume — so a run shows whether the procedure can continue
to lock after recovery. A pause after it has resumed once (from any halt) is answered as an
operator would: the body no longer matches the registration (a marker slid, the patient
moved), so it re-registers (START from PAUSED) instead of resuming into the same pause."""

from __future__ import annotations

from hil.controller.fsm import Event, State
from hil.controller.operator_input import OperatorView

HALTED = frozenset({State.FAULT, State.SAFE_STOP, State.PAUSED})


class CampaignOperator:
    """Args:
    recover_after_s: controller time (s) before which it will not try to recover (the end of
        the fault window plus a settling time).
    max_recoveries: recovery attempts (each resume / reset-and-restart counts one).
    holds: further ``(from_s, until_s)`` controller-time windows in which it will not recover
        either (a second fault of a compound-fault run: from its start to its end plus the
        settling time).
    """

    def __init__(self, recover_after_s: float, max_recoveries: int = 2,
                 holds: tuple[tuple[float, float], ...] = ()) -> None:
        self.recover_after_s = recover_after_s
        self.holds = holds
        self.recoveries_left = max_recoveries
        self._started = False
        self._last: Event | None = None
        self._last_state: State | None = None
        self._resumed = False
        self.commands: list[tuple[float, str]] = []

    def _send(self, view: OperatorView, ev: Event) -> Event:
        self._last, self._last_state = ev, view.state
        self.commands.append((round(view.t_s, 4), ev.value))
        return ev

    def _holding(self, t_s: float) -> bool:
        """Whether recovery must wait at controller time ``t_s`` (s)."""
        return t_s < self.recover_after_s or any(a <= t_s < b for a, b in self.holds)

    def poll(self, view: OperatorView) -> Event | None:
        if self._last is not None and view.state is not self._last_state:
            self._last = None  # the last command was applied (the state moved on)
        if not self._started and view.state is State.IDLE:
            self._started = True
            return self._send(view, Event.START_REQUESTED)
        if view.pending is not None:
            return Event.CONFIRM_REQUESTED
        halted = view.state in HALTED or (view.state is State.IDLE and self._started)
        if not halted or self._holding(view.t_s):
            self._last = None
            return None
        if view.state is State.IDLE:
            if self.recoveries_left <= 0:
                return None
            self.recoveries_left -= 1
            return self._send(view, Event.START_REQUESTED)
        if self._last is Event.RESUME_REQUESTED and self._last_state is view.state:
            # resume was rejected (no plan yet): start over
            return self._send(
                view, Event.START_REQUESTED if view.state is not State.FAULT else Event.RESET_REQUESTED
            )
        if self.recoveries_left <= 0:
            return None
        self.recoveries_left -= 1
        if view.state is State.PAUSED and self._resumed:
            return self._send(view, Event.START_REQUESTED)   # re-register
        self._resumed = True
        return self._send(view, Event.RESUME_REQUESTED)

    def finished(self, view: OperatorView) -> bool:
        if view.state is State.DONE:
            return True
        if self._holding(view.t_s):
            return False
        halted = view.state in HALTED or (view.state is State.IDLE and self._started)
        if not halted:
            return False
        if self.recoveries_left > 0:
            return False
        # out of attempts: done, unless a resume was just rejected and a restart is still owed
        return not (self._last is Event.RESUME_REQUESTED and self._last_state is view.state)
