"""The console's operator: key presses and buttons become numbered
:class:`~hil.controller.operator_input.OperatorCommand` s that the controller takes one per tick,
and the controller's verdict on each comes back here for the UI to show.

Thread-safe: :meth:`ConsoleOperator.post` and :meth:`take_results` are called from the UI thread,
:meth:`poll`, :meth:`acknowledge` and :meth:`drain_refused` from the controller thread. Only
operator events can be posted — device data and step results cannot be forged from the console,
and every command goes through the state machine and the safety layer like any other.

Nothing is dropped silently: a command is queued (and then decided and answered by the
controller) or refused here, at once, with the reason — the queue is full (the controller is
stuck) or the console is closing. Refusals are handed to the controller thread, which owns the
session log, by :meth:`drain_refused`.
"""

from __future__ import annotations

import collections
import itertools
import threading
import time

from hil.controller.fsm import OPERATOR_EVENTS, Event
from hil.controller.operator_input import CommandResult, OperatorCommand, OperatorView
from hil.errors import HilError

#: Commands waiting for the controller at most; a further one is refused (never an older one
#: dropped).
MAX_QUEUED = 16
#: Verdicts kept for the UI until it takes them (it does 10 times a second).
_MAX_RESULTS = 256


class ConsoleOperator:
    """Queue of operator commands, and the verdicts on them."""

    def __init__(self) -> None:
        self._queue: collections.deque[OperatorCommand] = collections.deque()
        self._results: collections.deque[CommandResult] = collections.deque(maxlen=_MAX_RESULTS)
        self._refused: list[CommandResult] = []
        self._lock = threading.Lock()
        self._quit = threading.Event()
        self._seq = itertools.count(1)

    def post(self, event: Event, *, origin: str = "console", confirms: str | None = None,
             decline: bool = False) -> CommandResult | None:
        """Queue one operator command for the controller.

        Args:
            event: an ``*_REQUESTED`` event.
            origin: what the operator did (``"key s"``, ``"button Start"``), for the log.
            confirms: with ``CONFIRM_REQUESTED``: the transition the console showed awaiting
                confirmation (``""``: none).
            decline: the operator answered *no* to the prompt for ``confirms``.

        Returns:
            None when queued (the verdict comes later through :meth:`take_results`), or the
            refusal (``outcome == "refused"``), already queued for the session log.

        Raises:
            HilError: ``event`` is not an operator command (a programming error, not an input).
        """
        if event not in OPERATOR_EVENTS:
            raise HilError(f"{event.value} is not an operator command")
        with self._lock:
            cmd = OperatorCommand(event, next(self._seq), origin, confirms, decline, time.monotonic_ns())
            why = ""
            if self._quit.is_set():
                why = "the console is closing (the procedure is being aborted)"
            elif len(self._queue) >= MAX_QUEUED:
                why = f"{MAX_QUEUED} commands already wait for the controller (it is not ticking)"
            if not why:
                self._queue.append(cmd)
                return None
            refused = CommandResult(cmd.seq, origin, event.value, "refused", why, "")
            self._refused.append(refused)
            self._results.append(refused)
            return refused

    def request_quit(self) -> None:
        """Ask the run loop to end (it stops the robot first)."""
        self._quit.set()

    @property
    def quit_requested(self) -> bool:
        return self._quit.is_set()

    def pending_commands(self) -> int:
        """Commands queued and not yet taken by the controller."""
        with self._lock:
            return len(self._queue)

    def take_results(self) -> list[CommandResult]:
        """The verdicts since the last call, oldest first (the UI shows each once)."""
        with self._lock:
            out = list(self._results)
            self._results.clear()
            return out

    # ---------------------------------------------------------- Operator protocol
    def poll(self, view: OperatorView) -> OperatorCommand | None:
        with self._lock:
            return self._queue.popleft() if self._queue else None

    def finished(self, view: OperatorView) -> bool:
        return self._quit.is_set()

    def input_waiting(self) -> bool:
        """WakingOperator: a command is queued, or the console is closing."""
        return bool(self._queue) or self._quit.is_set()

    # ---------------------------------------------------------- AcknowledgingOperator
    def acknowledge(self, result: CommandResult) -> None:
        with self._lock:
            self._results.append(result)

    def drain_refused(self) -> list[CommandResult]:
        with self._lock:
            out, self._refused = self._refused, []
            return out
