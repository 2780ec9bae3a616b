"""The transition table: complete, sound, exhaustively exercised; rejections change nothing."""

from __future__ import annotations

import itertools

import pytest

from hil.cli import main
from hil.controller.fsm import (
    CONFIRMABLE,
    TRANSITIONS,
    Event,
    FireResult,
    Fsm,
    Goto,
    Reject,
    State,
    Stay,
    TransitionTableError,
    check_table,
    render_dot,
    render_mermaid,
    render_text,
)

ALL_PAIRS = list(itertools.product(State, Event))


def test_table_has_an_outcome_for_every_pair() -> None:
    """Every state x event pair is programmed (IGSTK completeness)."""
    assert len(TRANSITIONS) == len(State) * len(Event)
    assert set(TRANSITIONS) == set(ALL_PAIRS)


def test_an_incomplete_table_is_refused() -> None:
    table = dict(TRANSITIONS)
    del table[(State.GATE, Event.GATE_OPENED)]
    with pytest.raises(TransitionTableError, match="not complete"):
        check_table(table)


def test_a_trap_state_is_refused() -> None:
    table = {k: (Reject("x") if k[0] is State.DONE and isinstance(v, Goto) else v)
             for k, v in TRANSITIONS.items()}
    with pytest.raises(TransitionTableError, match="done is a trap"):
        check_table(table)


def test_an_unreachable_state_is_refused() -> None:
    table = {k: (Reject("x") if isinstance(v, Goto) and v.target is State.RETRACT else v)
             for k, v in TRANSITIONS.items()}
    with pytest.raises(TransitionTableError, match="unreachable states: \\['retract'\\]"):
        check_table(table)


def _fsm_in(state: State, listener: list[FireResult] | None = None, confirm: tuple[str, ...] = ()) -> Fsm:
    return Fsm(confirm, initial=state, listener=None if listener is None else listener.append)


#: every guard the table names, true (has_plan: a guide plan; plan_current: one made on the
#: patient registration in force)
GUARDS_TRUE = {"has_plan": True, "plan_current": True}


@pytest.mark.parametrize(("state", "event"), ALL_PAIRS, ids=[f"{s.value}-{e.value}" for s, e in ALL_PAIRS])
def test_every_pair_does_exactly_what_the_table_says(state: State, event: Event) -> None:
    """Exhaustive: each pair, fired with guards true, lands where the table says and is reported."""
    seen: list[FireResult] = []
    fsm = _fsm_in(state, seen)
    out = TRANSITIONS[(state, event)]
    res = fsm.fire(event, guards=GUARDS_TRUE)
    assert seen == [res]
    if event is Event.CONFIRM_REQUESTED:
        assert (res.kind, fsm.state) == ("rejected", state)  # nothing pending
    elif isinstance(out, Goto):
        assert (res.kind, res.source, res.target, fsm.state) == ("transition", state, out.target, out.target)
        assert res.transition_name == out.name
    elif isinstance(out, Stay):
        assert (res.kind, fsm.state) == ("stay", state)
    else:
        assert (res.kind, fsm.state, res.reason) == ("rejected", state, out.reason)


@pytest.mark.parametrize(("state", "event"),
                         [(s, e) for (s, e), o in TRANSITIONS.items() if isinstance(o, Goto) and o.guard],
                         ids=lambda x: x.value)
def test_a_false_guard_rejects_and_changes_nothing(state: State, event: Event) -> None:
    fsm = _fsm_in(state)
    out = TRANSITIONS[(state, event)]
    assert isinstance(out, Goto)
    res = fsm.fire(event, guards=dict.fromkeys(GUARDS_TRUE, False))
    assert (res.kind, fsm.state) == ("rejected", state)
    assert res.reason == f"guard {out.guard} is false"


def test_fault_is_reachable_from_every_state_but_itself() -> None:
    for s in State:
        fsm = _fsm_in(s)
        fsm.fire(Event.FAULT_DETECTED, reason="watchdog: camera")
        assert fsm.state is State.FAULT


def test_rejected_operator_events_are_never_half_applied() -> None:
    """A rejected event leaves state and pending confirmation untouched."""
    fsm = _fsm_in(State.PLAN, confirm=("plan_to_approach",))
    assert fsm.fire(Event.PLAN_ACCEPTED).kind == "pending"
    pending = fsm.pending
    for ev in (Event.START_REQUESTED, Event.RESUME_REQUESTED, Event.PAUSE_REQUESTED, Event.STANDOFF_REACHED):
        assert fsm.fire(ev).kind == "rejected"
        assert fsm.state is State.PLAN
        assert fsm.pending is pending


def test_confirmation_holds_the_transition_until_confirmed() -> None:
    fsm = _fsm_in(State.PLAN, confirm=("plan_to_approach",))
    res = fsm.fire(Event.PLAN_ACCEPTED, reason="reachable")
    assert (res.kind, res.target, fsm.state) == ("pending", State.APPROACH, State.PLAN)
    res = fsm.fire(Event.CONFIRM_REQUESTED)
    assert (res.kind, res.event, fsm.state, res.reason) == ("transition", Event.PLAN_ACCEPTED,
                                                           State.APPROACH, "reachable")
    assert fsm.pending is None


def test_abort_clears_a_pending_confirmation() -> None:
    fsm = _fsm_in(State.PLAN, confirm=("plan_to_approach",))
    fsm.fire(Event.PLAN_ACCEPTED)
    fsm.fire(Event.ABORT_REQUESTED)
    assert (fsm.state, fsm.pending) == (State.SAFE_STOP, None)
    assert fsm.fire(Event.CONFIRM_REQUESTED).kind == "rejected"


