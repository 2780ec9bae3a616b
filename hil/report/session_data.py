"""Read a session log into the time series and figures a report shows.

The reader is tolerant of *missing* data (a session that never registered has no FRE; a lab
session has no ground truth) and strict about *wrong* data: a line that is not a JSON object,
a record without an integer ``t_ns`` or a string ``event``, or a known numeric field holding
something that is not a number raises :class:`~hil.errors.InputFileError` naming the file and the
line. Unknown events and fields are ignored (the log grows; old reports keep working).

Time axis: seconds since the first record's ``t_ns`` (the controller's monotonic clock).

Events read (names as the controller writes them, :mod:`hil.controller.events`):
``state_entered`` (state), ``fault_detected`` (reason), ``registration_done`` (fre_mm,
tre_expected_mm, robot_fre_mm, markers, reference_optical_mm, optional residuals_mm),
``gate_measured`` (deviation_rms_mm, open, shape_mm, marker_deviations_mm), ``compensation_step``
and ``lock_measured`` (guide_error_mm, gate_deviation_mm; change_fre_mm; lock: shape_mm,
marker_deviations_mm; compensation_step with the surrogate target model: target_turn_deg,
target_shift_mm, target_fallback), ``approach_measured`` (guide_error_mm), ``truth_error``
(state, position_mm, direction_deg; simulator only), ``command_sent`` (speed_mm_s),
``session_started`` (header; gate and lock tolerances from ``procedure.gate.tolerance_mm`` /
``procedure.lock.tolerance_mm`` as ``hil run`` writes them, or top-level ``gate_tolerance_mm`` /
``lock_tolerance_mm``), and — when the
controller logs them — any record with ``tcp_speed_mm_s`` (measured robot speed) and any record
with ``marker_residuals_mm`` or ``live_mm`` (per-marker residuals over time).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hil.errors import GeometryError, InputFileError
from hil.geometry.registration import register_horn
from hil.session.log import read_session_log

FloatArray = NDArray[np.float64]

#: States whose time is counted "gate open" on the breathing plot (the gate was passed).
_GATE_PASSED_STATES = frozenset({"compensate", "lock"})


@dataclass
class Series:
    """A time series: ``t_s`` (seconds since the session start) and ``y`` values."""

    t_s: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)

    def add(self, t_s: float, y: float | None) -> None:
        if y is not None and math.isfinite(y):
            self.t_s.append(t_s)
            self.y.append(y)

    def __len__(self) -> int:
        return len(self.y)

    def arrays(self) -> tuple[FloatArray, FloatArray]:
        return np.asarray(self.t_s, dtype=np.float64), np.asarray(self.y, dtype=np.float64)


@dataclass
class SessionData:
    """Everything a report plots and tabulates, extracted from one session log."""

    path: Path
    records: int = 0
    header: dict[str, Any] = field(default_factory=dict)
    closed: bool = False
    duration_s: float = 0.0
    #: (t_s, state) at every ``state_entered``; the session starts in ``idle`` at 0.
    state_entries: list[tuple[float, str]] = field(default_factory=list)
    #: (t_s, reason) of every ``fault_detected``.
    faults: list[tuple[float, str]] = field(default_factory=list)
    #: (t_s, transition name, source, target) of every applied transition.
    transitions: list[tuple[float, str, str, str]] = field(default_factory=list)
    breathing_mm: Series = field(default_factory=Series)
    #: (t_s, open) of every gate sample (``gate_measured``).
    gate_samples: list[tuple[float, bool]] = field(default_factory=list)
    gate_tolerance_mm: float | None = None
    guide_error_mm: Series = field(default_factory=Series)
    comp_error_mm: Series = field(default_factory=Series)
    lock_truth_mm: Series = field(default_factory=Series)
    lock_truth_deg: Series = field(default_factory=Series)
    #: the guide axis line's distance to the true target while locked, and the true skin's
    #: rigid-fit residual (simulation: ``truth_error``); the measured change's FRE
    #: (``compensation_step``)
    lock_target_mm: Series = field(default_factory=Series)
    body_residual_mm: Series = field(default_factory=Series)
    change_fre_mm: Series = field(default_factory=Series)
    lock_guide_error_mm: Series = field(default_factory=Series)
    #: the body's state against the registered one (``gate_measured``, ``lock_measured``): the
    #: shape residual after removing a rigid motion, and each marker's distance from its
    #: reference position (mm)
    shape_mm: Series = field(default_factory=Series)
    marker_deviations_mm: dict[int, Series] = field(default_factory=dict)
    marker_residuals_mm: dict[int, Series] = field(default_factory=dict)
    registration_residuals_mm: list[float] = field(default_factory=list)
    #: the surrogate target model per pair (``compensation_step``, issue 41): the turn it added
    #: (deg), the modelled target's shift (mm), and (t_s, reason) of each pair it fell back on
    target_turn_deg: Series = field(default_factory=Series)
    target_shift_mm: Series = field(default_factory=Series)
    target_fallbacks: list[tuple[float, str]] = field(default_factory=list)
    #: the pairs the model steered with its score or turn held at a bound (time s, which)
    target_held: list[tuple[float, str]] = field(default_factory=list)
    #: with a target sensor: how many pairs pointed the path at its target (None: the session ran
    #: without one, or its log is older than ``target_source``)
    target_sensor_pairs: int | None = None
    robot_speed_mm_s: Series = field(default_factory=Series)
    robot_speed_kind: str = ""  # "measured", "commanded" or "" (none)
    fre_mm: float | None = None
    tre_expected_mm: float | None = None
    robot_fre_mm: float | None = None
    registered_markers: int | None = None
    lock_tolerance_mm: float | None = None

    # ---------------------------------------------------------------- derived figures
    def state_intervals(self) -> list[tuple[str, float, float]]:
        """(state, start_s, end_s) covering [0, duration]."""
        entries = [(0.0, "idle"), *self.state_entries]
        out: list[tuple[str, float, float]] = []
        for i, (t, s) in enumerate(entries):
            end = entries[i + 1][0] if i + 1 < len(entries) else self.duration_s
            if end > t or i + 1 == len(entries):
                out.append((s, t, max(end, t)))
        return out

    def time_in_state_s(self) -> dict[str, float]:
        """Total seconds spent in each state visited, in order of first visit."""
        acc: dict[str, float] = {}
        for s, a, b in self.state_intervals():
            acc[s] = acc.get(s, 0.0) + (b - a)
        return acc

    def final_state(self) -> str:
        return self.state_entries[-1][1] if self.state_entries else "idle"

    def gate_open_intervals(self) -> list[tuple[float, float]]:
        """Intervals where the gate was open: runs of open ``gate_measured`` samples, and the
        time spent in the states entered through the open gate (compensate, lock)."""
        spans: list[tuple[float, float]] = []
        start: float | None = None
        last_t = 0.0
        for t, is_open in self.gate_samples:
            if is_open and start is None:
                start = t
            elif not is_open and start is not None:
                spans.append((start, t))
                start = None
            last_t = t
        if start is not None:
            spans.append((start, last_t))
        spans += [(a, b) for s, a, b in self.state_intervals() if s in _GATE_PASSED_STATES]
        return _merge(spans)

    def gate_closed_intervals(self) -> list[tuple[float, float]]:
        """Time in the GATE state while the gate was closed."""
        gate_spans = [(a, b) for s, a, b in self.state_intervals() if s == "gate"]
        opened = self.gate_open_intervals()
        return _subtract(gate_spans, opened)

    def lock_error_mm(self) -> float | None:
        """Optical guide error at the first lock measurement (the error at which it locked)."""
        return self.lock_guide_error_mm.y[0] if len(self.lock_guide_error_mm) else None

    def time_to_lock_s(self) -> float | None:
        for t, s in self.state_entries:
            if s == "lock":
                return t
        return None

    def target_model_fallback_fraction(self) -> float | None:
        """Of the pairs the surrogate target model judged, the share it fell back on (None: the
        session ran without the model)."""
        if not len(self.target_turn_deg):
            return None
        return len(self.target_fallbacks) / len(self.target_turn_deg)

    def target_sensor_fraction(self) -> float | None:
        """Of the pairs the surrogate target model judged, the share whose path pointed at the
        target sensor's target (None: the session ran without a target sensor)."""
        if not len(self.target_turn_deg) or self.target_sensor_pairs is None:
            return None
        return self.target_sensor_pairs / len(self.target_turn_deg)

    def target_model_held_fraction(self) -> float | None:
        """Of the pairs the surrogate target model judged, the share it steered with its score or
        turn held at a bound (None: the session ran without the model)."""
        if not len(self.target_turn_deg):
            return None
        return len(self.target_held) / len(self.target_turn_deg)

    def gate_open_fraction(self) -> float | None:
        if not self.gate_samples:
            return None
        return sum(1 for _, o in self.gate_samples if o) / len(self.gate_samples)


