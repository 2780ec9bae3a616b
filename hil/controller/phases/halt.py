"""The states where the arm stays stopped: IDLE, PAUSED, SAFE_STOP, DONE and FAULT. Entering one
stops the robot; a stop that cannot be delivered is retried every tick by the supervisor."""

from __future__ import annotations

from typing import ClassVar

from hil.controller.commands import Stop
from hil.controller.fsm import State
from hil.controller.phases.base import Phase, PhaseContext, PhaseResult


class HaltPhase(Phase):
    """One of the stopped states (``state`` is set per instance)."""

    HALTS: ClassVar[frozenset[State]] = frozenset(
        {State.IDLE, State.PAUSED, State.SAFE_STOP, State.DONE, State.FAULT})

    def __init__(self, ctx: PhaseContext, state: State) -> None:
        super().__init__(ctx)
        assert state in self.HALTS
        self.halt_state = state
        self.reason = ""

    def enter_with_reason(self, now_ns: int, transition: str, resumed: bool, reason: str) -> PhaseResult:
        self.reason = reason
        return self.enter(now_ns, transition, resumed)

    def on_enter(self, transition: str) -> PhaseResult:
        s = self.halt_state
        return PhaseResult().command(Stop("fault: " + self.reason if s is State.FAULT else s.value))
