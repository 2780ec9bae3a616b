"""Operator input: what an operator may ask, what the controller answers, and the stock operators.

Contract (issue 14): every operator input is either executed or refused, and the answer is
recorded. The controller takes at most one :class:`OperatorCommand` per tick from its
:class:`Operator`, logs it (``operator_command``), decides it — through the state machine, the
robot-readiness check, or the confirmation check below — and logs the verdict
(``operator_command_result``, a :class:`CommandResult`). An operator that wants the verdicts back
(the console, to show them) implements :class:`AcknowledgingOperator`.

A confirmation names what the operator saw: ``OperatorCommand.confirms`` is the transition the
console showed as awaiting confirmation when the key was pressed (``""``: it showed none). The
controller executes a confirmation only when that is the transition pending now, so a key pressed
before a prompt was on screen, or pressed twice, never confirms a motion the operator did not see.
``confirms=None`` (scripted operators: ``--auto``, campaigns) confirms whatever is pending.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

from hil.controller.fsm import HALT_STATES, Event, State

#: The verdicts a command can get.
Outcome = Literal["executed", "pending", "rejected", "refused", "declined"]


@dataclass(frozen=True)
class OperatorView:
    """What an operator sees each tick."""

    state: State
    pending: str | None
    last_reason: str
    t_s: float
    started: bool


@dataclass(frozen=True)
class OperatorCommand:
    """One operator input.

    Attributes:
        event: an ``*_REQUESTED`` event (``CONFIRM_REQUESTED`` also for a declined prompt).
        seq: the operator's own sequence number (0 for operators that do not number them).
        origin: where it came from, for the log (``"key c"``, ``"button"``, ``"auto"``...).
        confirms: for ``CONFIRM_REQUESTED``: the transition the operator saw awaiting
            confirmation (``""``: none shown); None: confirm whatever is pending (scripts).
        decline: the operator answered *no* to the prompt for ``confirms``: nothing changes,
            the confirmation stays pending, and the answer is logged.
        posted_ns: when the operator gave it (``time.monotonic_ns``; 0: not recorded), for the
            input -> action latency in the session log.
    """

    event: Event
    seq: int = 0
    origin: str = "operator"
    confirms: str | None = None
    decline: bool = False
    posted_ns: int = 0


@dataclass(frozen=True)
class CommandResult:
    """The controller's verdict on one :class:`OperatorCommand` (or the console's, when it could
    not even queue it: ``refused``). ``reason`` says why in plain words; ``state`` is the state
    it was decided in."""

    seq: int
    origin: str
    input: str
    outcome: Outcome
    reason: str
    state: str

    @property
    def accepted(self) -> bool:
        return self.outcome in ("executed", "pending")

    def message(self) -> str:
        """One line for the operator: ``"<input>: <outcome> — <reason>"``."""
        name = self.input.removesuffix("_requested")
        return f"{name}: {self.outcome}" + (f" — {self.reason}" if self.reason else "")


class Operator(Protocol):
    """Operator input: one command (an ``*_REQUESTED`` event, or an :class:`OperatorCommand`) or
    None per tick."""

    def poll(self, view: OperatorView) -> Event | OperatorCommand | None: ...

    def finished(self, view: OperatorView) -> bool:
        """True when the run should end (nothing more will be asked)."""
        ...


@runtime_checkable
class WakingOperator(Protocol):
    """An operator whose inputs arrive asynchronously (the console): the controller's wait for the
    next stereo pair ends as soon as one is waiting, so a stop or abort is acted on at once."""

    def input_waiting(self) -> bool:
        """Whether a command waits to be polled. Never blocks; any thread."""
        ...


@runtime_checkable
class AcknowledgingOperator(Protocol):
    """An operator that is told every verdict and hands over the inputs it refused itself."""

    def acknowledge(self, result: CommandResult) -> None:
        """Called by the controller thread once per decided command. Must not block."""
        ...

    def drain_refused(self) -> list[CommandResult]:
        """Inputs the operator refused before they reached the controller (queue full, closing),
        to be written to the session log by the log's owner. Never blocks."""
        ...


def as_command(polled: Event | OperatorCommand) -> OperatorCommand:
    """A polled event as a command (scripted operators return bare events)."""
    return polled if isinstance(polled, OperatorCommand) else OperatorCommand(polled)


class AutoOperator:
    """``--auto``: starts, confirms every pending transition, re-registers after an
    out-of-bounds pause (at most ``max_reregistrations`` times); ends the run in DONE, FAULT,
    SAFE_STOP, a failed start (back in IDLE), or a pause it will not resolve."""

    def __init__(self, max_reregistrations: int = 1) -> None:
        self.reregs_left = max_reregistrations
        self._started = False

    def poll(self, view: OperatorView) -> Event | None:
        if not self._started and view.state is State.IDLE:
            self._started = True
            return Event.START_REQUESTED
        if view.pending is not None:
            return Event.CONFIRM_REQUESTED
        if view.state is State.PAUSED and self.reregs_left > 0:
            self.reregs_left -= 1
            return Event.START_REQUESTED
        return None

    def finished(self, view: OperatorView) -> bool:
        if view.state in HALT_STATES or view.state is State.DONE:
            return True
        if view.state is State.IDLE and view.started and self._started:
            return True
        return view.state is State.PAUSED and self.reregs_left <= 0