def test_without_confirmation_config_the_transition_applies_at_once() -> None:
    fsm = _fsm_in(State.PLAN)
    assert fsm.fire(Event.PLAN_ACCEPTED).kind == "transition"


@pytest.mark.parametrize("name", sorted(CONFIRMABLE))
def test_each_confirmable_transition_can_be_held(name: str) -> None:
    (state, event), = [k for k, o in TRANSITIONS.items() if isinstance(o, Goto) and o.name == name]
    fsm = _fsm_in(state, confirm=(name,))
    assert fsm.fire(event).kind == "pending"
    assert fsm.fire(Event.CONFIRM_REQUESTED).kind == "transition"


def test_unknown_confirmation_name_is_refused() -> None:
    with pytest.raises(TransitionTableError, match="cannot require confirmation of \\['resume'\\]"):
        Fsm(("resume",))


def test_the_nominal_path_reaches_done() -> None:
    fsm = Fsm()
    for ev in (Event.START_REQUESTED, Event.REGISTERED, Event.PLAN_ACCEPTED, Event.STANDOFF_REACHED,
               Event.GATE_OPENED, Event.ALIGNED, Event.LOCK_COMPLETED):
        assert fsm.fire(ev).kind == "transition"
    assert fsm.state is State.DONE


def test_renderings_show_every_transition() -> None:
    gotos = [(s, e, o) for (s, e), o in TRANSITIONS.items() if isinstance(o, Goto)]
    text = render_text()
    assert len(text.splitlines()) == 1 + len(TRANSITIONS)
    mer = render_mermaid(confirm=("plan_to_approach",))
    assert mer.count(" --> ") == len(gotos) + 2
    assert "plan --> approach: plan_accepted (confirm)" in mer
    dot = render_dot()
    assert dot.count(" -> ") == len(gotos)
    assert dot.startswith("digraph procedure {")


@pytest.mark.parametrize("fmt", ["text", "mermaid", "dot"])
def test_hil_states_prints_the_table(fmt: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["states", "--format", fmt]) == 0
    out = capsys.readouterr().out
    assert "compensate" in out


def test_docs_states_md_is_current(capsys: pytest.CaptureFixture[str]) -> None:
    """docs/states.md is the output of `hil states --format markdown` (regenerate when the table changes)."""
    assert main(["states", "--format", "markdown"]) == 0
    with open("docs/states.md", encoding="utf-8") as fh:
        assert fh.read() == capsys.readouterr().out


# ------------------------------------------------------------------ recovery never skips a confirmation
@pytest.mark.parametrize("stop", [Event.FAULT_DETECTED, Event.ABORT_REQUESTED])
def test_recovery_re_asks_a_confirmation_that_was_never_given(stop: Event) -> None:
    """Bug: a protective stop while plan_to_approach waited for its confirmation, then RESUME went
    FAULT -> APPROACH and the robot moved unconfirmed. The recovery must wait for a confirmation."""
    fsm = _fsm_in(State.PLAN, confirm=("plan_to_approach",))
    assert fsm.fire(Event.PLAN_ACCEPTED).kind == "pending"
    fsm.fire(stop, reason="robot: protective_stop")
    assert fsm.pending is None
    stopped = fsm.state
    res = fsm.fire(Event.RESUME_REQUESTED, guards=GUARDS_TRUE)
    assert (res.kind, fsm.state, res.target) == ("pending", stopped, State.APPROACH)
    assert "plan_to_approach" in res.reason
    assert fsm.pending is not None
    res = fsm.fire(Event.CONFIRM_REQUESTED)
    assert (res.kind, fsm.state) == ("transition", State.APPROACH)
    assert res.transition_name in ("recover", "resume")


def test_recovery_after_a_given_confirmation_applies_at_once() -> None:
    fsm = _fsm_in(State.PLAN, confirm=("plan_to_approach",))
    fsm.fire(Event.PLAN_ACCEPTED)
    fsm.fire(Event.CONFIRM_REQUESTED)
    fsm.fire(Event.FAULT_DETECTED, reason="robot: protective_stop")
    res = fsm.fire(Event.RESUME_REQUESTED, guards=GUARDS_TRUE)
    assert (res.kind, fsm.state, res.transition_name) == ("transition", State.APPROACH, "recover")


def test_a_new_plan_needs_a_new_confirmation_before_recovery() -> None:
    fsm = _fsm_in(State.PLAN, confirm=("plan_to_approach",))
    fsm.fire(Event.PLAN_ACCEPTED)
    fsm.fire(Event.CONFIRM_REQUESTED)
    fsm.fire(Event.PAUSE_REQUESTED)
    for ev in (Event.START_REQUESTED, Event.REGISTERED):  # re-register: a new plan is made
        assert fsm.fire(ev).kind == "transition"
    assert fsm.fire(Event.PLAN_ACCEPTED).kind == "pending"
    fsm.fire(Event.FAULT_DETECTED, reason="robot: protective_stop")
    assert fsm.fire(Event.RESUME_REQUESTED, guards=GUARDS_TRUE).kind == "pending"
    assert fsm.state is State.FAULT


def test_a_fault_cancels_a_pending_recovery() -> None:
    fsm = _fsm_in(State.PLAN, confirm=("plan_to_approach",))
    fsm.fire(Event.PLAN_ACCEPTED)
    fsm.fire(Event.FAULT_DETECTED, reason="robot: protective_stop")
    fsm.fire(Event.RESUME_REQUESTED, guards=GUARDS_TRUE)
    fsm.fire(Event.FAULT_DETECTED, reason="watchdog: camera")
    assert fsm.pending is None
    assert fsm.fire(Event.CONFIRM_REQUESTED).kind == "rejected"
    assert fsm.state is State.FAULT