def _merge(spans: Iterable[tuple[float, float]]) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    for a, b in sorted(spans):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


Span = tuple[float, float]


def _subtract(spans: list[Span], holes: list[Span]) -> list[Span]:
    out: list[tuple[float, float]] = []
    for a, b in spans:
        cur = a
        for ha, hb in holes:
            if hb <= cur or ha >= b:
                continue
            if ha > cur:
                out.append((cur, ha))
            cur = max(cur, hb)
        if cur < b:
            out.append((cur, b))
    return out


# -------------------------------------------------------------------- field readers
class _Line:
    """Typed access to one record's fields; a wrong type names the file, line and field."""

    def __init__(self, path: Path, n: int, rec: Mapping[str, Any]) -> None:
        self.path, self.n, self.rec = path, n, rec

    def bad(self, key: str, what: str) -> InputFileError:
        return InputFileError(str(self.path), f"line {self.n}: field {key!r} of "
                                              f"{self.rec.get('event')!r} {what}")

    def num(self, key: str) -> float | None:
        v = self.rec.get(key)
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise self.bad(key, f"is not a number ({type(v).__name__})")
        return float(v)

    def text(self, key: str) -> str | None:
        v = self.rec.get(key)
        if v is None:
            return None
        if not isinstance(v, str):
            raise self.bad(key, f"is not a string ({type(v).__name__})")
        return v

    def flag(self, key: str) -> bool | None:
        v = self.rec.get(key)
        if v is None:
            return None
        if not isinstance(v, bool):
            raise self.bad(key, f"is not true/false ({type(v).__name__})")
        return v

    def numbers(self, key: str) -> list[float | None] | None:
        v = self.rec.get(key)
        if v is None:
            return None
        if not isinstance(v, list):
            raise self.bad(key, "is not a list")
        out: list[float | None] = []
        for x in v:
            if x is None:
                out.append(None)
            elif isinstance(x, bool) or not isinstance(x, int | float):
                raise self.bad(key, "holds a value that is not a number")
            else:
                out.append(float(x))
        return out

    def points(self, key: str) -> FloatArray | None:
        """An (N, 3) list of points; null rows or null coordinates become NaN rows."""
        v = self.rec.get(key)
        if v is None:
            return None
        if not isinstance(v, list):
            raise self.bad(key, "is not a list of points")
        out = np.full((len(v), 3), np.nan)
        for i, row in enumerate(v):
            if row is None:
                continue
            if not (isinstance(row, list) and len(row) == 3):
                raise self.bad(key, f"row {i} is not a 3-vector")
            if any(x is not None and (isinstance(x, bool) or not isinstance(x, int | float)) for x in row):
                raise self.bad(key, f"row {i} holds a value that is not a number")
            if all(x is not None for x in row):
                out[i] = [float(x) for x in row]
        return out


