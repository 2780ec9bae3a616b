"""Judging the second fault of a compound-fault run (``hil campaign --pairs``; docs/campaign.md,
"Compound faults").

The run as a whole is judged from its first fault by :func:`hil.campaign.runner.judge`. This adds
the second fault: its onset and the state it hit, and, for a second fault placed in the recovery
from the first, the same criteria again from the second fault's onset: the first safe state
entered at or after it (within the second fault's device bound when it is detectable, the robot
seen stopped before the next recovery, the procedure continuing to lock), or, when none was
entered, tolerated (done, lock within 2 mm). A recovery scenario whose second fault did not land in
the recovery state its placement aimed at fails: that cell was not tested.
"""

from __future__ import annotations

from .operator import CampaignOperator
from .recorder import Recording
from .runner import (
    SAFE_STATES,
    RunResult,
    RunSpec,
    _judge_tolerated,
    _state_at,
    check_safe_state,
    detectable_s,
)

Timeline = tuple[int, list[tuple[float, str]], float]


def judge_second(spec: RunSpec, result: RunResult, rec: Recording, timeline: Timeline,
                 operator: CampaignOperator) -> None:
    """Fill ``result``'s ``second_*`` fields and add to ``result.reasons`` (module doc).
    ``timeline`` is ``(t0_ns, [(t_s, state entered)], end_s)``."""
    assert spec.second_kind is not None
    assert spec.second_start_s is not None
    t0_ns, entered, end_s = timeline
    onset = spec.second_start_s
    result.second_kind = spec.second_kind
    result.second_onset_s = onset
    if end_s < onset:
        result.reasons.append(f"the run ended at {end_s:.2f} s, before the second fault at {onset:.2f} s")
        return
    result.second_state_at_onset = _state_at(entered, onset)
    if not spec.recovery:
        return
    if result.second_state_at_onset != spec.second_state:
        result.reasons.append(
            f"second fault started in {result.second_state_at_onset}, not in the recovery state "
            f"{spec.second_state} it was placed in: not tested")
        return
    safe = [(t, s) for t, s in entered if s in SAFE_STATES and t >= onset - 1e-9]
    if not safe:
        _judge_tolerated(result, "second fault")
        return
    ref = detectable_s(spec.second_kind, onset, rec, t0_ns)
    bound = result.second_latency_bound_ms
    if ref is None or ref > safe[0][0]:  # safe before the second fault was detectable: not bounded
        ref, bound = onset, None
    v = check_safe_state(safe[0], ref, bound, t0_ns, entered, end_s, rec, operator, result.final_state)
    result.second_safe_state = safe[0][1]
    result.second_safe_latency_ms = v.latency_ms
    if not v.bounded:
        result.second_latency_bound_ms = None
    result.reasons += [f"second fault: {r}" for r in v.reasons]
