"""Write a session log as one Rerun recording (``.rrd``) on the session's own clock.

Contract of :func:`write_replay`: the log is read and its hash chain verified with the report's
verifier (:func:`hil.session.log.verify_session_log`); a broken or incomplete chain (tampered,
truncated, not closed) or a log of another schema version is refused with :class:`ReplayError`
naming the file and what is wrong, unless ``allow_unverified`` — then the records up to the first
unreadable line are replayed and the recording carries the marker: recording name prefixed
``UNVERIFIED``, a warning in ``events/verification`` and ``session/verification`` saying why.
Timelines: ``session_time`` (seconds since the first record's ``t_ns``, the controller's
monotonic clock) and ``record`` (the record's ``seq``). The file is written next to its final
path and renamed into place: a failed replay leaves no partial file. Blocking; a few seconds for
a default ``hil run`` session (docs/replay.md has the figures).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.errors import HilError
from hil.replay.rerun_env import import_rerun
from hil.replay.scene import Scene, SceneItem, build_scene
from hil.session.log import SCHEMA_VERSION, VerifyReport, verify_session_log

#: Rerun application id of every recording the project writes.
APPLICATION_ID = "needle_guide_hil"
#: Timelines of a replay.
TIMELINE_TIME = "session_time"
TIMELINE_RECORD = "record"


class ReplayError(HilError):
    """A session log that cannot be replayed (missing, unreadable, tampered, truncated, other
    version) or a recording that cannot be written."""


@dataclass(frozen=True)
class ReplayResult:
    """What :func:`write_replay` wrote: the file, its size, the entity paths and timelines, and
    whether the chain was verified (``reason``: what is wrong when it was not)."""

    path: Path
    bytes: int
    entities: list[str]
    timelines: list[str]
    records: int
    verified: bool
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "bytes": self.bytes, "entities": self.entities,
                "timelines": self.timelines, "records": self.records, "verified": self.verified,
                "reason": self.reason}


def default_out_path(session_log: Path) -> Path:
    """``<log dir>/<log name>.rrd``."""
    return session_log.with_suffix(".rrd")


def _read_records(path: Path, upto: int | None) -> list[dict[str, Any]]:
    """The JSON object lines of ``path``, stopping before line ``upto`` (1-based) when given."""
    out: list[dict[str, Any]] = []
    with open(path, "rb") as fh:
        for n, raw in enumerate(fh, 1):
            if upto is not None and n >= upto:
                break
            try:
                rec = json.loads(raw)
            except (ValueError, RecursionError):
                break
            if not isinstance(rec, dict):
                break
            out.append(rec)
    return out


def _problem(report: VerifyReport, records: list[dict[str, Any]]) -> str:
    """What is wrong with a log ("" when it replays verified)."""
    if not report.ok:
        where = f"line {report.first_bad_line}: " if report.first_bad_line else ""
        return f"{where}{report.reason}"
    if not report.closed:
        return report.reason or "session not closed (truncated or ended abruptly)"
    return ""


def load_verified(path: Path, allow_unverified: bool) -> tuple[list[dict[str, Any]], str]:
    """(records, problem): the log's records and what is wrong with its chain ("" when verified).

    Raises:
        ReplayError: missing or unreadable file; empty; another schema version; a chain problem
            without ``allow_unverified``.
    """
    if not path.is_file():
        raise ReplayError(f"{path}: no such session log")
    try:
        report = verify_session_log(path)
    except HilError as exc:
        raise ReplayError(str(exc)) from None
    try:
        records = _read_records(path, report.first_bad_line if not report.ok else None)
    except OSError as exc:
        raise ReplayError(f"{path}: cannot read session log: {exc.strerror or exc}") from None
    if not records:
        raise ReplayError(f"{path}: not a session log ({report.reason or 'no records'})")
    first = records[0]
    if first.get("event") != "session_started":
        raise ReplayError(f"{path}: not a session log (first record is not session_started)")
    if first.get("schema") != SCHEMA_VERSION:
        raise ReplayError(f"{path}: session log schema {first.get('schema')!r}, this version of hil "
                          f"replays schema {SCHEMA_VERSION}")
    problem = _problem(report, records)
    if problem and not allow_unverified:
        raise ReplayError(f"{path}: {problem}; refused (--allow-unverified replays it marked "
                          "unverified)")
    return records, problem


def _log_item(rr: Any, rec: Any, item: SceneItem) -> None:
    rec.set_time(TIMELINE_RECORD, sequence=item.seq)
    rec.set_time(TIMELINE_TIME, duration=np.timedelta64(item.t_ns, "ns"))
    if item.kind == "scalar":
        rec.log(item.entity, rr.Scalars(item.value))
    elif item.kind == "points":
        rec.log(item.entity, rr.Points3D(item.points, radii=rr.Radius.ui_points(4.0)))
    elif item.kind == "arrows":
        rec.log(item.entity, rr.Arrows3D(origins=item.points, vectors=item.vectors))
    elif item.kind == "strips":
        rec.log(item.entity, rr.LineStrips3D([item.points]))
    else:
        rec.log(item.entity, rr.TextLog(item.text, level=item.level))


def blueprint() -> Any:
    """The default layout: the 3D scene left; the key plots and the event log right."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/world", name="procedure (optical frame, mm)"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/series/following", name="following error"),
                rrb.TimeSeriesView(origin="/series/gate", name="gate deviation"),
                rrb.TimeSeriesView(origin="/series/latency", name="latency"),
                rrb.TextLogView(origin="/events", name="transitions and faults"),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="expanded"),
        collapse_panels=False,
    )