def _residuals_to_reference(reference_mm: FloatArray, live_mm: FloatArray) -> list[float | None] | None:
    """Per-marker distance between the live markers and the reference set moved by the best
    rigid fit reference -> live (Horn, seed 000 eqs 17-21); None rows for missing markers."""
    if reference_mm.shape != live_mm.shape:
        return None
    ok = np.all(np.isfinite(reference_mm), axis=1) & np.all(np.isfinite(live_mm), axis=1)
    if int(ok.sum()) < 3:
        return None
    try:
        reg = register_horn(live_mm[ok], reference_mm[ok])
    except GeometryError:
        return None
    moved = reg.T_fixed_from_moving.apply(reference_mm[ok])
    d = np.linalg.norm(moved - live_mm[ok], axis=1)
    out: list[float | None] = [None] * reference_mm.shape[0]
    for k, i in enumerate(np.flatnonzero(ok)):
        out[int(i)] = float(d[k])
    return out


Progress = Callable[[str], None]


def _time_and_event(p: Path, n: int, rec: Mapping[str, Any]) -> tuple[int, str]:
    """A record's ``t_ns`` (integer ns) and ``event`` name.

    Raises:
        InputFileError: either is missing or of the wrong type (names the file and 1-based line ``n``).
    """
    t_ns = rec.get("t_ns")
    event = rec.get("event")
    if isinstance(t_ns, bool) or not isinstance(t_ns, int):
        raise InputFileError(str(p), f"line {n}: record has no integer 't_ns'")
    if not isinstance(event, str) or not event:
        raise InputFileError(str(p), f"line {n}: record has no 'event' name")
    return t_ns, event


