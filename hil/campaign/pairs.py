"""Compound faults: the pairs matrix of ``hil campaign --pairs`` and where the second fault goes.

Two families of scenarios (docs/campaign.md, "Compound faults"):

Both pair the 14 device kinds (:data:`~hil.campaign.scenarios.DEVICE_KINDS`); the patient kinds
(a cough, a shift, a marker lost or moved) are single-fault scenarios only.

* **Overlapping** ``A+B@S``: for every unordered pair of different fault kinds {A, B} (A before B
  in :class:`~hil.config.faults.FaultKind` order) and every target state S: A is placed as a single
  fault aimed at S (:func:`~hil.campaign.scenarios.place_fault` on the baseline's window) and B
  starts :data:`OVERLAP_OFFSET_S` later, while A is active, so both hit S (the controller acts
  on a pair of frames at the earliest one tick after A's onset). 91 pairs: 27 on one device
  (camera 15, tracker 6, robot 6) and 64 across devices; x 5 states = 455 scenarios.
* **Second fault during recovery** ``A+B@S+recovery`` (ordered): A is a fault the controller
  answers with a safe state (:func:`recovery_first_kinds`, detect ``watchdog``: 6 kinds), aimed at S;
  B, any of the 14 kinds, starts inside the recovery from A: the first state the controller
  enters by a recovery transition after A's safe state (``recover``/``resume`` into APPROACH,
  ``re_register`` or a restart into REGISTER), found in the session log of the single-fault run
  ``A@S`` of the same seed (the pair run follows that run exactly until B starts), placed as
  :func:`~hil.campaign.scenarios.place_fault` places a fault in a state. A's state picks the
  recovery path, so S is REGISTER (no plan yet: reset, restart, re-registration) or COMPENSATE
  (plan kept: resume, a fresh approach from the actual pose; APPROACH, GATE and LOCK take the
  same path). 6 x 14 x 2 = 168 scenarios.
"""

from __future__ import annotations

import fnmatch
import itertools
from dataclasses import dataclass

from hil.config.faults import FAULT_DEVICE, FaultKind

from .scenarios import DEVICE_KINDS, PROFILES, TARGET_STATES, KindProfile, ScenarioSelectionError, place_fault

#: Overlapping pairs: the second fault starts this long after the first (s): less than one frame
#: period of the simulated camera (15 Hz, 66.7 ms), so both start before the controller's next
#: tick and both hit the targeted state.
OVERLAP_OFFSET_S = 0.05
#: The states a first fault is aimed at in the recovery scenarios: REGISTER (recovery restarts and
#: registers again) and COMPENSATE (recovery resumes with a fresh approach).
RECOVERY_STATES: tuple[str, ...] = ("register", "compensate")
#: Transitions by which the controller re-enters the forward path after a fault (the recovery
#: window starts at the first of them after the first fault's safe state). ``start`` is the
#: restart from IDLE after a reset.
RECOVERY_TRANSITIONS = frozenset({"recover", "resume", "re_register", "start"})
#: Suffix of a recovery scenario's name.
RECOVERY_SUFFIX = "+recovery"


def recovery_first_kinds() -> list[FaultKind]:
    """The first faults of the recovery scenarios, in enum order: the kinds detectable at onset
    (detect ``watchdog``), which the controller answers with a safe state in every state.
    ``motion_rejected`` (detect ``on_command``) is not among them: the servo loop absorbs rejected
    servo commands (``servo_command_failed``) and the procedure goes on once motion is accepted
    again, so it is tolerated in every state and leaves no recovery to place a second fault in."""
    return [k for k in DEVICE_KINDS if PROFILES[k].detect == "watchdog"]


@dataclass(frozen=True)
class PairScenario:
    """Two faults: ``first`` aimed at ``state``, ``second`` overlapping it (``recovery`` False) or
    inside the recovery from it (``recovery`` True)."""

    first: FaultKind
    second: FaultKind
    state: str
    recovery: bool = False

    @property
    def pair(self) -> str:
        """``first+second`` (the report's row)."""
        return f"{self.first.value}+{self.second.value}"

    @property
    def name(self) -> str:
        return f"{self.pair}@{self.state}" + (RECOVERY_SUFFIX if self.recovery else "")

    @property
    def same_device(self) -> bool:
        return FAULT_DEVICE[self.first] == FAULT_DEVICE[self.second]

    @property
    def profile(self) -> KindProfile:
        return PROFILES[self.first]

    @property
    def second_profile(self) -> KindProfile:
        return PROFILES[self.second]


def overlap_scenarios() -> list[PairScenario]:
    """Every unordered pair of different device kinds x every target state (pair-major order)."""
    return [PairScenario(a, b, s) for a, b in itertools.combinations(DEVICE_KINDS, 2) for s in TARGET_STATES]


