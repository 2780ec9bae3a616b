"""The procedure state machine: explicit states, events and a complete transition table as data.

IGSTK's discipline: every (state, event) pair has a programmed outcome — a transition, an
in-state handling ("stay"), or an explicit rejection with its reason. A rejected event is logged
(``transition_rejected``) and changes nothing. The table is checked for completeness and
reachability at import time (python-statemachine's ``validate_*`` checks) and printed by
``hil states``.

Operator commands end in ``_REQUESTED``; device and internal events are past-tense facts.
Forward transitions have a name (``plan_to_approach`` …); those listed in the configured
confirmations wait for ``CONFIRM_REQUESTED`` before they are applied (``--auto`` confirms).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from types import MappingProxyType
from typing import Final

from hil.errors import HilError


class State(StrEnum):
    """Procedure states (nouns)."""

    IDLE = "idle"
    REGISTER = "register"
    PLAN = "plan"
    APPROACH = "approach"
    GATE = "gate"
    COMPENSATE = "compensate"
    LOCK = "lock"
    PAUSED = "paused"
    RETRACT = "retract"
    FAULT = "fault"
    SAFE_STOP = "safe_stop"
    DONE = "done"


class Event(StrEnum):
    """Inputs of the state machine."""

    # operator commands
    START_REQUESTED = "start_requested"
    CONFIRM_REQUESTED = "confirm_requested"
    PAUSE_REQUESTED = "pause_requested"
    RESUME_REQUESTED = "resume_requested"
    RETRACT_REQUESTED = "retract_requested"
    ABORT_REQUESTED = "abort_requested"
    RESET_REQUESTED = "reset_requested"
    # device data (handled inside the state)
    FRAME_RECEIVED = "frame_received"
    TRACKER_SAMPLE_RECEIVED = "tracker_sample_received"
    ROBOT_STATE_RECEIVED = "robot_state_received"
    # internal step results
    REGISTERED = "registered"
    REGISTRATION_FAILED = "registration_failed"
    PLAN_ACCEPTED = "plan_accepted"
    PLAN_REFUSED = "plan_refused"
    STANDOFF_REACHED = "standoff_reached"
    APPROACH_FAILED = "approach_failed"
    GATE_OPENED = "gate_opened"
    ALIGNED = "aligned"
    CORRECTION_OUT_OF_BOUNDS = "correction_out_of_bounds"
    LOCK_LOST = "lock_lost"
    DRIFT_DETECTED = "drift_detected"
    LOCK_COMPLETED = "lock_completed"
    RETRACTED = "retracted"
    TIMED_OUT = "timed_out"
    FAULT_DETECTED = "fault_detected"


OPERATOR_EVENTS: Final = frozenset(e for e in Event if e.value.endswith("_requested"))
DATA_EVENTS: Final = frozenset({Event.FRAME_RECEIVED, Event.TRACKER_SAMPLE_RECEIVED,
                                Event.ROBOT_STATE_RECEIVED})
#: States in which the robot may be moving under the controller's command.
MOTION_STATES: Final = frozenset({State.APPROACH, State.COMPENSATE, State.RETRACT})
#: States where the procedure has ended (the run loop stops when it reaches one).
FINAL_STATES: Final = frozenset({State.DONE})
#: States that end a run when no operator is there to decide (auto mode).
HALT_STATES: Final = frozenset({State.FAULT, State.SAFE_STOP})


@dataclass(frozen=True)
class Goto:
    """Apply a transition. ``name`` identifies it for confirmations; ``guard`` names a
    condition the caller must report true (see :meth:`Fsm.fire`)."""

    target: State
    name: str
    guard: str | None = None


@dataclass(frozen=True)
class Stay:
    """Accepted; handled inside the current state (no transition)."""

    note: str


@dataclass(frozen=True)
class Reject:
    """Not accepted in this state; logged as ``transition_rejected`` with the reason."""

    reason: str


Outcome = Goto | Stay | Reject


class TransitionTableError(HilError):
    """The transition table is incomplete or inconsistent."""


class TransitionRejectedError(HilError):
    """An event was rejected. Attributes: ``state``, ``event``, ``reason``."""

    def __init__(self, state: State, event: Event, reason: str) -> None:
        self.state = state
        self.event = event
        self.reason = reason
        super().__init__(f"{event.value} rejected in {state.value}: {reason}")


# ------------------------------------------------------------------ the table
_ALL = tuple(State)
_FORWARD: dict[tuple[State, Event], Goto] = {
    (State.IDLE, Event.START_REQUESTED): Goto(State.REGISTER, "start"),
    (State.REGISTER, Event.REGISTERED): Goto(State.PLAN, "register_to_plan"),
    (State.REGISTER, Event.REGISTRATION_FAILED): Goto(State.IDLE, "registration_failed"),
    (State.REGISTER, Event.TIMED_OUT): Goto(State.IDLE, "registration_timed_out"),
    (State.PLAN, Event.PLAN_ACCEPTED): Goto(State.APPROACH, "plan_to_approach"),
    (State.PLAN, Event.PLAN_REFUSED): Goto(State.IDLE, "plan_refused"),
    (State.APPROACH, Event.STANDOFF_REACHED): Goto(State.GATE, "approach_to_gate"),
    (State.APPROACH, Event.APPROACH_FAILED): Goto(State.FAULT, "approach_failed"),
    (State.APPROACH, Event.TIMED_OUT): Goto(State.FAULT, "approach_timed_out"),
    (State.GATE, Event.GATE_OPENED): Goto(State.COMPENSATE, "gate_to_compensate"),
    (State.GATE, Event.TIMED_OUT): Goto(State.GATE, "gate_timed_out"),
    (State.GATE, Event.CORRECTION_OUT_OF_BOUNDS): Goto(State.PAUSED, "gate_out_of_bounds"),
    (State.COMPENSATE, Event.ALIGNED): Goto(State.LOCK, "compensate_to_lock"),
    (State.COMPENSATE, Event.CORRECTION_OUT_OF_BOUNDS): Goto(State.PAUSED, "correction_out_of_bounds"),
    (State.COMPENSATE, Event.TIMED_OUT): Goto(State.GATE, "compensate_timed_out"),
    (State.LOCK, Event.LOCK_COMPLETED): Goto(State.DONE, "lock_to_done"),
    (State.LOCK, Event.LOCK_LOST): Goto(State.COMPENSATE, "lock_lost"),
    (State.LOCK, Event.DRIFT_DETECTED): Goto(State.RETRACT, "drift_retract"),
    (State.LOCK, Event.CORRECTION_OUT_OF_BOUNDS): Goto(State.PAUSED, "lock_out_of_bounds"),
    (State.RETRACT, Event.RETRACTED): Goto(State.SAFE_STOP, "retracted"),
    (State.RETRACT, Event.TIMED_OUT): Goto(State.FAULT, "retract_timed_out"),
    # recovery: always from where the robot actually is (APPROACH re-plans from the actual pose)
    (State.PAUSED, Event.RESUME_REQUESTED): Goto(State.APPROACH, "resume", guard="plan_current"),
    (State.SAFE_STOP, Event.RESUME_REQUESTED): Goto(State.APPROACH, "resume", guard="plan_current"),
    (State.FAULT, Event.RESUME_REQUESTED): Goto(State.APPROACH, "recover", guard="plan_current"),
    (State.PAUSED, Event.START_REQUESTED): Goto(State.REGISTER, "re_register"),
    (State.SAFE_STOP, Event.START_REQUESTED): Goto(State.REGISTER, "re_register"),
    (State.FAULT, Event.RESET_REQUESTED): Goto(State.IDLE, "reset"),
    (State.SAFE_STOP, Event.RESET_REQUESTED): Goto(State.IDLE, "reset"),
    (State.DONE, Event.RESET_REQUESTED): Goto(State.IDLE, "reset"),
    (State.IDLE, Event.RESET_REQUESTED): Goto(State.IDLE, "reset"),
}
for _s in (State.APPROACH, State.GATE, State.COMPENSATE, State.LOCK):
    _FORWARD[(_s, Event.PAUSE_REQUESTED)] = Goto(State.PAUSED, "pause")
for _s in (State.APPROACH, State.GATE, State.COMPENSATE, State.LOCK, State.PAUSED, State.SAFE_STOP):
    _FORWARD[(_s, Event.RETRACT_REQUESTED)] = Goto(State.RETRACT, "retract", guard="has_plan")
for _s in (State.REGISTER, State.PLAN, State.APPROACH, State.GATE, State.COMPENSATE, State.LOCK,
           State.PAUSED, State.RETRACT):
    _FORWARD[(_s, Event.ABORT_REQUESTED)] = Goto(State.SAFE_STOP, "abort")
for _s in _ALL:
    if _s is not State.FAULT:
        _FORWARD[(_s, Event.FAULT_DETECTED)] = Goto(State.FAULT, "fault")


def _default(state: State, event: Event) -> Stay | Reject:
    """Outcome of every pair the forward table does not name."""
    if event in DATA_EVENTS:
        return Stay("data is consumed by the state's own step")
    if event is Event.CONFIRM_REQUESTED:
        return Stay("applies the transition waiting for confirmation, if any")
    if event is Event.FAULT_DETECTED:  # only FAULT itself gets here
        return Stay("already in fault; the further reason is recorded")
    if event in OPERATOR_EVENTS:
        reasons = {
            Event.START_REQUESTED: "a procedure is already under way",
            Event.PAUSE_REQUESTED: "nothing is moving or waiting to move here",
            Event.RESUME_REQUESTED: "nothing is paused",
            Event.RETRACT_REQUESTED: "the guide is not near the patient",
            Event.ABORT_REQUESTED: "nothing to abort; the robot is not under way",
            Event.RESET_REQUESTED: "reset is only possible once stopped (fault, safe stop, done)",
        }
        if state is State.FAULT and event is not Event.RESET_REQUESTED:
            return Reject("in fault: resume (recover) or reset only")
        return Reject(reasons[event])
    return Reject(f"{event.value} is not expected in {state.value} (stale or out-of-order step result)")


def _build() -> Mapping[tuple[State, Event], Outcome]:
    table: dict[tuple[State, Event], Outcome] = {}
    for s in State:
        for e in Event:
            table[(s, e)] = _FORWARD.get((s, e)) or _default(s, e)
    return MappingProxyType(table)


TRANSITIONS: Final[Mapping[tuple[State, Event], Outcome]] = _build()

#: Every transition name that the confirmation config may list.
CONFIRMABLE: Final = frozenset({"register_to_plan", "plan_to_approach", "approach_to_gate",
                                "gate_to_compensate", "compensate_to_lock", "lock_to_done"})
#: Recovery transitions: they re-enter the forward path (APPROACH) from a stop. A recovery into a
#: state whose forward entry needs a confirmation that was not given for the current plan waits
#: for that confirmation (a stop must never skip it; see :meth:`Fsm.fire`).
RECOVERY: Final = frozenset({"resume", "recover"})


def check_table(table: Mapping[tuple[State, Event], Outcome], initial: State = State.IDLE) -> None:
    """Raise :class:`TransitionTableError` unless the table is complete and sound.

    Checks: every (state, event) has an outcome; every state is reachable from ``initial``; no
    non-final state is a trap (each has an exit); every state except FAULT goes to FAULT on
    FAULT_DETECTED; every motion state can be aborted to SAFE_STOP; the confirmable names exist.
    """
    missing = [(s, e) for s in State for e in Event if (s, e) not in table]
    if missing:
        raise TransitionTableError(f"transition table is not complete: {len(missing)} pairs missing, "
                                   f"first {missing[0][0].value} x {missing[0][1].value}")
    seen = {initial}
    frontier = [initial]
    while frontier:
        s = frontier.pop()
        for e in Event:
            out = table[(s, e)]
            if isinstance(out, Goto) and out.target not in seen:
                seen.add(out.target)
                frontier.append(out.target)
    unreachable = set(State) - seen
    if unreachable:
        raise TransitionTableError(f"unreachable states: {sorted(x.value for x in unreachable)}")
    for s in State:
        exits = [o for e in Event if isinstance(o := table[(s, e)], Goto) and o.target is not s]
        if not exits:
            raise TransitionTableError(f"state {s.value} is a trap (no way out)")
        if s is not State.FAULT:
            out = table[(s, Event.FAULT_DETECTED)]
            if not (isinstance(out, Goto) and out.target is State.FAULT):
                raise TransitionTableError(f"{s.value} does not go to fault on fault_detected")
    for s in MOTION_STATES:
        out = table[(s, Event.ABORT_REQUESTED)]
        if not (isinstance(out, Goto) and out.target is State.SAFE_STOP):
            raise TransitionTableError(f"{s.value} cannot be aborted to safe_stop")
    names = {o.name for o in table.values() if isinstance(o, Goto)}
    if not names >= CONFIRMABLE:
        raise TransitionTableError(f"confirmable names missing: {sorted(CONFIRMABLE - names)}")


check_table(TRANSITIONS)


# ------------------------------------------------------------------ the machine
@dataclass(frozen=True)
class FireResult:
    """What :meth:`Fsm.fire` did.

    ``kind``: ``transition`` (applied), ``stay`` (accepted in-state), ``pending`` (waits for a
    CONFIRM_REQUESTED), ``rejected``. ``transition_name`` names the Goto when there is one.
    """

    kind: str
    source: State
    target: State
    event: Event
    reason: str = ""
    transition_name: str = ""

    @property
    def changed(self) -> bool:
        return self.kind == "transition"


@dataclass(frozen=True)
class Pending:
    """A transition waiting for an operator confirmation."""

    event: Event
    goto: Goto
    reason: str
    #: the forward confirmation this one stands in for (a recovery re-asking ``plan_to_approach``)
    authorises: str = ""


Listener = Callable[[FireResult], None]


class Fsm:
    """The state machine. Not thread-safe: one caller (the controller's tick) fires events.

    Args:
        confirm: names of transitions (``plan_to_approach`` …) that wait for CONFIRM_REQUESTED.
        listener: called with every :class:`FireResult` (applied, pending, stayed or rejected);
            the controller logs it to the session log.

    Raises:
        TransitionTableError: ``confirm`` names a transition that does not exist.
    """

    def __init__(
        self,
        confirm: Iterable[str] = (),
        *,
        table: Mapping[tuple[State, Event], Outcome] = TRANSITIONS,
        initial: State = State.IDLE,
        listener: Listener | None = None,
    ) -> None:
        self._confirm = frozenset(confirm)
        unknown = self._confirm - CONFIRMABLE
        if unknown:
            raise TransitionTableError(f"cannot require confirmation of {sorted(unknown)}; "
                                       f"confirmable: {sorted(CONFIRMABLE)}")
        check_table(table, initial)
        self._table = table
        self._state = initial
        self._pending: Pending | None = None
        self._listener = listener
        # the confirmable forward transition entering each state (plan_to_approach for APPROACH)
        self._entry: dict[State, Goto] = {
            o.target: o for (s, _e), o in table.items()
            if isinstance(o, Goto) and o.name in CONFIRMABLE and o.target is not s}
        self._source = {o.name: s for (s, _e), o in table.items()
                        if isinstance(o, Goto) and o.name in CONFIRMABLE}
        # confirmable transitions applied (confirmed) since their source state was last entered
        self._authorised: set[str] = set()

    @property
    def state(self) -> State:
        return self._state

    @property
    def pending(self) -> Pending | None:
        """The transition waiting for confirmation, if any."""
        return self._pending

    def outcome(self, event: Event) -> Outcome:
        return self._table[(self._state, event)]

    def accepts(self, event: Event) -> bool:
        return not isinstance(self.outcome(event), Reject)

    def fire(
        self, event: Event, *, reason: str = "", guards: Mapping[str, bool] | None = None,
    ) -> FireResult:
        """Feed one event. Never raises for a rejected event: the result says ``rejected``.

        A Goto whose guard is not reported true by ``guards`` is rejected. A Goto whose name is
        in the confirmations becomes ``pending`` (state unchanged) until CONFIRM_REQUESTED. A
        recovery (``resume``/``recover``) into a state whose forward entry needs a confirmation
        that was never given since its source state was last entered (a stop while
        ``plan_to_approach`` was pending) also becomes ``pending``: the confirmation is re-asked,
        never skipped. Any applied transition (an abort, a fault …) and any fault clear a pending
        one; a rejected event changes nothing at all.
        """
        source = self._state
        out = self._table[(source, event)]
        if event is Event.FAULT_DETECTED:
            self._pending = None  # also in FAULT (a stay): a new fault cancels a pending recovery
        if event is Event.CONFIRM_REQUESTED:
            if self._pending is None:
                return self._emit(
                    FireResult("rejected", source, source, event, "nothing awaits confirmation"))
            p = self._pending
            self._pending = None
            return self._apply(source, p.event, p.goto, p.reason or reason, p.authorises)
        if isinstance(out, Reject):
            return self._emit(FireResult("rejected", source, source, event, out.reason))
        if isinstance(out, Stay):
            return self._emit(FireResult("stay", source, source, event, reason or out.note))
        if out.guard is not None and not (guards or {}).get(out.guard, False):
            return self._emit(FireResult("rejected", source, source, event,
                                         f"guard {out.guard} is false", out.name))
        if out.name in self._confirm:
            self._pending = Pending(event, out, reason)
            return self._emit(FireResult("pending", source, out.target, event, reason, out.name))
        unconfirmed = self._unconfirmed_entry(out)
        if unconfirmed is not None:
            why = (f"{unconfirmed} was not confirmed for the current plan; "
                   f"confirm to {out.name} into {out.target.value}")
            self._pending = Pending(event, out, why, authorises=unconfirmed)
            return self._emit(FireResult("pending", source, out.target, event, why, out.name))
        return self._apply(source, event, out, reason)

    def _unconfirmed_entry(self, goto: Goto) -> str | None:
        """The name of the confirmation a recovery into ``goto.target`` still needs, if any."""
        if goto.name not in RECOVERY:
            return None
        entry = self._entry.get(goto.target)
        if entry is None or entry.name not in self._confirm or entry.name in self._authorised:
            return None
        return entry.name

    def _apply(self, source: State, event: Event, goto: Goto, reason: str,
               authorises: str = "") -> FireResult:
        self._pending = None
        self._state = goto.target
        # entering a state starts it afresh (PLAN makes a new plan): its onward confirmations lapse
        self._authorised -= {n for n, s in self._source.items() if s is goto.target}
        for name in (goto.name, authorises):
            if name in CONFIRMABLE:
                self._authorised.add(name)
        return self._emit(FireResult("transition", source, goto.target, event, reason, goto.name))

    def _emit(self, result: FireResult) -> FireResult:
        if self._listener is not None:
            self._listener(result)
        return result


# ------------------------------------------------------------------ rendering
def transitions_list(
    table: Mapping[tuple[State, Event], Outcome] = TRANSITIONS,
) -> list[tuple[State, Event, Goto]]:
    """The applied transitions (Goto outcomes), in table order."""
    return [(s, e, o) for (s, e), o in table.items() if isinstance(o, Goto)]


def render_text(table: Mapping[tuple[State, Event], Outcome] = TRANSITIONS,
                confirm: Iterable[str] = ()) -> str:
    """The full table, one line per (state, event) pair: outcome and reason."""
    conf = frozenset(confirm)
    lines = [f"{'state':<11} {'event':<26} outcome"]
    for (s, e), o in table.items():
        if isinstance(o, Goto):
            extra = f" [{o.name}" + (f", guard {o.guard}" if o.guard else "") + \
                (", needs confirm" if o.name in conf else "") + "]"
            lines.append(f"{s.value:<11} {e.value:<26} -> {o.target.value}{extra}")
        elif isinstance(o, Stay):
            lines.append(f"{s.value:<11} {e.value:<26} stay ({o.note})")
        else:
            lines.append(f"{s.value:<11} {e.value:<26} reject ({o.reason})")
    return "\n".join(lines) + "\n"


def render_mermaid(table: Mapping[tuple[State, Event], Outcome] = TRANSITIONS,
                   confirm: Iterable[str] = ()) -> str:
    """A mermaid ``stateDiagram-v2`` of the applied transitions (rejections are not drawn)."""
    conf = frozenset(confirm)
    lines = ["stateDiagram-v2", f"    [*] --> {State.IDLE.value}"]
    for s, e, o in transitions_list(table):
        mark = " (confirm)" if o.name in conf else ""
        guard = f" [{o.guard}]" if o.guard else ""
        lines.append(f"    {s.value} --> {o.target.value}: {e.value}{guard}{mark}")
    lines.append(f"    {State.DONE.value} --> [*]")
    return "\n".join(lines) + "\n"


def render_dot(table: Mapping[tuple[State, Event], Outcome] = TRANSITIONS,
               confirm: Iterable[str] = ()) -> str:
    """A Graphviz digraph of the applied transitions (rejections are not drawn)."""
    conf = frozenset(confirm)
    lines = ["digraph procedure {", "    rankdir=LR;", "    node [shape=box, style=rounded];"]
    for st in State:
        shape = ", peripheries=2" if st in FINAL_STATES else ""
        color = ", color=red" if st in HALT_STATES else ""
        lines.append(f'    {st.value} [label="{st.name}"{shape}{color}];')
    for s, e, o in transitions_list(table):
        style = ", style=dashed" if o.name in conf else ""
        guard = f" [{o.guard}]" if o.guard else ""
        lines.append(f'    {s.value} -> {o.target.value} [label="{e.value}{guard}"{style}];')
    lines.append("}")
    return "\n".join(lines) + "\n"


def render_markdown(table: Mapping[tuple[State, Event], Outcome] = TRANSITIONS,
                    confirm: Iterable[str] = ()) -> str:
    """``docs/states.md``: the diagram and the complete table (regenerate with
    ``hil states --format markdown > docs/states.md``; a test checks it is current)."""
    conf = frozenset(confirm)
    out = [
        "# Procedure state machine",
        "",
        "Generated from `hil/controller/fsm.py` by `hil states --format markdown`; do not edit.",
        "",
        "Operator commands end in `_requested`. Every (state, event) pair has an outcome: a transition,",
        "`stay` (handled inside the state) or `reject` (logged as `transition_rejected`, nothing changes).",
        f"Transitions waiting for an operator confirmation by default: {', '.join(sorted(conf)) or 'none'}",
        "(configurable: `[procedure] confirm`).",
        "",
        "```mermaid",
        render_mermaid(table, conf).rstrip("\n"),
        "```",
        "",
        "| state | event | outcome | name / reason |",
        "|---|---|---|---|",
    ]
    for (s, e), o in table.items():
        if isinstance(o, Goto):
            extra = o.name + (f" (guard {o.guard})" if o.guard else "")
            extra += " (confirm)" if o.name in conf else ""
            out.append(f"| {s.value} | {e.value} | -> {o.target.value} | {extra} |")
        elif isinstance(o, Stay):
            out.append(f"| {s.value} | {e.value} | stay | {o.note} |")
        else:
            out.append(f"| {s.value} | {e.value} | reject | {o.reason} |")
    return "\n".join(out) + "\n"
