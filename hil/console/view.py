"""What the console shows, as plain data: built in the controller thread after a tick (bounded
work: a few small array operations), read by the UI thread. Immutable once built.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hil.console.keys import CONFIRM_KEYS_TEXT
from hil.controller.fsm import State

if TYPE_CHECKING:
    from hil.controller.plan_file import ProcedurePlan
    from hil.controller.snapshot import ControllerSnapshot

#: States shown on the workflow line, in procedure order.
WORKFLOW: tuple[State, ...] = (State.IDLE, State.REGISTER, State.PLAN, State.APPROACH, State.GATE,
                               State.COMPENSATE, State.LOCK, State.DONE)
_ROBOT_FRESH_S = 1.0


@dataclass(frozen=True)
class MarkerRow:
    """One marker: ``kind`` skin (CT fiducial order) or flange (layout order); position in the
    optical frame (mm, None: not seen); residual to the registered set moved by the live rigid
    change (mm, None before registration or when not seen); a skin marker's deviation from its
    reference position, what the gate judges (mm, None before registration or when not seen)."""

    kind: str
    index: int
    position_mm: tuple[float, float, float] | None
    residual_mm: float | None
    deviation_mm: float | None = None

    @property
    def visible(self) -> bool:
        return self.position_mm is not None


@dataclass(frozen=True)
class ConsoleView:
    """A snapshot of the controller for the UI (units in the field names)."""

    t_s: float
    state: str
    pending: str | None
    pending_reason: str
    last_reason: str
    hint: str
    markers: tuple[MarkerRow, ...]
    gate_deviation_mm: float | None
    gate_tolerance_mm: float
    gate_dwell_s: float
    gate_open: bool
    breathing_mm: tuple[float, ...]
    robot_connected: bool
    robot_mode: str
    robot_safety: str
    robot_speed_mm_s: float | None
    robot_tcp_mm: tuple[float, float, float] | None
    guide_error_mm: float | None
    fre_mm: float | None
    tre_expected_mm: float | None
    robot_fre_mm: float | None
    comp_error_mm: float | None
    faults: tuple[str, ...]
    timeline: tuple[tuple[float, str, str], ...]
    plan_source: str
    plan_fiducials: int
    plan_entry_mm: tuple[float, float, float]
    plan_target_mm: tuple[float, float, float]
    frames: int
    commands_sent: int
    commands_refused: int
    operator_commands_decided: int
    session_log: str
    igtl: str
    ended: bool = False
    #: the body's state against the registered one: the shape residual, the farthest marker's
    #: deviation (mm), and the deformation monitor (the change estimator and the skin markers'
    #: rigid-fit residual, mm); None before registration / a measured change
    gate_shape_mm: float | None = None
    gate_worst_marker_mm: float | None = None
    change_estimator: str | None = None
    change_fre_mm: float | None = None
    #: the surrogate target model's last pair (snapshot ``target_*``): shift mm, turn deg, why it
    #: kept the rigid direction, which bound held it; None without the model
    target_shift_mm: float | None = None
    target_turn_deg: float | None = None
    target_fallback: str | None = None
    target_limited: str | None = None
    #: with a target sensor: what the path pointed at, and why the sensor gave no target (snapshot)
    target_source: str | None = None
    target_sensor_why_not: str | None = None
    #: the breathing state at registration (snapshot ``breathing_*``): how far it moved the plan's
    #: entry and target (mm), or why Horn's fit was kept; None without a 4D CT's breathing model
    breathing_entry_shift_mm: float | None = None
    breathing_target_shift_mm: float | None = None
    breathing_kept_rigid_because: str | None = None
    error: str = ""
    #: markers located in the latest pair: (left image, right image, triangulated); None before
    #: a pair, or a camera's count None when the locator does not say
    located_counts: tuple[int | None, int | None, int] | None = None


def hint_for(state: State, pending: str | None, gate_tol_mm: float, gate_dwell_s: float) -> str:
    """What the next step needs, in plain words (with the key that does it)."""
    if pending is not None:
        return f"waiting for your confirmation of {pending}: {CONFIRM_KEYS_TEXT}"
    return {
        State.IDLE: "press s to start: registration needs a still breath-hold with the markers visible",
        State.REGISTER: "registering: keep the patient still (breath-hold requested), markers visible",
        State.PLAN: "planning the guide pose on the path (reachability, limits)",
        State.APPROACH: "robot moving to the stand-off pose; p pause, a abort",
        State.GATE: f"ask the patient to hold breath: the gate opens under {gate_tol_mm} mm "
                    f"for {gate_dwell_s} s",
        State.COMPENSATE: "following the patient to the corrected entry; p pause, a abort",
        State.LOCK: "locked at the entry: insert the needle; t retract, a abort",
        State.PAUSED: "paused: r resume (re-approach from the actual pose), s re-register, "
                      "t retract, a abort",
        State.RETRACT: "backing off along the guide axis",
        State.FAULT: "fault: r recover (re-approach from the actual pose once the cause is gone), x reset",
        State.SAFE_STOP: "stopped: r resume, s re-register, t retract, x reset",
        State.DONE: "procedure complete: x reset for another, q quit",
    }[state]


def _tuple3(p: Sequence[float] | np.ndarray) -> tuple[float, float, float]:
    return float(p[0]), float(p[1]), float(p[2])


@dataclass(frozen=True)
class ViewSetup:
    """What the view needs beyond a snapshot, fixed for the session: the plan, the gate's
    settings and the flange layout's size."""

    plan: ProcedurePlan
    gate_tolerance_mm: float
    gate_dwell_s: float
    flange_markers: int


