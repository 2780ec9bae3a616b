"""The campaign matrix: fault kind x workflow state (x seeds), and where each fault is placed.

A fault is placed inside the window the baseline (fault-free) run of the same seed spent in the
targeted state: the simulator is deterministic for a seed, so the run with the fault follows the
baseline exactly until the fault starts, and the fault hits that state.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from typing import Literal

from hil.config.faults import FAULT_DEVICE, FaultKind
from hil.errors import HilError

#: Workflow states a fault is aimed at (PLAN lasts one frame on the simulator and is skipped).
TARGET_STATES: tuple[str, ...] = ("register", "approach", "gate", "compensate", "lock")

Detect = Literal["watchdog", "on_command", "content"]


@dataclass(frozen=True)
class KindProfile:
    """How long a kind's fault lasts in a campaign and how it becomes detectable.

    ``watchdog``: detectable at onset (an error or a stale/old sample): its safe-state latency is
    bounded. ``on_command``: detectable at the first motion command after onset (bounded from
    there). ``content``: shows only in the data (images, qualities, timing); the controller may
    tolerate it, so its latency is recorded but not bounded.
    """

    duration_s: float
    detect: Detect


PROFILES: dict[FaultKind, KindProfile] = {
    FaultKind.FRAME_DROP: KindProfile(0.6, "watchdog"),
    FaultKind.FROZEN_FRAME: KindProfile(0.6, "content"),
    FaultKind.STALE_TIMESTAMP: KindProfile(0.6, "watchdog"),
    FaultKind.LR_DESYNC: KindProfile(0.6, "content"),
    FaultKind.OCCLUSION: KindProfile(1.0, "content"),
    FaultKind.GLARE: KindProfile(1.0, "content"),
    FaultKind.TRACKER_TIMEOUT: KindProfile(0.6, "watchdog"),
    FaultKind.CORRUPT_RECORD: KindProfile(0.3, "watchdog"),
    FaultKind.BAD_QUALITY: KindProfile(1.0, "content"),
    FaultKind.SENSOR_MISSING: KindProfile(1.0, "content"),
    FaultKind.ROBOT_DISCONNECT: KindProfile(0.6, "watchdog"),
    FaultKind.PROTECTIVE_STOP: KindProfile(0.6, "watchdog"),
    FaultKind.MOTION_REJECTED: KindProfile(0.6, "on_command"),
    FaultKind.MOTION_LAG: KindProfile(1.5, "content"),
    # the patient (issue 41): the body, not a device; they show only in the markers
    FaultKind.COUGH: KindProfile(0.8, "content"),
    FaultKind.PATIENT_SHIFT: KindProfile(0.5, "content"),
    FaultKind.MARKER_LOST: KindProfile(1.5, "content"),
    FaultKind.MARKER_MOVED: KindProfile(1.5, "content"),
}


@dataclass(frozen=True)
class Scenario:
    kind: FaultKind
    state: str

    @property
    def name(self) -> str:
        return f"{self.kind.value}@{self.state}"

    @property
    def device(self) -> str:
        return FAULT_DEVICE[self.kind]

    @property
    def profile(self) -> KindProfile:
        return PROFILES[self.kind]


#: The kinds that hit a device (camera, tracker, robot), and those that happen to the patient
#: (the simulated body). The compound-fault matrix (:mod:`hil.campaign.pairs`) pairs device kinds.
DEVICE_KINDS: tuple[FaultKind, ...] = tuple(k for k in FaultKind if FAULT_DEVICE[k] != "patient")
PATIENT_KINDS: tuple[FaultKind, ...] = tuple(k for k in FaultKind if FAULT_DEVICE[k] == "patient")


def all_scenarios() -> list[Scenario]:
    return [Scenario(k, s) for k in FaultKind for s in TARGET_STATES]


class ScenarioSelectionError(HilError, ValueError):
    """A scenario pattern matches nothing."""


def select(patterns: list[str]) -> list[Scenario]:
    """Scenarios matching any pattern: ``kind@state`` with shell wildcards, or a bare ``kind`` /
    ``@state`` (all states / all kinds). No pattern: the whole matrix.

    Raises:
        ScenarioSelectionError: a pattern matches nothing (names the pattern and the choices).
    """
    every = all_scenarios()
    if not patterns:
        return every
    chosen: list[Scenario] = []
    for pat in patterns:
        full = pat if "@" in pat else f"{pat}@*"
        if full.startswith("@"):
            full = "*" + full
        hit = [s for s in every if fnmatch.fnmatchcase(s.name, full)]
        if not hit:
            kinds = ", ".join(k.value for k in FaultKind)
            raise ScenarioSelectionError(
                f"scenario {pat!r} matches nothing (kinds: {kinds}; states: {', '.join(TARGET_STATES)})"
            )
        chosen += [s for s in hit if s not in chosen]
    return chosen


def place_fault(window_s: tuple[float, float] | None, duration_s: float) -> float | None:
    """Start time (s after the devices opened) of a fault aimed at a state the baseline spent
    ``window_s`` in: 30 % into the window, at most 0.3 s after its start. None when the baseline
    never reached the state."""
    if window_s is None:
        return None
    a, b = window_s
    return round(a + min(0.3 * max(b - a, 0.0), 0.3), 4)
