"""Hand-eye pose pairs from the project's own session logs (``hil run``'s JSONL, docs/run.md).

Each ``frame_measured`` record holds the flange markers the controller saw in that stereo pair
(``flange_mm``: optical frame, mm, layout order; null rows not seen), the arm's reported pose the
controller paired with it (``T_robot_from_guide``: robot base frame, mm) and the arm's speed.
Pairs are made from the arm's still stretches only: a pose paired with a frame while the arm moves
carries the pairing's timing error times the speed.

1. **Still frames**: ``tcp_speed_mm_s`` at most :data:`STILL_SPEED_MM_S` and at least three
   flange markers seen.
2. **One pair per still pose**: consecutive still frames whose reported pose stays within
   :data:`SAME_POSE_MM` / :data:`SAME_POSE_DEG` of the stretch's first are one pose; its markers
   are averaged (per marker, over the frames that saw it), its robot pose is the stretch's middle
   record's. A stretch of fewer than :data:`MIN_STILL_FRAMES` frames is not used.
3. **The target**: the marker plate's shape is taken from the pose that saw the most markers
   (its markers, centred on their mean: the **target frame** is that plate as it stood then, axes
   of the optical frame, origin at the markers' centroid). Each pose's ``T_camera_from_target`` is
   that shape fitted to its markers (Horn, seed 000 eqs 17-21) over the markers both saw.

The hand frame of these pairs is the **needle guide** (the log records ``T_robot_from_guide``), so
``X`` comes out as ``T_guide_from_target``; everything else is the ``--samples`` convention
(:mod:`hil.rigcal.samples`). The markers are what the controller used: through the rig
calibration's optical correction when the session had one (its header names the file).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.errors import GeometryError
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform
from hil.rigcal.samples import FloatArray, PosePairs, SamplesError, check_finite, make_pairs

#: frames with the arm slower than this (mm/s) are still
STILL_SPEED_MM_S = 1.0
#: still frames within this of their stretch's first pose (mm, deg) are the same pose
SAME_POSE_MM = 0.5
SAME_POSE_DEG = 0.2
#: a still stretch needs this many frames to make a pair
MIN_STILL_FRAMES = 3
#: the record a session log starts with, and the records pairs are made from
SESSION_STARTED = "session_started"
FRAME_MEASURED = "frame_measured"


@dataclass(frozen=True)
class _Frame:
    line: int
    t_s: float
    T_robot_from_guide: RigidTransform
    markers_mm: FloatArray     # (M, 3), NaN rows not seen


def is_session_log(path: Path) -> bool:
    """Whether the file's first line is a session log's first record (for format detection)."""
    try:
        with path.open() as f:
            first = json.loads(f.readline())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(first, dict) and first.get("event") == SESSION_STARTED


def _records(path: Path) -> Iterator[tuple[int, dict[str, Any]]]:
    p = str(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SamplesError(p, f"cannot read: {getattr(exc, 'strerror', None) or exc}") from None
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as exc:
            raise SamplesError(p, f"line {n}: not JSON: {exc.msg}") from None
        if not isinstance(rec, dict):
            raise SamplesError(p, f"line {n}: not a JSON object")
        if n == 1 and rec.get("event") != SESSION_STARTED:
            raise SamplesError(p, f"line 1: not a session log (the first record must be {SESSION_STARTED!r})")
        yield n, rec


def _pose(value: Any, path: str, where: str) -> RigidTransform:
    if not isinstance(value, dict) or "rotvec_rad" not in value or "t_mm" not in value:
        raise SamplesError(path, f"{where}: T_robot_from_guide must be {{rotvec_rad, t_mm}}")
    try:
        rv = np.array(value["rotvec_rad"], dtype=np.float64).reshape(3)
        t = np.array(value["t_mm"], dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise SamplesError(path, f"{where}: T_robot_from_guide is not two 3-vectors") from None
    check_finite(np.concatenate([rv, t]), path, f"{where} (T_robot_from_guide)")
    return RigidTransform.from_rotvec(rv, t)


def _markers(value: Any, path: str, where: str) -> FloatArray | None:
    if value is None:
        return None
    try:
        rows = [[np.nan] * 3 if r is None else r for r in value]
        m = np.array(rows, dtype=np.float64).reshape(-1, 3)
    except (TypeError, ValueError):
        raise SamplesError(path, f"{where}: flange_mm is not a list of [x, y, z] rows (or nulls)") from None
    return m


def _still_frames(path: Path) -> list[_Frame]:
    p = str(path)
    out = []
    for n, rec in _records(path):
        if rec.get("event") != FRAME_MEASURED:
            continue
        where = f"line {n}"
        speed = rec.get("tcp_speed_mm_s")
        m = _markers(rec.get("flange_mm"), p, where)
        if m is None or int(np.all(np.isfinite(m), axis=1).sum()) < 3:
            continue
        if not isinstance(speed, int | float) or speed > STILL_SPEED_MM_S:
            continue
        t_ns = rec.get("exposure_t_ns")
        if not isinstance(t_ns, int):
            raise SamplesError(p, f"{where}: exposure_t_ns must be an integer (ns)")
        out.append(_Frame(n, t_ns * 1e-9, _pose(rec.get("T_robot_from_guide"), p, where), m))
    return out


def _stretches(frames: list[_Frame]) -> list[list[_Frame]]:
    groups: list[list[_Frame]] = []
    for f in frames:
        g = groups[-1] if groups else None
        if g is not None and g[-1].markers_mm.shape == f.markers_mm.shape:
            d = g[0].T_robot_from_guide.inverse() @ f.T_robot_from_guide
            if (float(np.linalg.norm(d.t)) <= SAME_POSE_MM
                    and np.degrees(d.rotation_angle_rad()) <= SAME_POSE_DEG):
                g.append(f)
                continue
        groups.append([f])
    return [g for g in groups if len(g) >= MIN_STILL_FRAMES]


def _mean_markers(g: list[_Frame]) -> FloatArray:
    stack = np.array([f.markers_mm for f in g])
    seen = np.isfinite(stack).all(axis=2)
    out = np.full(stack.shape[1:], np.nan)
    for i in range(stack.shape[1]):
        if seen[:, i].any():
            out[i] = stack[seen[:, i], i].mean(axis=0)
    return out


def read_session_log(path: Path) -> PosePairs:
    """The pose pairs of a session log (module doc): ``T_base_from_flange`` = the guide's reported
    pose (hand frame: the needle guide), ``T_camera_from_target`` = the marker plate's pose.

    Raises:
        SamplesError: unreadable, not a session log, a malformed record (its line named), or no
            still pose with three or more flange markers.
    """
    p = str(path)
    stretches = _stretches(_still_frames(path))
    if not stretches:
        raise SamplesError(p, "no still poses with >= 3 flange markers seen (frame_measured records "
                              f"with tcp_speed_mm_s <= {STILL_SPEED_MM_S:g} mm/s, {MIN_STILL_FRAMES} frames "
                              "or more at one pose)")
    markers = [_mean_markers(g) for g in stretches]
    ref = max(range(len(markers)), key=lambda k: int(np.isfinite(markers[k]).all(axis=1).sum()))
    shape = markers[ref] - np.nanmean(markers[ref], axis=0)
    T_cam, T_rob, where, t_s = [], [], [], []
    for g, m in zip(stretches, markers, strict=True):
        ok = np.isfinite(m).all(axis=1) & np.isfinite(shape).all(axis=1)
        mid = g[len(g) // 2]
        if int(ok.sum()) < 3:
            continue
        try:
            T = register_horn(m[ok], shape[ok]).T_fixed_from_moving
        except GeometryError:
            continue   # collinear markers at this pose: it fixes no plate pose
        T_cam.append(T.as_matrix())
        T_rob.append(mid.T_robot_from_guide.as_matrix())
        where.append(f"line {mid.line}")
        t_s.append(mid.t_s)
    return make_pairs(np.array(T_rob).reshape(-1, 4, 4), np.array(T_cam).reshape(-1, 4, 4), tuple(where), p,
                      np.array(t_s))
