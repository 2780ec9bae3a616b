"""Compound faults (``hil campaign --pairs``) without simulating: the pairs matrix, its names and
selection, where the second fault goes, the operator's holds, the summary's rows."""

from __future__ import annotations

import itertools
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.campaign.operator import CampaignOperator
from hil.campaign.pairs import (
    OVERLAP_OFFSET_S,
    RECOVERY_STATES,
    all_pairs,
    overlap_scenarios,
    place_in_recovery,
    place_second,
    recovery_first_kinds,
    recovery_scenarios,
    recovery_window,
    select_pairs,
)
from hil.campaign.pairs_campaign import pair_spec, pairs_matrix_ids, single_runs
from hil.campaign.recorder import Recording, StateSample
from hil.campaign.report import pair_row_of, row_order, table
from hil.campaign.runner import RunResult, RunSpec, judge_second
from hil.campaign.scenarios import DEVICE_KINDS, PATIENT_KINDS, TARGET_STATES, ScenarioSelectionError
from hil.cli import main
from hil.config.faults import FAULT_DEVICE, FaultKind
from hil.controller.fsm import Event, State
from hil.controller.operator_input import OperatorView

KIND_NAMES = [k.value for k in DEVICE_KINDS]


def test_overlap_matrix_counts() -> None:
    scs = overlap_scenarios()
    assert len(scs) == 91 * 5 == 455
    pairs = {(s.first, s.second) for s in scs}
    assert len(pairs) == 91
    same = {p for p in pairs if FAULT_DEVICE[p[0]] == FAULT_DEVICE[p[1]]}
    assert len(same) == 15 + 6 + 6  # camera, tracker, robot
    assert len(pairs - same) == 64
    assert all(a != b and KIND_NAMES.index(a.value) < KIND_NAMES.index(b.value) for a, b in pairs)
    assert {s.state for s in scs} == set(TARGET_STATES)


def test_recovery_matrix_counts() -> None:
    scs = recovery_scenarios()
    # motion_rejected is tolerated in every state (the servo loop absorbs the rejections): no
    # recovery to place a second fault in
    assert [k.value for k in recovery_first_kinds()] == [
        "frame_drop", "stale_timestamp", "tracker_timeout", "corrupt_record", "robot_disconnect",
        "protective_stop"]
    assert len(scs) == 6 * 14 * 2 == 168
    assert {s.state for s in scs} == set(RECOVERY_STATES) == {"register", "compensate"}
    assert sum(1 for s in scs if s.first is s.second) == 6 * 2  # the same kind again
    assert len(all_pairs()) == 455 + 168 == 623


def test_names() -> None:
    o = overlap_scenarios()[0]
    assert (o.name, o.pair, o.same_device) == (
        "frame_drop+frozen_frame@register", "frame_drop+frozen_frame", True)
    r = recovery_scenarios()[-1]
    assert r.name == "protective_stop+motion_lag@compensate+recovery"
    names = [s.name for s in all_pairs()]
    assert len(set(names)) == len(names)


@pytest.mark.parametrize(
    ("patterns", "count", "first"),
    [
        (["frame_drop+robot_disconnect@lock"], 1, "frame_drop+robot_disconnect@lock"),
        (["robot_disconnect+frame_drop@lock"], 1, "frame_drop+robot_disconnect@lock"),  # either order
        # every state, overlapping and (this order) in recovery
        (["frame_drop+robot_disconnect"], 5 + 2, "frame_drop+robot_disconnect@register"),
        (["@lock"], 91, "frame_drop+frozen_frame@lock"),
        (["+recovery"], 168, "frame_drop+frame_drop@register+recovery"),
        (["*@compensate+recovery"], 84, "frame_drop+frame_drop@compensate+recovery"),
        (["robot_disconnect+glare@register+recovery"], 1, "robot_disconnect+glare@register+recovery"),
        # 13 partners x 5 states, 14 x 2 with it first in recovery, 5 x 2 more with it second
        (["frame_drop"], 65 + 28 + 10, "frame_drop+frozen_frame@register"),
        (["*_stop+*@gate"], 13, "frame_drop+protective_stop@gate"),  # globs match either order too
    ],
)
def test_select_pairs(patterns: list[str], count: int, first: str) -> None:
    got = select_pairs(patterns)
    assert (len(got), got[0].name) == (count, first)


