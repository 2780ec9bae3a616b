"""Pose sources for the emulators: what each sensor's pose is at a time.

A :class:`PoseSource` answers ``pose(sensor, t_s)`` with ``T_tracker_from_sensor`` (mm) or None
(the sensor is not seen). ``sensor`` is the device-side id as a string: the FBB address for a
Flock of Birds (``"0"`` standalone, ``"1"``...), the port handle in upper-case hex for an
Aurora (``"0A"``...). Sources compose: :class:`BreathingPoses` wraps another source.

Pose script files (``--poses FILE``):

* JSON: ``{"loop": true, "sensors": {"1": [{"t_s": 0.0, "position_mm": [x, y, z],
  "quaternion_wxyz": [w, x, y, z]}, {"t_s": 1.0, "missing": true}, ...]}}``
* CSV with header ``t_s,sensor,x_mm,y_mm,z_mm,qw,qx,qy,qz``; empty pose fields = missing.

Between samples the position is interpolated linearly and the rotation by normalised linear
interpolation of the quaternions; a missing sample holds until the next one.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from hil.errors import InputFileError
from hil.geometry.transform import RigidTransform


class PoseSource(Protocol):
    def pose(self, sensor: str, t_s: float) -> RigidTransform | None:
        """Pose of ``sensor`` at emulator time ``t_s`` (s since start), or None when not seen."""
        ...


@dataclass
class StaticPoses:
    """Fixed poses; a sensor without an entry sits at ``default_mm`` + ``spacing_mm`` x its index."""

    poses: dict[str, RigidTransform | None] = field(default_factory=dict)
    default_mm: tuple[float, float, float] = (300.0, 0.0, 100.0)
    spacing_mm: tuple[float, float, float] = (0.0, 40.0, 0.0)
    order: tuple[str, ...] = ()

    def pose(self, sensor: str, t_s: float) -> RigidTransform | None:
        if sensor in self.poses:
            return self.poses[sensor]
        k = self.order.index(sensor) if sensor in self.order else 0
        t = np.asarray(self.default_mm) + k * np.asarray(self.spacing_mm)
        return RigidTransform(RigidTransform.from_euler_zyx(0.3 * k, 0.2, -0.1).R, t)


@dataclass
class BreathingPoses:
    """The base pose plus breathing: a displacement ``amplitude_mm x (1 - cos(2 pi t / period)) / 2``
    (seed 003's assumption: the body surface moves with the organs), applied to every sensor
    except those in ``still``."""

    base: PoseSource
    amplitude_mm: tuple[float, float, float] = (0.0, 0.0, 8.0)
    period_s: float = 4.0
    still: frozenset[str] = frozenset()

    def pose(self, sensor: str, t_s: float) -> RigidTransform | None:
        T = self.base.pose(sensor, t_s)
        if T is None or sensor in self.still:
            return T
        s = (1.0 - math.cos(2.0 * math.pi * t_s / self.period_s)) / 2.0
        return RigidTransform(T.R, T.t + s * np.asarray(self.amplitude_mm))


@dataclass(frozen=True)
class _Sample:
    t_s: float
    T: RigidTransform | None


@dataclass
class ScriptPoses:
    """Poses from a time-keyed script (see the module docstring)."""

    samples: dict[str, list[_Sample]]
    loop: bool = False

    def pose(self, sensor: str, t_s: float) -> RigidTransform | None:
        seq = self.samples.get(sensor)
        if not seq:
            return None
        if self.loop and seq[-1].t_s > 0:
            t_s = t_s % seq[-1].t_s
        if t_s <= seq[0].t_s:
            return seq[0].T
        for a, b in itertools.pairwise(seq):
            if a.t_s <= t_s < b.t_s:
                if a.T is None or b.T is None:
                    return a.T
                f = (t_s - a.t_s) / (b.t_s - a.t_s)
                return _interpolate(a.T, b.T, f)
        return seq[-1].T


def _interpolate(a: RigidTransform, b: RigidTransform, f: float) -> RigidTransform:
    qa, qb = a.as_quaternion(), b.as_quaternion()
    if float(np.dot(qa, qb)) < 0:
        qb = -qb
    q = (1 - f) * qa + f * qb
    return RigidTransform.from_quaternion(q / np.linalg.norm(q), (1 - f) * a.t + f * b.t)


def _pose_from(entry: dict[str, Any], where: str) -> RigidTransform | None:
    if entry.get("missing"):
        return None
    try:
        t = [float(v) for v in entry["position_mm"]]
        q = [float(v) for v in entry.get("quaternion_wxyz", [1.0, 0.0, 0.0, 0.0])]
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}: needs position_mm [x, y, z] and quaternion_wxyz [w, x, y, z]") from exc
    if len(t) != 3 or len(q) != 4 or not all(math.isfinite(v) for v in t + q) or np.linalg.norm(q) < 1e-9:
        raise ValueError(f"{where}: bad position_mm/quaternion_wxyz")
    return RigidTransform.from_quaternion(q, t)


def load_pose_script(path: str | Path) -> ScriptPoses:
    """Read a JSON or CSV pose script.

    Raises:
        InputFileError: unreadable, bad syntax, missing fields, times not increasing.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputFileError(str(path), f"cannot read: {exc.strerror}") from exc
    samples: dict[str, list[_Sample]] = {}
    loop = False
    try:
        if p.suffix.lower() == ".csv":
            for i, row in enumerate(csv.DictReader(text.splitlines()), start=2):
                where = f"line {i}"
                sensor = (row.get("sensor") or "").strip()
                if not sensor:
                    raise ValueError(f"{where}: no sensor")
                missing = not (row.get("x_mm") or "").strip()
                entry: dict[str, Any] = {"missing": missing}
                if not missing:
                    entry["position_mm"] = [row["x_mm"], row["y_mm"], row["z_mm"]]
                    entry["quaternion_wxyz"] = [row["qw"], row["qx"], row["qy"], row["qz"]]
                samples.setdefault(sensor, []).append(_Sample(float(row["t_s"]), _pose_from(entry, where)))
        else:
            doc = json.loads(text)
            loop = bool(doc.get("loop", False))
            for sensor, entries in dict(doc["sensors"]).items():
                for j, entry in enumerate(entries):
                    where = f"sensors.{sensor}[{j}]"
                    samples.setdefault(str(sensor), []).append(
                        _Sample(float(entry["t_s"]), _pose_from(entry, where)))
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise InputFileError(str(path), f"not a pose script: {exc}") from exc
    for sensor, seq in samples.items():
        times = [s.t_s for s in seq]
        if any(b <= a for a, b in itertools.pairwise(times)):
            raise InputFileError(str(path), f"sensor {sensor}: t_s must increase")
    return ScriptPoses(samples, loop)
