"""The procedure plan: CT fiducials, skin entry and target, all in the image (CT) frame, mm.

Two ways to write a plan:

1. The project's own JSON (``configs/plans/*.json``)::

    {"format": "hil-plan", "version": 1, "frame": "image", "units": "mm",
     "fiducials_mm": [[x, y, z], ...], "entry_mm": [x, y, z], "target_mm": [x, y, z],
     "phases": [{"fiducials_mm": [[x, y, z], ...], "target_mm": [x, y, z], "entry_mm": [x, y, z]}, ...],
     "phases_period_s": 4.0}

   ``phases`` is optional: the fiducials and the target at other phases of a breathing cycle, as a
   4D CT shows them (same frame, fiducials in the same order). The main ``fiducials_mm`` and
   ``target_mm`` are the phase the procedure registers at (end-exhale). The surrogate target
   model (``[procedure.compensation] target_model = "surrogate"``, hil/controller/target_model.py)
   is fitted to them. ``phases_period_s`` (optional, s) says the phases are the equal phase bins of
   one breath, in order after the registered one, at that mean breathing period (what a 4D CT's
   respiratory surrogate records): the model then also learns the target's lag from them.
   A phase's ``entry_mm`` (optional; in every phase or in none) is where the skin entry sits at
   that phase, as the CT's skin surface shows it: the ``pattern`` change estimator
   (``[procedure.compensation] estimator = "pattern"``, hil/controller/entry_pattern.py) is fitted
   to the fiducials and the entry.

2. A labelled point list, as planning software writes it: a 3D Slicer markups file
   (``.mrk.json``, ``.fcsv``) or a CSV/JSON point file read by :func:`hil.io.read_points`, with one
   point labelled ``entry`` and one labelled ``target`` (case-insensitive); every other point is
   a CT fiducial, in file order. Slicer files are read in LPS (the DICOM patient frame of the CT).
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
from hil.io.points import PointSet, read_points

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PlanPhase:
    """One breathing phase of a 4D CT (image frame, mm): the fiducials in the plan's order, (N, 3),
    the target, (3,), and the skin entry, (3,) (None when the plan does not give it)."""

    fiducials_mm: FloatArray
    target_mm: FloatArray
    entry_mm: FloatArray | None = None


@dataclass(frozen=True)
class ProcedurePlan:
    """The physician's plan in the image frame (mm).

    Attributes:
        fiducials_mm: (N, 3) CT ring-marker centres, N >= 3.
        entry_mm: (3,) skin entry point.
        target_mm: (3,) target point.
        source: where it came from (file path or ``<memory>``).
        phases: other breathing phases of a 4D CT (module doc); empty when the plan has none.
        phases_period_s: the 4D CT's mean breathing period when the phases are its equal bins in
            order (module doc); None when not known.
    """

    fiducials_mm: FloatArray
    entry_mm: FloatArray
    target_mm: FloatArray
    source: str = "<memory>"
    phases: tuple[PlanPhase, ...] = ()
    phases_period_s: float | None = None

    def __post_init__(self) -> None:
        if self.fiducials_mm.shape[0] < 3:
            raise GeometryError(f"plan needs >= 3 fiducials, has {self.fiducials_mm.shape[0]}")
        if float(np.linalg.norm(self.target_mm - self.entry_mm)) < 1.0:
            raise GeometryError("plan entry and target are less than 1 mm apart")
        for k, ph in enumerate(self.phases):
            if ph.fiducials_mm.shape != self.fiducials_mm.shape:
                raise GeometryError(f"phases[{k}].fiducials_mm: {ph.fiducials_mm.shape[0]} points, the plan "
                                    f"has {self.fiducials_mm.shape[0]} fiducials")

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
    pts = {key: _one_point(doc.get(key, []), key, source) for key in ("entry_mm", "target_mm")}
    phases = _phases(doc.get("phases", []), source)
    period = doc.get("phases_period_s")
    if period is not None and (isinstance(period, bool) or not isinstance(period, (int, float))
                               or not 0.5 <= period <= 30.0):
        raise InputFileError(source, f"phases_period_s: a breathing period in s, 0.5-30 (got {period!r})")
    if period is not None and not phases:
        raise InputFileError(source, "phases_period_s: given without phases")
    try:
        return ProcedurePlan(fid, pts["entry_mm"], pts["target_mm"], source, phases,
                             None if period is None else float(period))
    except GeometryError as exc:
        raise InputFileError(source, str(exc)) from None


def _one_point(value: Any, where: str, source: str) -> FloatArray:
    try:
        arr = as_points(value, where)
    except (GeometryError, TypeError, ValueError) as exc:
        raise InputFileError(source, f"{where}: {exc}") from None
    if arr.shape[0] != 1:
        raise InputFileError(source, f"{where}: must be one point [x, y, z]")
    out: FloatArray = arr[0]
    return out


def _phases(doc: Any, source: str) -> tuple[PlanPhase, ...]:
    """``phases`` of a plan document (module doc); InputFileError naming the phase and field."""
    if not isinstance(doc, list):
        raise InputFileError(source, "phases: must be a list of {fiducials_mm, target_mm}")
    out: list[PlanPhase] = []
    for k, ph in enumerate(doc):
        if not isinstance(ph, dict) or not {"fiducials_mm", "target_mm"} <= set(ph) <= _PHASE_KEYS:
            raise InputFileError(source, f"phases[{k}]: must be an object with fiducials_mm, target_mm "
                                         "and optionally entry_mm")
        try:
            fid = as_points(ph["fiducials_mm"], f"phases[{k}].fiducials_mm")
        except (GeometryError, TypeError, ValueError) as exc:
            raise InputFileError(source, f"phases[{k}].fiducials_mm: {exc}") from None
        entry = _one_point(ph["entry_mm"], f"phases[{k}].entry_mm", source) if "entry_mm" in ph else None
        out.append(PlanPhase(fid, _one_point(ph["target_mm"], f"phases[{k}].target_mm", source), entry))
    with_entry = [ph.entry_mm is not None for ph in out]
    if any(with_entry) and not all(with_entry):
        k = with_entry.index(False)
        raise InputFileError(source, f"phases[{k}]: no entry_mm, where other phases give one (in every "
                                     "phase or in none)")
    return tuple(out)


#: the keys a phase may have
_PHASE_KEYS = frozenset({"fiducials_mm", "target_mm", "entry_mm"})


def plan_from_points(points: PointSet, source: str) -> ProcedurePlan:
    """A plan from labelled points: ``entry`` and ``target`` by label, the rest fiducials.

    Raises:
        InputFileError: no (or more than one) point labelled entry / target, < 3 fiducials.
    """
    roles: dict[str, list[int]] = {"entry": [], "target": []}
    fiducial_rows: list[int] = []
    for i, label in enumerate(points.labels):
        key = label.strip().lower()
        if key in roles:
            roles[key].append(i)
        else:
            fiducial_rows.append(i)
    for role, rows in roles.items():
        if len(rows) != 1:
            found = "none" if not rows else f"{len(rows)} (points {', '.join(str(r + 1) for r in rows)})"
            raise InputFileError(
                source, f"a plan needs exactly one point labelled {role!r}; found {found}"
            )
    if len(fiducial_rows) < 3:
        raise InputFileError(
            source, f"a plan needs >= 3 fiducials besides entry and target; found {len(fiducial_rows)}"
        )
    pts = points.points_mm
    try:
        return ProcedurePlan(
            pts[fiducial_rows], pts[roles["entry"][0]], pts[roles["target"][0]], source
        )
    except GeometryError as exc:
        raise InputFileError(source, str(exc)) from None


def load_plan(path: str | Path) -> ProcedurePlan:
    """Read a plan file: the project's ``hil-plan`` JSON, or labelled points (module doc).

    Raises:
        InputFileError: unreadable, not JSON (also hostile JSON: nested too deeply, huge
            integer literals), or invalid (naming the field).
    """
    p = Path(path)
    if p.suffix.lower() in (".fcsv", ".csv") or p.name.lower().endswith(".mrk.json"):
        return plan_from_points(read_points(p), str(path))
    try:
        text = p.read_text(encoding="utf-8")
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
    if isinstance(doc, dict) and not ({"format", "fiducials_mm"} & doc.keys()):
        return plan_from_points(read_points(p), str(path))  # {"points": [...]} with labels
    if isinstance(doc, list):
        return plan_from_points(read_points(p), str(path))  # a labelled point list
    return plan_from_dict(doc, str(path))