def _read_header(data: SessionData, ln: _Line) -> None:
    """``session_started``: the header and the gate / lock tolerances (mm), from the record or,
    for ``hil run``'s header, from its resolved procedure config."""
    rec, p, n = ln.rec, ln.path, ln.n
    data.header = dict(rec)
    data.gate_tolerance_mm = ln.num("gate_tolerance_mm")
    data.lock_tolerance_mm = ln.num("lock_tolerance_mm")
    proc = rec.get("procedure")
    if isinstance(proc, dict):  # hil run's header: the resolved procedure config
        gate, lock = proc.get("gate"), proc.get("lock")
        if data.gate_tolerance_mm is None and isinstance(gate, dict):
            data.gate_tolerance_mm = _Line(p, n, {"event": "session_started.procedure.gate",
                                                  **gate}).num("tolerance_mm")
        if data.lock_tolerance_mm is None and isinstance(lock, dict):
            data.lock_tolerance_mm = _Line(p, n, {"event": "session_started.procedure.lock",
                                                  **lock}).num("tolerance_mm")


def _read_state_entered(data: SessionData, ln: _Line, t: float) -> str:
    """``state_entered`` at ``t`` (s from the first record): record it and return the new state.

    Raises:
        InputFileError: the record has no ``state``.
    """
    s = ln.text("state")
    if s is None:
        raise ln.bad("state", "is missing")
    data.state_entries.append((t, s))
    return s


def _read_registration(data: SessionData, ln: _Line) -> FloatArray | None:
    """``registration_done``: FRE / expected TRE (mm), marker count and residuals; returns the
    reference marker positions (optical frame, mm) the live residuals are measured against."""
    data.fre_mm = ln.num("fre_mm")
    data.tre_expected_mm = ln.num("tre_expected_mm")
    data.robot_fre_mm = ln.num("robot_fre_mm")
    m = ln.num("markers")
    data.registered_markers = None if m is None else int(m)
    reference = ln.points("reference_optical_mm")
    res = ln.numbers("residuals_mm")
    if res is not None:
        data.registration_residuals_mm = [math.nan if r is None else r for r in res]
    return reference


def _read_procedure_event(data: SessionData, ln: _Line, event: str, t: float, state: str) -> None:
    """Transitions, faults and the per-state measurements (mm, deg) at ``t`` (s); ``state`` is the
    state last entered (for truth errors that do not name theirs). Other events are ignored."""
    if event == "transition_applied":
        data.transitions.append((t, ln.text("transition") or "", ln.text("source") or "",
                                 ln.text("target") or ""))
    elif event == "fault_detected":
        data.faults.append((t, ln.text("reason") or "(no reason given)"))
    elif event == "gate_measured":
        data.breathing_mm.add(t, ln.num("deviation_rms_mm"))
        o = ln.flag("open")
        if o is not None:
            data.gate_samples.append((t, o))
        _read_body_state(data, ln, t)
    elif event in ("compensation_step", "lock_measured"):
        data.guide_error_mm.add(t, ln.num("guide_error_mm"))
        data.breathing_mm.add(t, ln.num("gate_deviation_mm"))
        data.change_fre_mm.add(t, ln.num("change_fre_mm"))
        _read_target_model(data, ln, t)
        if event == "lock_measured":
            data.lock_guide_error_mm.add(t, ln.num("guide_error_mm"))
            _read_body_state(data, ln, t)
    elif event == "approach_measured":
        data.guide_error_mm.add(t, ln.num("guide_error_mm"))
    elif event == "truth_error":
        st = ln.text("state") or state
        data.body_residual_mm.add(t, ln.num("body_rigid_residual_mm"))
        if st == "lock":
            data.lock_target_mm.add(t, ln.num("target_mm"))
        if st == "compensate":
            data.comp_error_mm.add(t, ln.num("position_mm"))
        elif st == "lock":
            data.lock_truth_mm.add(t, ln.num("position_mm"))
            data.lock_truth_deg.add(t, ln.num("direction_deg"))


