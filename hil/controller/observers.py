"""Who watches the controller, and how they are kept away from control.

An observer is called in the controller's thread with a frozen
:class:`~hil.controller.snapshot.ControllerSnapshot`: after every tick (``on_tick``) and after
every applied transition (``on_transition``). Plain callables (``observers=`` of the controller)
get the tick; plugins implement the ``hil_on_tick`` / ``hil_on_transition`` hooks
(:mod:`plugins.hookspecs`). Each call is isolated: an exception is logged (``observer_failed``,
once per observer and distinct error) and never reaches the control loop, and the other observers
are still called. The snapshot is built only when somebody watches.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

from hil.controller import events as ev
from hil.controller.fsm import FireResult
from hil.controller.snapshot import ControllerSnapshot
from hil.log import get_logger
from hil.session.log import SessionLog

_log = get_logger(__name__)

TickObserver = Callable[[ControllerSnapshot], None]


class HookCaller(Protocol):
    """What the observers need of a plugin manager: each plugin's implementation of a hook."""

    def implementations(self, hook: str) -> Sequence[tuple[str, Callable[..., Any]]]: ...


class Observers:
    """Calls the tick observers and the plugins' runtime hooks (module doc)."""

    def __init__(self, observers: Sequence[TickObserver], hooks: HookCaller | None,
                 session: SessionLog) -> None:
        self.observers = tuple(observers)
        self.hooks = hooks
        self.session = session
        self._errors: dict[str, str] = {}

    def _implementations(self, hook: str) -> Sequence[tuple[str, Callable[..., Any]]]:
        return () if self.hooks is None else self.hooks.implementations(hook)

    def watching_ticks(self) -> bool:
        return bool(self.observers) or bool(self._implementations("hil_on_tick"))

    def watching_transitions(self) -> bool:
        return bool(self._implementations("hil_on_transition"))

    def on_tick(self, snapshot: ControllerSnapshot) -> None:
        for obs in self.observers:
            self._call(getattr(obs, "__name__", repr(obs)), obs, snapshot)
        for name, fn in self._implementations("hil_on_tick"):
            self._call(name, fn, snapshot=snapshot)

    def on_transition(self, transition: FireResult, snapshot: ControllerSnapshot) -> None:
        for name, fn in self._implementations("hil_on_transition"):
            self._call(name, fn, transition=transition, snapshot=snapshot)

    def _call(self, name: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        try:
            fn(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - an observer (display, stream, plugin) must not stop control
            error = f"{type(exc).__name__}: {exc}"
            _log.warning(ev.OBSERVER_FAILED, observer=name, error=error)
            if self._errors.get(name) != error:  # once per distinct error, not every tick
                self._errors[name] = error
                self.session.write(ev.OBSERVER_FAILED, observer=name, error=error)