def _write(scene: Scene, out: Path, name: str, problem: str) -> list[str]:
    """Log ``scene`` into ``out``; returns the entity paths logged."""
    rr = import_rerun()
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=scene.session_id or None)
    rec.save(str(out), default_blueprint=blueprint())
    try:
        rec.set_log_time_enabled(False)
        rec.send_recording_name(f"UNVERIFIED {name}" if problem else name)
        entities = scene.entities()
        status = f"UNVERIFIED: {problem}" if problem else "verified: hash chain intact, session closed"
        rec.log("session/verification", rr.TextDocument(status), static=True)
        entities.append("session/verification")
        if problem:
            rec.set_time(TIMELINE_RECORD, sequence=0)
            rec.set_time(TIMELINE_TIME, duration=np.timedelta64(0, "ns"))
            rec.log("events/verification", rr.TextLog(status, level="WARN"))
            entities.append("events/verification")
        rec.log("world", rr.ViewCoordinates.RDF, static=True)  # the optical frame: x right, y down
        if scene.T_optical_from_robot is not None:
            T = scene.T_optical_from_robot
            rec.log("world/robot", rr.Transform3D(translation=T.t, mat3x3=T.R), static=True)
            entities.append("world/robot")
        for item in scene.items:
            _log_item(rr, rec, item)
        rec.flush()
    finally:
        rec.disconnect()
    return sorted(set(entities) | {"world"})


def write_replay(session_log: str | Path, out: str | Path | None = None, *,
                 allow_unverified: bool = False) -> ReplayResult:
    """Verify ``session_log`` and write its replay to ``out`` (default ``<log>.rrd``); module doc.

    Raises:
        ReplayError: the log is refused (module doc) or the recording cannot be written.
        ViewerUnavailableError: rerun-sdk is not installed.
    """
    path = Path(session_log)
    out_path = Path(out) if out is not None else default_out_path(path)
    records, problem = load_verified(path, allow_unverified)
    scene = build_scene(records)
    if not out_path.parent.is_dir():
        raise ReplayError(f"{out_path}: directory {out_path.parent} does not exist")
    tmp = out_path.with_name(f".{out_path.name}.{os.getpid()}.part")
    try:
        entities = _write(scene, tmp, path.stem, problem)
        tmp.replace(out_path)
    except OSError as exc:
        raise ReplayError(f"{out_path}: cannot write the recording: {exc.strerror or exc}") from None
    finally:
        tmp.unlink(missing_ok=True)
    return ReplayResult(out_path, out_path.stat().st_size, entities, [TIMELINE_RECORD, TIMELINE_TIME],
                        scene.records, not problem, problem)
