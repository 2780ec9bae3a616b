"""The procedure plan: CT fiducials, skin entry and target, all in the image (CT) frame, mm.

File format (``configs/plans/*.json``)::

    {"format": "hil-plan", "version": 1, "frame": "image", "units": "mm",
     "fiducials_mm": [[x, y, z], ...], "entry_mm": [x, y, z], "target_mm": [x, y, z]}
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hil.errors import GeometryError, InputFileError
from hil.geometry.transform import as_points

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ProcedurePlan:
    """The physician's plan in the image frame (mm).

    Attributes:
        fiducials_mm: (N, 3) CT ring-marker centres, N >= 3.
        entry_mm: (3,) skin entry point.
        target_mm: (3,) target point.
        source: where it came from (file path or ``<memory>``).
    """

    fiducials_mm: FloatArray
    entry_mm: FloatArray
    target_mm: FloatArray
    source: str = "<memory>"

    def __post_init__(self) -> None:
        if self.fiducials_mm.shape[0] < 3:
            raise GeometryError(f"plan needs >= 3 fiducials, has {self.fiducials_mm.shape[0]}")
        if float(np.linalg.norm(self.target_mm - self.entry_mm)) < 1.0:
            raise GeometryError("plan entry and target are less than 1 mm apart")

    @property
    def path_length_mm(self) -> float:
        return float(np.linalg.norm(self.target_mm - self.entry_mm))


def plan_from_dict(doc: Any, source: str = "<memory>") -> ProcedurePlan:
    """Validate a plan document (see module doc).

    Raises:
        InputFileError: naming ``source`` and the offending field.
    """
    if not isinstance(doc, dict):
        raise InputFileError(source, "plan must be a JSON object")
    if doc.get("format") != "hil-plan":
        raise InputFileError(source, f"format: expected 'hil-plan', got {doc.get('format')!r}")
    if doc.get("version") != 1:
        raise InputFileError(source, f"version: unsupported {doc.get('version')!r} (this reads 1)")
    for key, want in (("frame", "image"), ("units", "mm")):
        if doc.get(key, want) != want:
            raise InputFileError(source, f"{key}: expected {want!r}, got {doc.get(key)!r}")
    try:
        fid = as_points(doc.get("fiducials_mm", []), "fiducials_mm")
    except (GeometryError, TypeError, ValueError) as exc:
        raise InputFileError(source, f"fiducials_mm: {exc}") from None
    pts: dict[str, FloatArray] = {}
    for key in ("entry_mm", "target_mm"):
        try:
            arr = as_points(doc.get(key, []), key)
        except (GeometryError, TypeError, ValueError) as exc:
            raise InputFileError(source, f"{key}: {exc}") from None
        if arr.shape[0] != 1:
            raise InputFileError(source, f"{key}: must be one point [x, y, z]")
        pts[key] = arr[0]
    try:
        return ProcedurePlan(fid, pts["entry_mm"], pts["target_mm"], source)
    except GeometryError as exc:
        raise InputFileError(source, str(exc)) from None


def load_plan(path: str | Path) -> ProcedurePlan:
    """Read a plan file.

    Raises:
        InputFileError: unreadable, not JSON (also hostile JSON: nested too deeply, huge
            integer literals), or invalid (naming the field).
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(str(path), f"cannot read plan: {exc}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(str(path), f"not JSON: {exc.msg} at line {exc.lineno}") from None
    except ValueError as exc:  # e.g. an integer literal longer than Python's digit limit
        raise InputFileError(str(path), f"unusable JSON: {exc}") from None
    except RecursionError:
        raise InputFileError(str(path), "unusable JSON: nested too deeply") from None
    return plan_from_dict(doc, str(path))