def test_select_recovery_is_ordered_and_bounded_first() -> None:
    # glare may be tolerated: no recovery to place a second fault in; nor LOCK (COMPENSATE's path)
    for pat in ("glare+robot_disconnect@compensate+recovery", "robot_disconnect+glare@lock+recovery",
                "motion_rejected+glare@compensate+recovery"):
        with pytest.raises(ScenarioSelectionError, match=r"matches nothing .* first kind one of frame_drop"):
            select_pairs([pat])
    with pytest.raises(ScenarioSelectionError, match="matches nothing"):
        select_pairs(["frame_drop+frame_drop@lock"])  # overlapping pairs are of two different kinds


@given(a=st.sampled_from(DEVICE_KINDS), b=st.sampled_from(DEVICE_KINDS),
       state=st.sampled_from(TARGET_STATES))
def test_any_two_kinds_select_their_overlapping_scenario_in_either_order(a: FaultKind, b: FaultKind,
                                                                         state: str) -> None:
    if a is b:
        return
    want = sorted([a, b], key=KIND_NAMES.index)
    for x, y in ((a, b), (b, a)):
        (only,) = select_pairs([f"{x.value}+{y.value}@{state}"])
        assert (only.first, only.second, only.state, only.recovery) == (want[0], want[1], state, False)


