"""What a replay shows, read from session records: a list of :class:`SceneItem` (pure data, no
Rerun), one per entity per record, in log order.

Frames: ``world`` is the optical (camera) frame, millimetres. Robot-frame entities live under
``world/robot``, whose transform ``T_optical_from_robot`` is the inverse of the session's last
robot registration (``registration_done.T_robot_from_optical``), logged static: the camera and the
robot's base do not move during a session. Before that registration the controller did not know
it either; a session without one shows the robot frame at the optical origin.

Entities (the session log's fields, docs/run.md; absent fields are skipped):

- ``world/skin/seen``: ``frame_measured.live_mm`` (skin markers as located; unseen rows dropped);
  ``world/skin/registered``: ``registration_done.reference_optical_mm``;
- ``world/flange/seen``: ``frame_measured.flange_mm``;
- ``world/robot/tcp``: ``frame_measured.robot_tcp_mm``; ``world/robot/guide``: the guide axis
  (z of ``frame_measured.T_robot_from_guide``, an arrow of :data:`GUIDE_ARROW_MM`);
- ``world/robot/plan/{entry,target,path}``: ``plan_accepted`` entry, target and the line between;
- ``world/robot/commanded``: TCP positions commanded (``command_sent``: a move's ``target`` pose or
  a tracking command's ``target_mm``);
- ``world/truth/skin``, ``world/truth/entry``, ``world/truth/target``, ``world/truth/path``
  (simulation only): where the simulator's truth put the skin markers, the entry and the target
  (``truth_positions``, optical frame, one per stereo pair; the line from entry to target);
- ``events/transitions`` (every ``transition_applied``: ``source -> target (transition: reason)``),
  ``events/faults`` (``fault_detected``), ``events/operator`` (``operator_command_result``);
- the scalar series of :data:`SCALAR_SERIES` under ``series/``.

The simulator's ground truth enters the log as positions (``truth_positions``, above) and as
errors (``truth_error``: position and direction of the guide against the true moving path, two
series).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]

#: The truth meter's positions record (``hil.controller.metrics.TRUTH_POSITIONS``).
TRUTH_POSITIONS_EVENT = "truth_positions"
#: (record field, entity) of the truth's points; the path joins entry and target.
TRUTH_POINTS: tuple[tuple[str, str], ...] = (("markers_optical_mm", "world/truth/skin"),
                                             ("entry_optical_mm", "world/truth/entry"),
                                             ("target_optical_mm", "world/truth/target"))

#: Length of the guide-axis arrow, mm.
GUIDE_ARROW_MM = 40.0

#: (event, field, entity path) of every scalar series; a record's field that is a finite number
#: gives one sample. The same entity may be fed by several events.
SCALAR_SERIES: tuple[tuple[str, str, str], ...] = (
    ("approach_measured", "guide_error_mm", "series/following/guide_error_mm"),
    ("compensation_step", "guide_error_mm", "series/following/guide_error_mm"),
    ("lock_measured", "guide_error_mm", "series/following/guide_error_mm"),
    ("servo_stats", "following_peak_mm", "series/following/servo_peak_mm"),
    ("compensation_step", "latency_detect_ms", "series/latency/detect_ms"),
    ("compensation_step", "latency_command_ms", "series/latency/command_ms"),
    ("gate_measured", "deviation_rms_mm", "series/gate/deviation_rms_mm"),
    ("frame_measured", "gate_deviation_mm", "series/gate/frame_deviation_mm"),
    ("registration_done", "fre_mm", "series/registration/fre_mm"),
    ("registration_done", "robot_fre_mm", "series/registration/robot_fre_mm"),
    ("frame_measured", "camera_discrepancy_mm", "series/camera_discrepancy_mm"),
    ("frame_measured", "tcp_speed_mm_s", "series/robot/tcp_speed_mm_s"),
    ("truth_error", "position_mm", "series/truth/position_error_mm"),
    ("truth_error", "direction_deg", "series/truth/direction_error_deg"),
    ("servo_stats", "longest_interval_ms", "series/servo/longest_interval_ms"),
    ("servo_stats", "late", "series/servo/late"),
    ("servo_stats", "late_wakes", "series/servo/late_wakes"),
    ("servo_stats", "overruns", "series/servo/overruns"),
    ("servo_stats", "stale_periods", "series/servo/stale_periods"),
    ("servo_stats", "following_faults", "series/servo/following_faults"),
)

ItemKind = Literal["points", "arrows", "strips", "scalar", "text"]


@dataclass(frozen=True)
class SceneItem:
    """One entity's value at one record. ``seq``: the record's sequence number; ``t_ns``: ns since
    the first record's ``t_ns`` (the ``session_time`` timeline). ``points``: N x 3 (points; arrow
    origins; a strip's vertices), ``vectors``: N x 3 (arrows); ``value``: the scalar;
    ``text``/``level``: a text annotation."""

    entity: str
    kind: ItemKind
    seq: int
    t_ns: int
    points: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    vectors: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    value: float = math.nan
    text: str = ""
    level: str = "INFO"


@dataclass
class Scene:
    """A session's items plus its static context: ``T_optical_from_robot`` (None without a robot
    registration) and header fields."""

    items: list[SceneItem] = field(default_factory=list)
    T_optical_from_robot: RigidTransform | None = None
    session_id: str | None = None
    records: int = 0
    duration_s: float = 0.0

    def entities(self) -> list[str]:
        """Every entity path an item uses, sorted."""
        return sorted({i.entity for i in self.items})


def _rows(value: Any) -> FloatArray | None:
    """A list of 3-vectors -> the rows that are finite (None: not such a list)."""
    if not isinstance(value, list) or not value:
        return None
    try:
        a = np.asarray([[math.nan if v is None else float(v) for v in row] for row in value],
                       dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if a.ndim != 2 or a.shape[1] != 3:
        return None
    a = a[np.all(np.isfinite(a), axis=1)]
    return a if len(a) else None


def _vec3(value: Any) -> FloatArray | None:
    rows = _rows([value]) if isinstance(value, list) else None
    return None if rows is None else rows[0]


def _transform(value: Any) -> RigidTransform | None:
    """A logged transform (``{"rotvec_rad": [..], "t_mm": [..]}``) or None."""
    if not isinstance(value, Mapping):
        return None
    r, t = _vec3(value.get("rotvec_rad")), _vec3(value.get("t_mm"))
    if r is None or t is None:
        return None
    return RigidTransform.from_rotvec(r, t)


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def _scalar_table() -> dict[str, list[tuple[str, str]]]:
    table: dict[str, list[tuple[str, str]]] = {}
    for event, name, entity in SCALAR_SERIES:
        table.setdefault(event, []).append((name, entity))
    return table


_SCALARS = _scalar_table()


def _record_items(rec: Mapping[str, Any], seq: int, t_ns: int) -> Iterator[SceneItem]:
    """The items of one record (module doc)."""
    event = rec.get("event")
    for name, entity in _SCALARS.get(str(event), ()):
        x = _number(rec.get(name))
        if x is not None:
            yield SceneItem(entity, "scalar", seq, t_ns, value=x)
    if event == "frame_measured":
        for name, entity in (("live_mm", "world/skin/seen"), ("flange_mm", "world/flange/seen")):
            pts = _rows(rec.get(name))
            if pts is not None:
                yield SceneItem(entity, "points", seq, t_ns, points=pts)
        tcp = _vec3(rec.get("robot_tcp_mm"))
        if tcp is not None:
            yield SceneItem("world/robot/tcp", "points", seq, t_ns, points=tcp.reshape(1, 3))
        guide = _transform(rec.get("T_robot_from_guide"))
        if guide is not None:
            yield SceneItem("world/robot/guide", "arrows", seq, t_ns, points=guide.t.reshape(1, 3),
                            vectors=(guide.R[:, 2] * GUIDE_ARROW_MM).reshape(1, 3))
    elif event == "registration_done":
        ref = _rows(rec.get("reference_optical_mm"))
        if ref is not None:
            yield SceneItem("world/skin/registered", "points", seq, t_ns, points=ref)
    elif event == "plan_accepted":
        entry, target = _vec3(rec.get("entry_robot_mm")), _vec3(rec.get("target_robot_mm"))
        if entry is not None and target is not None:
            yield SceneItem("world/robot/plan/entry", "points", seq, t_ns, points=entry.reshape(1, 3))
            yield SceneItem("world/robot/plan/target", "points", seq, t_ns, points=target.reshape(1, 3))
            yield SceneItem("world/robot/plan/path", "strips", seq, t_ns, points=np.vstack([entry, target]))
    elif event == "command_sent":
        tgt = _transform(rec.get("target"))
        cmd = tgt.t if tgt is not None else _vec3(rec.get("target_mm"))
        if cmd is not None:
            yield SceneItem("world/robot/commanded", "points", seq, t_ns, points=cmd.reshape(1, 3))
    elif event == TRUTH_POSITIONS_EVENT:
        yield from truth_items(rec, seq, t_ns)
    elif event == "transition_applied":
        yield SceneItem("events/transitions", "text", seq, t_ns, text=transition_text(rec))
    elif event == "fault_detected":
        yield SceneItem("events/faults", "text", seq, t_ns, level="ERROR",
                        text=str(rec.get("reason", "fault")))
    elif event == "operator_command_result":
        yield SceneItem("events/operator", "text", seq, t_ns,
                        text=f"{rec.get('input')}: {rec.get('outcome')} ({rec.get('reason')})")


def truth_items(rec: Mapping[str, Any], seq: int, t_ns: int) -> Iterator[SceneItem]:
    """The truth's points of one ``truth_positions`` record (or the truth meter's
    ``last_positions``) and the entry-to-target line (the live stream draws them the same way)."""
    found: dict[str, FloatArray] = {}
    for name, entity in TRUTH_POINTS:
        value = rec.get(name)
        value = value.tolist() if isinstance(value, np.ndarray) else value   # live: the meter's arrays
        pts = _rows(value if name == "markers_optical_mm" else [value])
        if pts is not None:
            found[name] = pts
            yield SceneItem(entity, "points", seq, t_ns, points=pts)
    if "entry_optical_mm" in found and "target_optical_mm" in found:
        yield SceneItem("world/truth/path", "strips", seq, t_ns,
                        points=np.vstack([found["entry_optical_mm"], found["target_optical_mm"]]))


def transition_text(rec: Mapping[str, Any]) -> str:
    """The annotation of a ``transition_applied`` record: ``source -> target (name: reason)``."""
    return f"{rec.get('source')} -> {rec.get('target')} ({rec.get('transition')}: {rec.get('reason')})"


def build_scene(records: Iterable[Mapping[str, Any]]) -> Scene:
    """The scene of a session's records (module doc). Records without an integer ``t_ns`` are
    skipped; time is seconds since the first record's ``t_ns``."""
    scene = Scene()
    t0: int | None = None
    for rec in records:
        t_ns = rec.get("t_ns")
        if isinstance(t_ns, bool) or not isinstance(t_ns, int):
            continue
        t0 = t_ns if t0 is None else t0
        seq_raw = rec.get("seq")
        seq = seq_raw if isinstance(seq_raw, int) and not isinstance(seq_raw, bool) else scene.records
        dt_ns = t_ns - t0
        scene.records += 1
        scene.duration_s = max(scene.duration_s, dt_ns / 1e9)
        if rec.get("event") == "session_started" and isinstance(rec.get("session_id"), str):
            scene.session_id = str(rec["session_id"])
        if rec.get("event") == "registration_done":
            T = _transform(rec.get("T_robot_from_optical"))
            if T is not None:
                scene.T_optical_from_robot = T.inverse()
        scene.items.extend(_record_items(rec, seq, dt_ns))
    return scene