def _read_target_model(data: SessionData, ln: _Line, t: float) -> None:
    """The surrogate target model's fields of a ``compensation_step`` (absent without the model:
    nothing is added). A pair counts when it logged its turn; a non-empty ``target_fallback`` is
    a pair that kept the rigid direction, with the reason; a non-empty ``target_limited`` (absent
    in older logs) a pair steered with its score or turn held at a bound."""
    turn = ln.num("target_turn_deg")
    if turn is None:
        return
    data.target_turn_deg.add(t, turn)
    data.target_shift_mm.add(t, ln.num("target_shift_mm"))
    why = ln.text("target_fallback")
    if why:
        data.target_fallbacks.append((t, why))
    held = ln.text("target_limited")
    if held:
        data.target_held.append((t, held))
    if ln.text("target_sensor_why_not") is not None:   # logged only with a target sensor
        data.target_sensor_pairs = (data.target_sensor_pairs or 0) + int(ln.text("target_source") == "sensor")


def _read_body_state(data: SessionData, ln: _Line, t: float) -> None:
    """The shape residual and the per-marker deviations (mm) of a ``gate_measured`` or
    ``lock_measured`` record (absent in logs older than the fields: nothing is added)."""
    data.shape_mm.add(t, ln.num("shape_mm"))
    for i, d in enumerate(ln.numbers("marker_deviations_mm") or []):
        data.marker_deviations_mm.setdefault(i, Series()).add(t, d)


def _read_marker_residuals(data: SessionData, ln: _Line, t: float, reference: FloatArray | None) -> None:
    """Per-marker residuals (mm) of any record: ``marker_residuals_mm`` as logged, or computed from
    ``live_mm`` against the registration's ``reference`` (optical frame, mm)."""
    residuals = ln.numbers("marker_residuals_mm")
    if residuals is None and "live_mm" in ln.rec and reference is not None:
        live = ln.points("live_mm")
        residuals = None if live is None else _residuals_to_reference(reference, live)
    if residuals is not None:
        for i, r in enumerate(residuals):
            data.marker_residuals_mm.setdefault(i, Series()).add(t, r)


def load_session(path: str | Path, progress: Progress | None = None) -> SessionData:
    """Read a session log into :class:`SessionData`.

    Raises:
        InputFileError: the file cannot be read, is empty, or a line is not a well-formed
            record (message names the file and the 1-based line).
    """
    p = Path(path)
    data = SessionData(path=p)
    t0: int | None = None
    t_last = 0.0
    reference: FloatArray | None = None
    state = "idle"
    last_event = ""
    commanded = Series()
    for n, rec in enumerate(read_session_log(p), 1):
        t_ns, event = _time_and_event(p, n, rec)
        if t0 is None:
            t0 = t_ns
        t = (t_ns - t0) * 1e-9
        t_last = max(t_last, t)
        data.records = n
        last_event = event
        if progress is not None and n % 5000 == 0:
            progress(f"read {n} records")
        ln = _Line(p, n, rec)
        if event == "session_started":
            _read_header(data, ln)
        elif event == "state_entered":
            state = _read_state_entered(data, ln, t)
        elif event == "registration_done":
            reference = _read_registration(data, ln)
        elif event == "command_sent":
            commanded.add(t, ln.num("speed_mm_s"))
        else:
            _read_procedure_event(data, ln, event, t, state)
        if "tcp_speed_mm_s" in rec:
            data.robot_speed_mm_s.add(t, ln.num("tcp_speed_mm_s"))
        _read_marker_residuals(data, ln, t, reference)
    if t0 is None:
        raise InputFileError(str(p), "empty session log (no records)")
    data.duration_s = t_last
    data.closed = last_event == "session_closed"
    if len(data.robot_speed_mm_s):
        data.robot_speed_kind = "measured"
    elif len(commanded):
        data.robot_speed_mm_s, data.robot_speed_kind = commanded, "commanded"
    return data