def recovery_scenarios() -> list[PairScenario]:
    """Every first kind of :func:`recovery_first_kinds` x every second kind (the same kind again
    included) x :data:`RECOVERY_STATES`."""
    return [PairScenario(a, b, s, recovery=True)
            for a in recovery_first_kinds() for b in DEVICE_KINDS for s in RECOVERY_STATES]


def all_pairs() -> list[PairScenario]:
    """The whole pairs matrix: the overlapping scenarios, then the recovery ones."""
    return [*overlap_scenarios(), *recovery_scenarios()]


def _full_pattern(pat: str) -> str:
    """A pattern as a full-name glob. ``A+B`` means either order for overlapping pairs (the
    names keep enum order, so ``robot_disconnect+frame_drop`` finds ``frame_drop+robot_disconnect``);
    ``A`` alone: every pair with A first or second; ``@S`` every pair in S; ``+recovery`` every
    recovery scenario."""
    if pat == RECOVERY_SUFFIX:
        return "*" + RECOVERY_SUFFIX
    head, at, tail = pat.partition("@")
    if not at:
        tail = "*"
    if head == "":
        head = "*"
    return f"{head}@{tail}"


def _matches(sc: PairScenario, pat: str) -> bool:
    full = _full_pattern(pat)
    if fnmatch.fnmatchcase(sc.name, full):
        return True
    head, _, tail = full.partition("@")
    swapped = f"{sc.second.value}+{sc.first.value}@{sc.state}" + (RECOVERY_SUFFIX if sc.recovery else "")
    if not sc.recovery and fnmatch.fnmatchcase(swapped, full):
        return True
    if "+" not in head:  # a single kind: the pair holds it first or second
        return any(fnmatch.fnmatchcase(k.value, head) for k in (sc.first, sc.second)) and (
            fnmatch.fnmatchcase(sc.name.partition("@")[2], tail))
    return False


def select_pairs(patterns: list[str]) -> list[PairScenario]:
    """Pair scenarios matching any pattern (:func:`_full_pattern`; shell wildcards); no pattern:
    the whole matrix. A state pattern without ``+recovery`` matches only overlapping scenarios
    unless it ends in a wildcard (``@compensate*`` both).

    Raises:
        ScenarioSelectionError: a pattern matches nothing (names it and the syntax).
    """
    every = all_pairs()
    if not patterns:
        return every
    chosen: list[PairScenario] = []
    for pat in patterns:
        hit = [s for s in every if _matches(s, pat)]
        if not hit:
            kinds = ", ".join(k.value for k in DEVICE_KINDS)
            firsts = ", ".join(k.value for k in recovery_first_kinds())
            raise ScenarioSelectionError(
                f"pair scenario {pat!r} matches nothing (A+B@STATE or A+B@STATE+recovery, A, B kinds: "
                f"{kinds}; states: {', '.join(TARGET_STATES)}; recovery: first kind one of "
                f"{firsts}, state {' or '.join(RECOVERY_STATES)})")
        chosen += [s for s in hit if s not in chosen]
    return chosen


def place_second(first_start_s: float) -> float:
    """Start (s) of an overlapping scenario's second fault: :data:`OVERLAP_OFFSET_S` after the
    first's."""
    return round(first_start_s + OVERLAP_OFFSET_S, 4)


def recovery_window(entered: list[tuple[float, str, str]], first_onset_s: float,
                    end_s: float) -> tuple[float, float, str] | None:
    """The recovery window of a single-fault run: ``(enter_s, leave_s, state)`` of the first state
    entered by a :data:`RECOVERY_TRANSITIONS` transition after the run first entered a safe state
    (``fault``, ``safe_stop``, ``paused``) at or after ``first_onset_s``. ``entered`` is the run's
    ``(t_s, state, transition)`` list; ``end_s`` closes a window still open at the end. None when
    the fault never led to a safe state or the run never recovered."""
    halted = [i for i, (t, s, _) in enumerate(entered)
              if s in ("fault", "safe_stop", "paused") and t >= first_onset_s - 1e-9]
    if not halted:
        return None
    for i in range(halted[0] + 1, len(entered)):
        t, s, how = entered[i]
        if how in RECOVERY_TRANSITIONS:
            leave = entered[i + 1][0] if i + 1 < len(entered) else end_s
            return (round(t, 4), round(leave, 4), s)
    return None


def place_in_recovery(window: tuple[float, float, str] | None) -> float | None:
    """Start (s) of a recovery scenario's second fault: inside the recovery window as
    :func:`~hil.campaign.scenarios.place_fault` places a fault in a state. None: no recovery."""
    if window is None:
        return None
    return place_fault((window[0], window[1]), 0.0)
