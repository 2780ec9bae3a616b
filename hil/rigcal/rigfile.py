"""The rig calibration file (``hil.rig_calibration`` version 1, docs/rig-calibration.md).

A JSON object::

    {"schema": "hil.rig_calibration", "version": 1,
     "units": {"length": "mm", "time": "ms", "angle": "deg"},
     "created_utc": "...", "setup": "...", "setup_name": "...",
     "stereo_calibration": path | null, "stereo_calibration_sha256": hex | null,
     "hand_eye": null | {"flange_markers_mm": [[x, y, z], ...],      # flange frame, layout order
                         "T_flange_from_tcp": 4x4, "T_optical_from_robot": 4x4,
                         "poses": n, "poses_used": n, "outliers": [i, ...],
                         "residual_mm_rms": r, "residual_deg_rms": r,
                         "validation_mm_rms": r | null, "validation_bound_mm": b,
                         "optical_correction": null | 4x4,   # measured -> metric optical points
                         "optical_correction_mm": m | null,  # its furthest move over the poses
                         "per_pose": [{"index", "residual_mm", "residual_deg", "role"}, ...]},
     "time_offsets": null | {"camera": {"offset_ms": o, "sigma_ms": s}, "robot": {...},
                             "tracker": {...}}}   # sigma_ms null: unknown

A device's offset is its reported timestamp minus the true time of what it reports; the
controller subtracts it (:mod:`hil.rigcal.time_align`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hil.errors import GeometryError, InputFileError
from hil.geometry.projective import ProjectiveCorrection

FloatArray = NDArray[np.float64]

SCHEMA = "hil.rig_calibration"
VERSION = 1
DEVICES = ("camera", "robot", "tracker")
#: A file's optical correction is refused when its linear part is further than this from the
#: identity (per element) or its projective row larger than this per mm: no stereo calibration that
#: ``hil rig-calibrate`` accepts is off by that much (its own bound is in millimetres, far smaller).
MAX_CORRECTION_LINEAR = 0.05
MAX_CORRECTION_PROJECTIVE_PER_MM = 1e-4


@dataclass(frozen=True)
class TimeOffset:
    """One device's time offset: reported stamp minus true time, ms, and its 1-sigma uncertainty."""

    offset_ms: float
    sigma_ms: float


@dataclass(frozen=True)
class RigCalibration:
    """What ``hil run`` takes from a rig calibration file.

    Attributes:
        flange_markers_mm: (M, 3) calibrated layout in the flange frame, or None (no hand-eye part).
        optical_correction: measured -> metric optical points, or None (none fitted).
        time_offsets: per device, or empty (no temporal part).
        document: the whole file as read.
    """

    flange_markers_mm: FloatArray | None
    optical_correction: ProjectiveCorrection | None = None
    time_offsets: dict[str, TimeOffset] = field(default_factory=dict)
    document: dict[str, Any] = field(default_factory=dict)

    def offset_ns(self, device: str) -> int:
        """The offset to subtract from ``device``'s stamps, ns (0 when not calibrated)."""
        o = self.time_offsets.get(device)
        return 0 if o is None else round(o.offset_ms * 1e6)


def save_rig_calibration(doc: dict[str, Any], path: Path) -> None:
    """Write ``doc`` (already in the schema) atomically: a temporary file renamed over ``path``.

    Raises:
        InputFileError: the file cannot be written.
    """
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(doc, indent=2) + "\n")
        tmp.replace(path)
    except OSError as exc:
        raise InputFileError(str(path), f"cannot write the rig calibration: {exc.strerror}") from None


def _finite(x: Any, where: str, path: str) -> float:
    if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(float(x)):
        raise InputFileError(path, f"{where} must be a finite number, got {x!r}")
    return float(x)