def test_cli_reports_a_bad_pair_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["campaign", "--pairs", "nosuch+glare"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("hil campaign: error: pair scenario 'nosuch+glare' matches nothing")
    assert main(["campaign", "--pairs", "--transport"]) == 2


@given(start=st.floats(0.0, 100.0, allow_nan=False))
def test_second_fault_overlaps_the_first(start: float) -> None:
    b = place_second(round(start, 4))
    assert b == round(round(start, 4) + OVERLAP_OFFSET_S, 4)
    assert 0 < b - start < min(p.duration_s for p in (s.profile for s in overlap_scenarios()))


def test_recovery_window_is_the_first_recovery_entry_after_the_safe_state() -> None:
    entered = [(0.03, "register", "start"), (2.3, "plan", "register_to_plan"),
               (2.36, "approach", "plan_to_approach"), (7.2, "fault", "fault"),
               (7.96, "approach", "recover"), (8.5, "gate", "approach_to_gate"), (9.0, "lock", "x")]
    assert recovery_window(entered, 7.0, 12.0) == (7.96, 8.5, "approach")
    assert place_in_recovery((7.96, 8.5, "approach")) == round(7.96 + 0.3 * 0.54, 4)
    # the fault hit REGISTER: reset, then a restart registers again
    entered = [(0.03, "register", "start"), (0.5, "fault", "fault"), (1.6, "idle", "reset"),
               (1.67, "register", "start"), (4.0, "plan", "register_to_plan")]
    assert recovery_window(entered, 0.4, 9.0) == (1.67, 4.0, "register")
    assert place_in_recovery((1.67, 4.0, "register")) == 1.97
    # tolerated (no safe state), or never recovered: nowhere to place a second fault
    assert recovery_window(entered[:1], 0.4, 9.0) is None
    assert recovery_window(entered[:2], 0.4, 9.0) is None
    assert place_in_recovery(None) is None
    # a recovery still open at the end of the run closes there
    assert recovery_window(entered[:4], 0.4, 9.0) == (1.67, 9.0, "register")


def test_pair_specs_place_both_faults() -> None:
    windows = {"compensate": [6.6967, 7.1527], "register": [0.03, 2.2967]}
    (ov,) = select_pairs(["frame_drop+robot_disconnect@compensate"])
    spec = pair_spec(ov, 1, windows, None, "c.toml", None, 90.0)
    assert isinstance(spec, RunSpec)
    assert (spec.scenario, spec.start_s, spec.duration_s) == (
        "frame_drop+robot_disconnect@compensate", 6.8335, 0.6)
    assert (spec.second_kind, spec.second_start_s, spec.second_duration_s, spec.recovery) == (
        "robot_disconnect", 6.8835, 0.6, False)
    assert spec.windows() == [("frame_drop", 6.8335, 0.6), ("robot_disconnect", 6.8835, 0.6)]
    (rc,) = select_pairs(["robot_disconnect+tracker_timeout@compensate+recovery"])
    single = {"outcome": "safe_state", "recovery_window_s": [7.9633, 8.4967, "approach"]}
    spec = pair_spec(rc, 1, windows, single, "c.toml", None, 90.0)
    assert isinstance(spec, RunSpec)
    assert (spec.start_s, spec.second_start_s, spec.second_state, spec.recovery) == (
        6.8335, 8.1233, "approach", True)
    assert spec.scenario == "robot_disconnect+tracker_timeout@compensate+recovery"
    why = pair_spec(rc, 1, windows, {"outcome": "tolerated", "recovery_window_s": None}, "c.toml", None, 90.0)
    assert why == ("the single-fault run robot_disconnect@compensate of seed 1 never recovered (outcome "
                   "tolerated): no recovery to place the second fault in")
    assert pair_spec(ov, 1, {}, None, "c.toml", None, 90.0) == "baseline of seed 1 never reached compensate"


def test_matrix_ids_hold_the_placement_runs() -> None:
    scs = select_pairs(["frame_drop+glare@lock", "robot_disconnect+glare@register+recovery",
                        "robot_disconnect+frame_drop@register+recovery"])
    assert [s.name for s in single_runs(scs)] == ["robot_disconnect@register"]
    assert pairs_matrix_ids(scs, [1, 2])[:5] == [
        "baseline_s1", "robot_disconnect@register_s1", "frame_drop+glare@lock_s1",
        "robot_disconnect+glare@register+recovery_s1", "robot_disconnect+frame_drop@register+recovery_s1"]
    assert len(pairs_matrix_ids(scs, [1, 2])) == 10


def _view(state: State, t_s: float) -> OperatorView:
    return OperatorView(state, None, "", t_s, True)


def test_operator_holds_recovery_through_a_second_fault() -> None:
    op = CampaignOperator(recover_after_s=5.0, max_recoveries=4, holds=((6.0, 7.1),))
    assert op.poll(_view(State.IDLE, 0.0)) is Event.START_REQUESTED
    assert op.poll(_view(State.FAULT, 4.9)) is None
    assert op.poll(_view(State.FAULT, 5.0)) is Event.RESUME_REQUESTED
    assert op.poll(_view(State.FAULT, 6.5)) is None  # the second fault: hold until it is over + settle
    assert not op.finished(_view(State.FAULT, 7.0))
    assert op.poll(_view(State.FAULT, 7.1)) is Event.RESUME_REQUESTED
    assert op.recoveries_left == 2


def test_pairs_table_rows() -> None:
    results: list[dict[str, Any]] = [
        {"scenario": "baseline", "kind": None, "state": None, "passed": True},
        {"scenario": "robot_disconnect@register", "kind": "robot_disconnect", "state": "register",
         "passed": True, "safe_latency_ms": 100.0},
        {"scenario": "frame_drop+glare@lock", "kind": "frame_drop", "state": "lock", "passed": False,
         "safe_latency_ms": 400.0},
        {"scenario": "robot_disconnect+glare@register+recovery", "kind": "robot_disconnect",
         "state": "register", "passed": True, "safe_latency_ms": 120.0},
    ]
    rows = row_order(results, pair_row_of)
    assert rows == ["robot_disconnect", "frame_drop+glare", "robot_disconnect+glare+recovery"]
    assert table(results, row_of=pair_row_of, order=rows).splitlines() == [
        "fault \\ state                    register    lock",
        "robot_disconnect                 pass 100ms  -",
        "frame_drop+glare                 -           FAIL 1/1 400ms",
        "robot_disconnect+glare+recovery  pass 120ms  -",
    ]


def test_every_pair_is_in_the_matrix_once() -> None:
    got = {(s.first, s.second) for s in overlap_scenarios()}
    assert got == {tuple(sorted(p, key=lambda k: KIND_NAMES.index(k.value)))
                   for p in itertools.combinations(DEVICE_KINDS, 2)}


def test_patient_kinds_are_single_fault_scenarios_only() -> None:
    """The pairs matrix pairs the device kinds; a patient kind in a pair pattern is refused."""
    assert [k.value for k in PATIENT_KINDS] == ["cough", "patient_shift", "marker_lost", "marker_moved"]
    assert len(DEVICE_KINDS) == 14
    assert all(FAULT_DEVICE[k] == "patient" for k in PATIENT_KINDS)
    assert not any(s.first in PATIENT_KINDS or s.second in PATIENT_KINDS for s in all_pairs())
    with pytest.raises(ScenarioSelectionError, match="matches nothing"):
        select_pairs(["frame_drop+cough@lock"])


# ---------------------------------------------------------------------- judging the second fault
T0_NS = 1_000_000_000
ENTERED = [(0.03, "register"), (2.3, "plan"), (2.36, "approach"), (4.4, "gate"), (6.7, "compensate"),
           (6.9, "fault"), (7.96, "approach"), (8.2, "fault"), (9.4, "approach"), (11.0, "gate"),
           (12.0, "compensate"), (12.5, "lock"), (14.0, "done")]


def _recovery_spec(second: str = "robot_disconnect") -> RunSpec:
    return RunSpec("r", "c.toml", None, 1, kind="tracker_timeout", state="compensate", start_s=6.83,
                   duration_s=0.6, second_kind=second, second_start_s=8.12, second_duration_s=0.6,
                   recovery=True, second_state="approach")


def _judged(spec: RunSpec, entered: list[tuple[float, str]], stopped_at_s: float | None = 8.25,
            final: str = "done", lock_mm: float | None = 0.3) -> RunResult:
    rec = Recording()
    if stopped_at_s is not None:
        rec.states.append(StateSample(T0_NS + round(stopped_at_s * 1e9), 0.2, "stopped", "normal"))
    op = CampaignOperator(recover_after_s=7.93, max_recoveries=4, holds=((8.12, 9.22),))
    op.commands = [(7.95, "resume_requested"), (9.3, "resume_requested")]
    result = RunResult("r", spec.scenario, spec.kind, spec.state, 1, passed=False, final_state=final,
                       lock_error_mm=lock_mm, second_latency_bound_ms=183.333)
    judge_second(spec, result, rec, (T0_NS, entered, 14.1), op)
    return result


def test_second_fault_in_recovery_judged_on_its_own() -> None:
    r = _judged(_recovery_spec(), ENTERED)
    assert r.reasons == []
    assert (r.second_kind, r.second_onset_s, r.second_state_at_onset, r.second_safe_state) == (
        "robot_disconnect", 8.12, "approach", "fault")
    assert (r.second_safe_latency_ms, r.second_latency_bound_ms) == (80.0, 183.333)


def test_second_fault_in_recovery_failures() -> None:
    late = [(t + (0.2 if t >= 8.2 else 0.0), s) for t, s in ENTERED]  # FAULT 280 ms after onset
    assert _judged(_recovery_spec(), late, stopped_at_s=8.45).reasons == [
        "second fault: safe state fault 280 ms after the fault was detectable (bound 183 ms)"]
    assert _judged(_recovery_spec(), ENTERED, stopped_at_s=None).reasons == [
        "second fault: robot not seen stopped (< 1.0 mm/s) in fault before recovery"]
    no_lock = [(t, s) for t, s in ENTERED if t < 9.0]
    assert _judged(_recovery_spec(), no_lock, final="fault").reasons == [
        "second fault: did not continue to lock after recovery (final state fault)"]
    missed = [(t, s) for t, s in ENTERED if t != 7.96]  # still in FAULT when the second fault came
    assert _judged(_recovery_spec(), missed).reasons == [
        "second fault started in fault, not in the recovery state approach it was placed in: not tested"]
    tolerated = [(t, s) for t, s in ENTERED if t != 8.2]
    assert _judged(_recovery_spec("glare"), tolerated).reasons == []
    assert _judged(_recovery_spec("glare"), tolerated, lock_mm=2.5).reasons == [
        "tolerated, but lock error 2.5 mm > 2.0 mm"]
    assert _judged(_recovery_spec("glare"), tolerated, final="safe_stop").reasons == [
        "second fault neither reached a safe state nor was tolerated (final state safe_stop)"]
