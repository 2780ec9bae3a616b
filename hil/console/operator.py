"""The console's operator: key presses and buttons become ``*_REQUESTED`` events that the
controller reads once per tick (:class:`hil.controller.procedure.Operator`).

Thread-safe: :meth:`ConsoleOperator.post` is called from the UI thread, :meth:`poll` from the
controller thread. Only operator events can be posted — device data and step results cannot be
forged from the console, and every command goes through the state machine and the safety
layer like any other (a rejected command is logged and changes nothing).
"""

from __future__ import annotations

import collections
import threading

from hil.controller.fsm import OPERATOR_EVENTS, Event
from hil.controller.procedure import OperatorView
from hil.errors import HilError

_MAX_QUEUED = 16


class ConsoleOperator:
    """Queue of operator commands (at most 16 waiting; older ones are dropped beyond that)."""

    def __init__(self) -> None:
        self._queue: collections.deque[Event] = collections.deque(maxlen=_MAX_QUEUED)
        self._lock = threading.Lock()
        self._quit = threading.Event()

    def post(self, event: Event) -> None:
        """Queue one operator command for the next tick.

        Raises:
            HilError: ``event`` is not an operator command.
        """
        if event not in OPERATOR_EVENTS:
            raise HilError(f"{event.value} is not an operator command")
        with self._lock:
            self._queue.append(event)

    def request_quit(self) -> None:
        """Ask the run loop to end (it stops the robot first)."""
        self._quit.set()

    @property
    def quit_requested(self) -> bool:
        return self._quit.is_set()

    def pending_commands(self) -> int:
        with self._lock:
            return len(self._queue)

    # ---------------------------------------------------------- Operator protocol
    def poll(self, view: OperatorView) -> Event | None:
        with self._lock:
            return self._queue.popleft() if self._queue else None

    def finished(self, view: OperatorView) -> bool:
        return self._quit.is_set()
