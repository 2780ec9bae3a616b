"""What a run measured: the per-tick figures the controller collects, the simulator-truth meter
(an observer of the tick, never part of the control path) and the :class:`RunSummary` that
``hil run`` prints (docs/run.md)."""

from __future__ import annotations

import math
from array import array
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from hil.controller import events as ev
from hil.controller.estimate import Estimate
from hil.controller.fsm import State
from hil.controller.truth import GroundTruth
from hil.session.log import SessionLog

if TYPE_CHECKING:
    from hil.controller.planning import RigGeometry
    from hil.controller.snapshot import ControllerSnapshot


@dataclass
class RunSummary:
    """What ``hil run`` reports (see docs/run.md)."""

    final_state: str
    states: list[str]
    timeline: list[dict[str, Any]]
    fre_mm: float | None
    tre_expected_mm: float | None
    robot_fre_mm: float | None
    lock_error_mm: float | None
    lock_error_max_mm: float | None
    lock_direction_error_deg: float | None
    comp_error_rms_mm: float | None
    comp_error_p95_mm: float | None
    comp_error_max_mm: float | None
    latency_ms: dict[str, float | None]
    processing_ms: dict[str, float | None]
    gate_open_fraction: float | None
    time_to_lock_s: float | None
    duration_s: float
    frames: int
    commands_sent: int
    commands_refused: int
    faults: list[str]
    session_log: str
    needle_direction_error_deg: float | None = None
    #: the published chain head: SHA-256 of the session log's last line (set once it is closed)
    session_log_sha256: str | None = None
    #: the HTML report built after the run (``hil run``; None when not built)
    report: str | None = None
    #: the tracked needle tip against the planned target while locked (last sample; see docs/run.md)
    tracked_needle: dict[str, float] | None = None
    #: marker-location time per stereo pair, p50 / p95 (ms; set by hil run from its locator)
    locate_ms: dict[str, float | None] = field(default_factory=lambda: {"p50": None, "p95": None})
    comp_errors_mm: list[float] = field(default_factory=list, repr=False)
    comp_error_age_s: list[float] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """The JSON summary (docs/run.md); the per-tick error series is left out."""
        d = dict(self.__dict__)
        d.pop("comp_errors_mm")
        d.pop("comp_error_age_s")
        return d


def percentile(values: Sequence[float], q: float) -> float | None:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if len(values) else None


def samples() -> array[float]:
    """A per-frame sample series: 8 bytes a value (a long run's figures must not grow the process
    by a Python object per frame: 32 bytes)."""
    return array("d")


@dataclass
class RunMetrics:
    """Figures collected during the run (ms on the controller clock unless said)."""

    detect_ms: array[float] = field(default_factory=samples)       # exposure -> markers perceived
    processing_ms: array[float] = field(default_factory=samples)   # tick work, wall clock (profiling)
    gate_samples: int = 0
    gate_open_samples: int = 0
    lock_time_s: float | None = None
    frames: int = 0
    frames_overwritten: int = 0   # prefetched pairs replaced before a tick took them (latest wins)

    def on_frame(self, est: Estimate, state: State, gate_tolerance_mm: float) -> None:
        """After perception: the gate-open fraction counts every registered pair outside REGISTER."""
        if est.patient_reg is not None and state is not State.REGISTER:
            self.gate_samples += 1
            self.gate_open_samples += int(est.gate_deviation_mm() <= gate_tolerance_mm)

    @property
    def gate_open_fraction(self) -> float | None:
        return (self.gate_open_samples / self.gate_samples) if self.gate_samples else None


class TruthMeter:
    """Simulation only, an observer of the controller's snapshots (never used for control): after
    each tick in COMPENSATE or LOCK, the real guide's error against the real moving path
    (``truth_error``), from the simulator's truth and the arm's pose the snapshot read when it was
    built (``ControllerSnapshot.robot_now``, at ``t_ns``). Its lists feed the run summary."""

    def __init__(self, truth: GroundTruth | None, rig: RigGeometry, session: SessionLog) -> None:
        self.truth, self.rig, self.session = truth, rig, session
        self.comp_errors_mm = samples()
        self.comp_error_age_s = samples()   # time since COMPENSATE was entered, per sample
        self.lock_errors: list[tuple[float, float]] = []
        self.__name__ = "truth_meter"   # how the observer is named in an observer_failed record

    def errors(self, snap: ControllerSnapshot) -> tuple[float, float] | None:
        """(position error mm, direction error deg) of the guide, or None without a plan or a
        robot state."""
        state, standoff_mm = snap.robot_now, snap.standoff_mm
        if self.truth is None or state is None or standoff_mm is None:
            return None
        now = state.t_ns
        T_robot_from_guide = state.T_robot_from_tcp @ self.rig.T_tcp_from_guide
        T_guide = self.truth.T_optical_from_robot @ T_robot_from_guide
        # a simulator with a real rig's errors knows the real arm, not only its (late, imprecise) report
        if (T_of := self.truth.T_optical_from_flange(now := snap.t_ns)) is not None:
            T_guide = T_of @ self.rig.T_flange_from_guide
        entry = np.asarray(self.truth.entry_optical(now), dtype=np.float64)
        target = np.asarray(self.truth.target_optical(now), dtype=np.float64)
        u = (target - entry) / np.linalg.norm(target - entry)
        ideal = entry - standoff_mm * u
        pos = float(np.linalg.norm(T_guide.t - ideal))
        cosang = float(np.clip(T_guide.R[:, 2] @ u, -1.0, 1.0))
        return pos, math.degrees(math.acos(cosang))

    def __call__(self, snap: ControllerSnapshot) -> None:
        """Observe one snapshot (the controller's thread, after the tick)."""
        state = State(snap.state)
        if state not in (State.COMPENSATE, State.LOCK):
            return
        errs = self.errors(snap)
        if errs is None:
            return
        if state is State.COMPENSATE:
            entered_s = snap.timeline[-1].t_s if snap.timeline else 0.0
            self.comp_errors_mm.append(errs[0])
            self.comp_error_age_s.append(snap.t_s - entered_s)
        else:
            self.lock_errors.append(errs)
        self.session.write(ev.TRUTH_ERROR, state=state, position_mm=errs[0], direction_deg=errs[1])