def _layout(he: Any, path: str) -> FloatArray | None:
    if he is None:
        return None
    if not isinstance(he, dict):
        raise InputFileError(path, "hand_eye must be an object or null")
    pts = he.get("flange_markers_mm")
    if not isinstance(pts, list) or len(pts) < 3 or not all(isinstance(p, list) and len(p) == 3 for p in pts):
        raise InputFileError(path, "hand_eye.flange_markers_mm must be a list of >= 3 [x, y, z] points (mm)")
    return np.array([[_finite(v, f"hand_eye.flange_markers_mm[{i}]", path) for v in p]
                     for i, p in enumerate(pts)], dtype=np.float64)


def _correction(he: Any, path: str) -> ProjectiveCorrection | None:
    H = he.get("optical_correction") if isinstance(he, dict) else None
    if H is None:
        return None
    where = "hand_eye.optical_correction"
    if not isinstance(H, list) or len(H) != 4 or not all(isinstance(r, list) and len(r) == 4 for r in H):
        raise InputFileError(path, f"{where} must be a 4x4 matrix (a list of four rows of four) or null")
    M = np.array([[_finite(v, f"{where}[{i}][{j}]", path) for j, v in enumerate(r)] for i, r in enumerate(H)])
    try:
        corr = ProjectiveCorrection.from_matrix(M)
    except GeometryError as exc:
        raise InputFileError(path, f"{where}: {exc}") from None
    Hn = corr.H_metric_from_measured
    linear = float(np.max(np.abs(Hn[:3, :3] - np.eye(3))))
    projective = float(np.max(np.abs(Hn[3, :3])))
    if linear > MAX_CORRECTION_LINEAR or projective > MAX_CORRECTION_PROJECTIVE_PER_MM:
        raise InputFileError(path, f"{where} is too far from the identity (linear part off by "
                                   f"{linear:.3g}, bound {MAX_CORRECTION_LINEAR}; projective row "
                                   f"{projective:.3g}/mm, bound {MAX_CORRECTION_PROJECTIVE_PER_MM}/mm): not "
                                   "a correction of a stereo calibration; recalibrate (hil rig-calibrate)")
    return corr


def _offsets(to: Any, path: str) -> dict[str, TimeOffset]:
    if to is None:
        return {}
    if not isinstance(to, dict):
        raise InputFileError(path, "time_offsets must be an object or null")
    out: dict[str, TimeOffset] = {}
    for dev, v in to.items():
        if dev not in DEVICES:
            raise InputFileError(path, f"time_offsets.{dev}: unknown device (one of {', '.join(DEVICES)})")
        if not isinstance(v, dict) or "offset_ms" not in v:
            raise InputFileError(path, f"time_offsets.{dev} must be an object with offset_ms (and sigma_ms)")
        s = v.get("sigma_ms")
        sigma = math.nan if s is None else _finite(s, f"time_offsets.{dev}.sigma_ms", path)
        out[dev] = TimeOffset(_finite(v["offset_ms"], f"time_offsets.{dev}.offset_ms", path), sigma)
    return out


def rig_calibration_from_dict(doc: Any, path: str = "<rig calibration>") -> RigCalibration:
    """Validate a parsed file.

    Raises:
        InputFileError: wrong schema or version, or a malformed field (named).
    """
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
        raise InputFileError(path, f"not a rig calibration file (schema must be {SCHEMA!r})")
    if doc.get("version") != VERSION:
        raise InputFileError(path, f"rig calibration version {doc.get('version')!r} is not supported "
                                   f"(this hil reads version {VERSION})")
    layout = _layout(doc.get("hand_eye"), path)
    correction = _correction(doc.get("hand_eye"), path)
    offsets = _offsets(doc.get("time_offsets"), path)
    if layout is None and not offsets:
        raise InputFileError(path, "the file holds neither a hand_eye nor a time_offsets part")
    return RigCalibration(layout, correction, offsets, doc)


def load_rig_calibration(path: str | Path) -> RigCalibration:
    """Read and validate a rig calibration file.

    Raises:
        InputFileError: unreadable, not JSON, or not a valid rig calibration.
    """
    p = str(path)
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise InputFileError(p, f"cannot read the rig calibration: {exc.strerror}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(p, f"not JSON: line {exc.lineno}: {exc.msg}") from None
    return rig_calibration_from_dict(doc, p)