def _markers(snap: ControllerSnapshot, vs: ViewSetup) -> tuple[MarkerRow, ...]:
    rows: list[MarkerRow] = []
    live = snap.live_mm
    n_skin = vs.plan.fiducials_mm.shape[0]
    ref, T_change = snap.reference_optical_mm, snap.T_change_meas
    moved = None
    ref_ok = None
    if ref is not None and T_change is not None:
        moved = T_change.apply(np.nan_to_num(ref))
        ref_ok = np.all(np.isfinite(ref), axis=1)
    dev = snap.marker_deviations_mm
    for i in range(n_skin):
        pos = None
        res = None
        deviation = None
        if live is not None and i < live.shape[0] and bool(np.all(np.isfinite(live[i]))):
            pos = _tuple3(live[i])
            if moved is not None and ref_ok is not None and bool(ref_ok[i]):
                res = float(np.linalg.norm(moved[i] - live[i]))
            if dev is not None and i < dev.shape[0] and bool(np.isfinite(dev[i])):
                deviation = float(dev[i])
        rows.append(MarkerRow("skin", i, pos, res, deviation))
    fl = snap.flange_mm
    for i in range(vs.flange_markers):
        pos = None
        if fl is not None and i < fl.shape[0] and bool(np.all(np.isfinite(fl[i]))):
            pos = _tuple3(fl[i])
        rows.append(MarkerRow("flange", i, pos, None))
    return tuple(rows)


def _worst(deviations_mm: np.ndarray | None) -> float | None:
    """The largest finite per-marker deviation (mm), or None."""
    if deviations_mm is None:
        return None
    finite = deviations_mm[np.isfinite(deviations_mm)]
    return float(finite.max()) if finite.size else None


def build_view(snap: ControllerSnapshot, vs: ViewSetup, *, breathing_mm: Sequence[float],
               session_log: str, igtl: str, ended: bool = False, error: str = "") -> ConsoleView:
    """The console's view of one controller snapshot (pure; any thread)."""
    state = State(snap.state)
    st = snap.robot
    connected = st is not None and (snap.t_ns - st.t_ns) * 1e-9 <= _ROBOT_FRESH_S and not (
        state is State.FAULT and "disconnect" in snap.last_reason.lower())
    plan = vs.plan
    timeline = tuple((r.t_s, r.state, r.reason) for r in snap.timeline[-12:])
    return ConsoleView(
        t_s=snap.t_s, state=snap.state, pending=snap.pending, pending_reason=snap.pending_reason,
        last_reason=snap.last_reason,
        hint=hint_for(state, snap.pending, vs.gate_tolerance_mm, vs.gate_dwell_s),
        markers=_markers(snap, vs),
        gate_deviation_mm=snap.gate_deviation_mm, gate_tolerance_mm=vs.gate_tolerance_mm,
        gate_dwell_s=vs.gate_dwell_s,
        gate_open=state in (State.COMPENSATE, State.LOCK),
        breathing_mm=tuple(breathing_mm),
        robot_connected=connected,
        robot_mode="unknown" if st is None else st.mode.value,
        robot_safety="unknown" if st is None else st.safety.value,
        robot_speed_mm_s=None if st is None else float(st.tcp_speed_mm_s),
        robot_tcp_mm=None if st is None else _tuple3(st.T_robot_from_tcp.t),
        guide_error_mm=snap.guide_error_mm,
        fre_mm=snap.fre_mm, tre_expected_mm=snap.tre_expected_mm, robot_fre_mm=snap.robot_fre_mm,
        comp_error_mm=snap.truth_error_mm,
        faults=snap.faults[-8:],
        timeline=timeline,
        plan_source=plan.source, plan_fiducials=int(plan.fiducials_mm.shape[0]),
        plan_entry_mm=_tuple3(np.asarray(plan.entry_mm).reshape(3)),
        plan_target_mm=_tuple3(np.asarray(plan.target_mm).reshape(3)),
        frames=snap.frames, commands_sent=snap.commands_sent,
        commands_refused=snap.commands_refused,
        operator_commands_decided=snap.operator_commands_decided,
        session_log=session_log, igtl=igtl, ended=ended, error=error,
        gate_shape_mm=snap.gate_shape_mm, gate_worst_marker_mm=_worst(snap.marker_deviations_mm),
        change_estimator=snap.change_estimator, change_fre_mm=snap.change_fre_mm,
        target_shift_mm=snap.target_shift_mm, target_turn_deg=snap.target_turn_deg,
        target_fallback=snap.target_fallback, target_limited=snap.target_limited,
        target_source=snap.target_source, target_sensor_why_not=snap.target_sensor_why_not,
        breathing_entry_shift_mm=snap.breathing_entry_shift_mm,
        breathing_target_shift_mm=snap.breathing_target_shift_mm,
        breathing_kept_rigid_because=snap.breathing_kept_rigid_because,
        located_counts=None if snap.located is None else snap.located.counts,
    )
