"""A tracker calibration session: recorded stylus poses in, calibration file out.

Recorded-poses file (``hil tracker-calibrate --poses FILE``; also written by ``--record``)::

    {"format": "hil.tracker_poses", "version": 1, "stylus": "stylus", "reference": null,
     "pivot": [POSE, ...],                  # the stylus swivelled about the divot
     "pivot_reference": [POSE, ...],        # optional: a reference sensor at the same instants
     "touches": [{"label": "M1", "optical_mm": [x, y, z], "poses": [POSE, ...]}, ...]}

    POSE = {"position_mm": [x, y, z], "quaternion_wxyz": [w, x, y, z]}  or  {"matrix": 4x4 rows}

``optical_mm`` may be left out when the markers' optical positions are given separately
(``--markers FILE``, paired in order). Calibration file (``--out``)::

    {"format": "hil.tracker_calibration", "version": 1, "stylus": ..., "pivot": {...},
     "registration": {"T_optical_from_tracker": {"matrix": ...}, "fre_rms_mm": ..., "markers": [...]}}
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from hil.clock import Clock
from hil.errors import CalibrationError, GeometryError, InputFileError
from hil.geometry.transform import FloatArray, RigidTransform
from hil.tracking.pivot import PivotCalibration, pivot_calibration
from hil.tracking.tracker_registration import StylusTouch, TrackerRegistration, register_tracker_to_optical

POSES_FORMAT = "hil.tracker_poses"
CALIBRATION_FORMAT = "hil.tracker_calibration"


# --- poses ----------------------------------------------------------------------------------------
def pose_to_json(T: RigidTransform) -> dict[str, list[float]]:
    q = T.as_quaternion()
    return {"position_mm": [float(v) for v in T.t], "quaternion_wxyz": [float(v) for v in q]}


def pose_from_json(obj: Any, where: str) -> RigidTransform:
    """Raises ValueError naming ``where``."""
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: a pose must be an object")
    try:
        if "matrix" in obj:
            return RigidTransform.from_matrix(np.asarray(obj["matrix"], dtype=np.float64))
        t = np.asarray(obj["position_mm"], dtype=np.float64)
        q = np.asarray(obj["quaternion_wxyz"], dtype=np.float64)
    except KeyError as exc:
        raise ValueError(f"{where}: needs position_mm and quaternion_wxyz (or matrix)") from exc
    except (TypeError, ValueError, GeometryError) as exc:
        raise ValueError(f"{where}: {exc}") from exc
    if t.shape != (3,) or q.shape != (4,) or not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise ValueError(f"{where}: position_mm must be 3 numbers and quaternion_wxyz 4 finite numbers")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        raise ValueError(f"{where}: quaternion_wxyz has norm {norm:.6g}, not 1")
    return RigidTransform.from_quaternion(q, t)


@dataclass
class RecordedTouch:
    label: str
    poses: list[RigidTransform]
    optical_mm: FloatArray | None = None


@dataclass
class RecordedSession:
    """What a calibration session measured."""

    stylus: str = "stylus"
    reference: str | None = None
    pivot: list[RigidTransform] = field(default_factory=list)
    pivot_reference: list[RigidTransform] | None = None
    touches: list[RecordedTouch] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "format": POSES_FORMAT, "version": 1, "stylus": self.stylus, "reference": self.reference,
            "pivot": [pose_to_json(p) for p in self.pivot],
        }
        if self.pivot_reference is not None:
            out["pivot_reference"] = [pose_to_json(p) for p in self.pivot_reference]
        out["touches"] = [
            {"label": t.label, "poses": [pose_to_json(p) for p in t.poses],
             **({"optical_mm": [float(v) for v in t.optical_mm]} if t.optical_mm is not None else {})}
            for t in self.touches
        ]
        return out


def _read_json(path: str | Path) -> Any:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise InputFileError(str(path), f"cannot read: {exc.strerror or exc}") from exc
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(str(path), f"not JSON: {exc.msg} at line {exc.lineno}") from exc


def load_recorded_session(path: str | Path) -> RecordedSession:
    """Read a recorded-poses file.

    Raises:
        InputFileError: unreadable, not JSON, wrong format, or a bad field (named).
    """
    doc = _read_json(path)
    if not isinstance(doc, dict):
        raise InputFileError(str(path), "top level must be an object")
    if doc.get("format", POSES_FORMAT) != POSES_FORMAT:
        raise InputFileError(str(path), f"format is {doc.get('format')!r}, expected {POSES_FORMAT!r}")
    try:
        pivot = [pose_from_json(p, f"pivot[{i}]") for i, p in enumerate(_list(doc, "pivot"))]
        ref = None
        if doc.get("pivot_reference") is not None:
            ref = [pose_from_json(p, f"pivot_reference[{i}]")
                   for i, p in enumerate(_list(doc, "pivot_reference"))]
        touches = []
        for i, t in enumerate(_list(doc, "touches", required=False)):
            if not isinstance(t, dict):
                raise ValueError(f"touches[{i}]: must be an object")
            optical = None
            if t.get("optical_mm") is not None:
                optical = np.asarray(t["optical_mm"], dtype=np.float64)
                if optical.shape != (3,) or not np.all(np.isfinite(optical)):
                    raise ValueError(f"touches[{i}].optical_mm: must be 3 finite numbers")
            poses = [pose_from_json(p, f"touches[{i}].poses[{j}]") for j, p in enumerate(_list(t, "poses"))]
            touches.append(RecordedTouch(str(t.get("label", i + 1)), poses, optical))
    except (ValueError, TypeError) as exc:
        raise InputFileError(str(path), str(exc)) from exc
    reference = doc.get("reference")
    return RecordedSession(str(doc.get("stylus", "stylus")), None if reference is None else str(reference),
                           pivot, ref, touches)


def _list(doc: dict[str, Any], key: str, *, required: bool = True) -> list[Any]:
    value = doc.get(key)
    if value is None and not required:
        return []
    if not isinstance(value, list):
        raise ValueError(f"{key}: must be a list")
    return value


# --- calibration ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrackerCalibration:
    """The result written to the calibration file."""

    stylus: str
    pivot: PivotCalibration
    registration: TrackerRegistration | None

    def to_json(self) -> dict[str, Any]:
        return {
            "format": CALIBRATION_FORMAT, "version": 1, "stylus": self.stylus,
            "pivot": self.pivot.to_dict(),
            "registration": None if self.registration is None else self.registration.to_dict(),
        }


def calibrate(session: RecordedSession, optical_points_mm: FloatArray | None = None, *,
              max_touch_spread_mm: float = 1.0) -> TrackerCalibration:
    """Pivot calibration, then (when there are touches) the tracker -> optical registration.

    Args:
        session: the recorded poses.
        optical_points_mm: (N, 3) marker positions in the optical frame, paired in order with
            the touches; when None, each touch's own ``optical_mm`` is used.

    Raises:
        CalibrationError: any calibration failure, or touches without optical positions.
    """
    piv = pivot_calibration(session.pivot, references=session.pivot_reference)
    if not session.touches:
        return TrackerCalibration(session.stylus, piv, None)
    if optical_points_mm is None:
        missing = [t.label for t in session.touches if t.optical_mm is None]
        if missing:
            raise CalibrationError(
                f"touches {missing} have no optical_mm; give the markers' optical positions")
        optical = np.stack([t.optical_mm for t in session.touches if t.optical_mm is not None])
    else:
        optical = np.asarray(optical_points_mm, dtype=np.float64)
    touches = [StylusTouch(t.label, tuple(t.poses)) for t in session.touches]
    reg = register_tracker_to_optical(touches, optical, piv.tip_offset_sensor_mm,
                                      max_touch_spread_mm=max_touch_spread_mm)
    return TrackerCalibration(session.stylus, piv, reg)


def save_json(path: str | Path, doc: dict[str, Any]) -> None:
    """Write ``doc`` (creating the directory).

    Raises:
        InputFileError: the file cannot be written.
    """
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    except OSError as exc:
        raise InputFileError(str(path), f"cannot write: {exc.strerror or exc}") from exc


def load_tracker_calibration(path: str | Path) -> tuple[FloatArray, RigidTransform | None]:
    """Read a calibration file: (tip offset in the sensor frame (3,), T_optical_from_tracker or None).

    Raises:
        InputFileError: unreadable or not JSON.
        CalibrationError: wrong format or a bad field (named).
    """
    doc = _read_json(path)
    if not isinstance(doc, dict) or doc.get("format") != CALIBRATION_FORMAT:
        raise CalibrationError(f"{path}: not a {CALIBRATION_FORMAT} file")
    try:
        tip = np.asarray(doc["pivot"]["tip_offset_sensor_mm"], dtype=np.float64)
        if tip.shape != (3,) or not np.all(np.isfinite(tip)):
            raise ValueError("must be 3 finite numbers")
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: pivot.tip_offset_sensor_mm: {exc}") from exc
    reg = doc.get("registration")
    if reg is None:
        return tip, None
    try:
        T = RigidTransform.from_matrix(np.asarray(reg["T_optical_from_tracker"]["matrix"], dtype=np.float64))
    except (KeyError, TypeError, ValueError, GeometryError) as exc:
        raise CalibrationError(f"{path}: registration.T_optical_from_tracker: {exc}") from exc
    return tip, T


# --- interactive collection -----------------------------------------------------------------------
class _Sample(Protocol):
    @property
    def T_tracker_from_sensor(self) -> RigidTransform | None: ...

    @property
    def seq(self) -> int: ...

    @property
    def missing(self) -> bool: ...


class SampleSource(Protocol):
    """What the collection needs from a tracker (``drivers.interfaces.PoseTracker`` fits)."""

    def latest(self) -> Any: ...


def collect_samples(tracker: SampleSource, sensor: str, n: int, clock: Clock, *,
                    reference: str | None = None, poll_s: float = 0.005,
                    timeout_s: float = 60.0) -> tuple[list[RigidTransform], list[RigidTransform] | None]:
    """Collect ``n`` new poses of ``sensor`` (and of ``reference`` from the same poll).

    A sample counts once (by its ``seq``); missing samples are skipped.

    Raises:
        CalibrationError: fewer than ``n`` usable samples within ``timeout_s`` (clock time).
        DriverError subclasses from ``tracker.latest()``.
    """
    out: list[RigidTransform] = []
    refs: list[RigidTransform] | None = [] if reference is not None else None
    last_seq: int | None = None
    start = clock.now_ns()
    while len(out) < n:
        samples = tracker.latest()
        s = samples.get(sensor)
        ok = s is not None and not s.missing and s.T_tracker_from_sensor is not None and s.seq != last_seq
        r = samples.get(reference) if reference is not None else None
        if ok and reference is not None and (r is None or r.missing or r.T_tracker_from_sensor is None):
            ok = False
        if ok:
            assert s is not None
            out.append(s.T_tracker_from_sensor)
            last_seq = s.seq
            if refs is not None and r is not None:
                refs.append(r.T_tracker_from_sensor)
            continue
        if (clock.now_ns() - start) * 1e-9 > timeout_s:
            raise CalibrationError(f"only {len(out)} of {n} samples of {sensor!r} in {timeout_s:g} s "
                                   "(sensor missing or out of volume?)")
        clock.sleep(poll_s)
    return out, refs


def collect_interactive(tracker: SampleSource, clock: Clock, *, stylus: str, labels: Sequence[str],
                        ask: Callable[[str], object], say: Callable[[str], object],
                        reference: str | None = None, pivot_samples: int = 200,
                        touch_samples: int = 20, settle_samples: int = 5) -> RecordedSession:
    """Walk the user through a pivot calibration and one touch per marker.

    ``ask(message)`` waits for the user (Enter); ``say(message)`` reports progress. The first
    ``settle_samples`` after each Enter are dropped (the hand settles; records in flight).
    """
    session = RecordedSession(stylus=stylus, reference=reference)
    ask(f"Pivot calibration: put the tip of {stylus!r} in the divot. Press Enter, then swivel the "
        f"tool about the tip (cone of 20-40 deg, in all directions) while {pivot_samples} samples are taken.")
    collect_samples(tracker, stylus, settle_samples, clock)
    session.pivot, session.pivot_reference = collect_samples(tracker, stylus, pivot_samples, clock,
                                                             reference=reference)
    piv = pivot_calibration(session.pivot, references=session.pivot_reference)
    say(f"pivot: tip offset {np.round(piv.tip_offset_sensor_mm, 2).tolist()} mm, "
        f"RMS {piv.rms_mm:.3f} mm over {piv.n_poses} poses, swivel {piv.rotation_spread_deg:.0f} deg")
    for label in labels:
        ask(f"Touch marker {label} with the stylus tip, hold still, press Enter.")
        collect_samples(tracker, stylus, settle_samples, clock)
        poses, _ = collect_samples(tracker, stylus, touch_samples, clock)
        tip = np.stack([p.apply(piv.tip_offset_sensor_mm) for p in poses])
        spread = float(np.sqrt(np.mean(np.sum((tip - tip.mean(axis=0)) ** 2, axis=1))))
        say(f"marker {label}: {len(poses)} samples, spread {spread:.3f} mm")
        session.touches.append(RecordedTouch(label, poses))
    return session

