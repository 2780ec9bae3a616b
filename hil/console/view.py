"""What the console shows, as plain data: built in the controller thread after a tick (bounded
work: a few small array operations), read by the UI thread. Immutable once built.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hil.controller.fsm import State
from hil.controller.gate import rms_deviation_mm

if TYPE_CHECKING:
    from hil.controller.controller import Controller

#: States shown on the workflow line, in procedure order.
WORKFLOW: tuple[State, ...] = (State.IDLE, State.REGISTER, State.PLAN, State.APPROACH, State.GATE,
                               State.COMPENSATE, State.LOCK, State.DONE)
_ROBOT_FRESH_S = 1.0


@dataclass(frozen=True)
class MarkerRow:
    """One marker: ``kind`` skin (CT fiducial order) or flange (layout order); position in the
    optical frame (mm, None: not seen); residual to the registered set moved by the live rigid
    change (mm, None before registration or when not seen)."""

    kind: str
    index: int
    position_mm: tuple[float, float, float] | None
    residual_mm: float | None

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
    error: str = ""


def hint_for(state: State, pending: str | None, gate_tol_mm: float, gate_dwell_s: float) -> str:
    """What the next step needs, in plain words (with the key that does it)."""
    if pending is not None:
        return f"waiting for your confirmation of {pending}: press c (confirm) or a (abort)"
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


def _markers(ctl: Controller) -> tuple[MarkerRow, ...]:
    rows: list[MarkerRow] = []
    live = ctl.live_mm
    n_skin = ctl.plan.fiducials_mm.shape[0]
    preg, T_change = ctl.patient_reg, ctl.T_change_meas
    moved = None
    ref_ok = None
    if preg is not None and T_change is not None:
        moved = T_change.apply(np.nan_to_num(preg.reference_optical_mm))
        ref_ok = np.all(np.isfinite(preg.reference_optical_mm), axis=1)
    for i in range(n_skin):
        pos = None
        res = None
        if live is not None and i < live.shape[0] and bool(np.all(np.isfinite(live[i]))):
            pos = _tuple3(live[i])
            if moved is not None and ref_ok is not None and bool(ref_ok[i]):
                res = float(np.linalg.norm(moved[i] - live[i]))
        rows.append(MarkerRow("skin", i, pos, res))
    fl = ctl.flange_mm
    for i in range(ctl.rig.flange_markers_mm.shape[0]):
        pos = None
        if fl is not None and i < fl.shape[0] and bool(np.all(np.isfinite(fl[i]))):
            pos = _tuple3(fl[i])
        rows.append(MarkerRow("flange", i, pos, None))
    return tuple(rows)


def _finite(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


def build_view(ctl: Controller, *, breathing_mm: Sequence[float], comp_error_mm: float | None,
               session_log: str, igtl: str, ended: bool = False, error: str = "") -> ConsoleView:
    """Snapshot the controller (call in the controller thread, between ticks)."""
    cfg = ctl.cfg
    v = ctl.view()
    dev: float | None = None
    if ctl.patient_reg is not None and ctl.live_mm is not None:
        dev = _finite(rms_deviation_mm(ctl.patient_reg.reference_optical_mm, ctl.live_mm)[0])
    st = ctl.last_state
    now_ns = ctl.clock.now_ns()
    connected = st is not None and (now_ns - st.t_ns) * 1e-9 <= _ROBOT_FRESH_S and not (
        v.state is State.FAULT and "disconnect" in v.last_reason.lower())
    guide_err: float | None = None
    if v.state in (State.APPROACH, State.GATE, State.COMPENSATE, State.LOCK):
        try:
            guide_err = _finite(ctl.guide_error_optical_mm())
        except Exception:  # noqa: BLE001 - a display probe must never stop the loop
            guide_err = None
    plan = ctl.plan
    timeline = tuple((float(r["t_s"]), str(r["state"]), str(r.get("reason") or ""))
                     for r in ctl.timeline[-12:])
    return ConsoleView(
        t_s=v.t_s, state=v.state.value, pending=v.pending,
        pending_reason="" if ctl.fsm.pending is None else ctl.fsm.pending.reason, last_reason=v.last_reason,
        hint=hint_for(v.state, v.pending, cfg.gate.tolerance_mm, cfg.gate.dwell_s),
        markers=_markers(ctl),
        gate_deviation_mm=dev, gate_tolerance_mm=cfg.gate.tolerance_mm, gate_dwell_s=cfg.gate.dwell_s,
        gate_open=v.state in (State.COMPENSATE, State.LOCK),
        breathing_mm=tuple(breathing_mm),
        robot_connected=connected,
        robot_mode="unknown" if st is None else st.mode.value,
        robot_safety="unknown" if st is None else st.safety.value,
        robot_speed_mm_s=None if st is None else float(st.tcp_speed_mm_s),
        robot_tcp_mm=None if st is None else _tuple3(st.T_robot_from_tcp.t),
        guide_error_mm=guide_err,
        fre_mm=None if ctl.patient_reg is None else ctl.patient_reg.fre_rms_mm,
        tre_expected_mm=None if ctl.patient_reg is None else ctl.patient_reg.tre_expected_mm,
        robot_fre_mm=None if ctl.robot_reg is None else ctl.robot_reg.fre_rms_mm,
        comp_error_mm=comp_error_mm,
        faults=tuple(ctl.faults[-8:]),
        timeline=timeline,
        plan_source=plan.source, plan_fiducials=int(plan.fiducials_mm.shape[0]),
        plan_entry_mm=_tuple3(np.asarray(plan.entry_mm).reshape(3)),
        plan_target_mm=_tuple3(np.asarray(plan.target_mm).reshape(3)),
        frames=ctl.frames, commands_sent=ctl.safety.commands_sent,
        commands_refused=ctl.safety.commands_refused,
        operator_commands_decided=ctl.operator_commands_decided,
        session_log=session_log, igtl=igtl, ended=ended, error=error,
    )
