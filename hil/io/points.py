"""Read 3-D point lists from the files planning software writes.

Formats, chosen by file name:

- ``*.mrk.json`` — 3D Slicer markups JSON: every ``markups[].controlPoints[].position`` in order,
  labels from ``label``; each markup's ``coordinateSystem`` (``"LPS"`` or ``"RAS"``) is honoured.
- ``*.fcsv`` — 3D Slicer markups fiducial CSV: the ``# columns = id,x,y,z,...`` header names the
  columns (default: Slicer's id,x,y,z,...,label order); ``# CoordinateSystem = LPS|RAS|0|1``
  (0 = RAS, 1 = LPS, Slicer's numeric codes) is honoured; a file without it is RAS (Slicer < 4.11).
- ``*.json`` — a list of ``[x, y, z]``; a list of objects with ``x``/``y``/``z`` (or
  ``position``) and optional ``label``/``name``/``id``; or either of those under ``{"points": ...}``.
- anything else (``*.csv``, ``*.txt``, ...) — delimited text (comma, semicolon, tab or spaces),
  ``#`` comments; an optional header row naming columns ``x``, ``y``, ``z`` (optionally with a
  unit suffix such as ``x_mm``) and an optional ``label``/``name``/``id`` column; without a header,
  rows of ``x,y,z`` or ``label,x,y,z``.

Coordinate convention: Slicer files are converted to **LPS** (DICOM patient coordinates, the
convention CT scanners and ITK use and the one Slicer writes markup files in since 4.11) by
default; pass ``coordinate_system="RAS"`` for RAS. RAS <-> LPS negates x and y. Plain CSV/JSON
carry no convention and are returned as written. Units are millimetres (a Slicer file declaring
other ``coordinateUnits`` is rejected).

Every failure raises :class:`hil.errors.InputFileError` naming the file and the problem.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from hil.errors import InputFileError

FloatArray = NDArray[np.float64]
CoordinateSystem = Literal["LPS", "RAS"]

_LABEL_NAMES = ("label", "name", "id")
_RAS_TO_LPS = np.array([-1.0, -1.0, 1.0])


@dataclass(frozen=True)
class PointSet:
    """Points read from a file.

    Attributes:
        points_mm: (N, 3) float64, read-only, mm, in the file's order.
        labels: one label per point (the file's labels, else "1".."N").
        source_coordinate_system: "LPS"/"RAS" as declared by a Slicer file, else None.
        coordinate_system: convention of ``points_mm`` ("LPS"/"RAS"), or None when the file
            declares none (plain CSV/JSON, returned as written).
    """

    points_mm: FloatArray
    labels: tuple[str, ...]
    source_coordinate_system: str | None = None
    coordinate_system: str | None = None

    def __len__(self) -> int:
        return int(self.points_mm.shape[0])


def read_points(path: str | Path, *, coordinate_system: CoordinateSystem = "LPS") -> PointSet:
    """Read a point list (format by file name, see module docstring).

    Args:
        path: the file.
        coordinate_system: convention for Slicer files' output ("LPS" default, or "RAS").

    Returns:
        PointSet with at least one point, all finite.

    Raises:
        InputFileError: unreadable file, unknown layout, non-numeric or non-finite coordinates,
            wrong column count, no points, unsupported Slicer coordinate system or units.
    """
    name = str(path)
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputFileError(name, "file not found") from None
    except IsADirectoryError:
        raise InputFileError(name, "is a directory, not a point file") from None
    except UnicodeDecodeError:
        raise InputFileError(name, "not a UTF-8 text file") from None
    except OSError as exc:
        raise InputFileError(name, f"cannot read: {exc.strerror or exc}") from None
    lower = p.name.lower()
    if lower.endswith(".mrk.json"):
        return _read_mrk_json(name, text, coordinate_system)
    if lower.endswith(".fcsv"):
        return _read_fcsv(name, text, coordinate_system)
    if lower.endswith(".json"):
        return _read_json(name, text, coordinate_system)
    return _read_delimited(name, text)


# ---------------------------------------------------------------------- helpers
def _finish(
    name: str,
    rows: Sequence[Sequence[float]],
    labels: Sequence[str | None],
    source_cs: str | None = None,
    out_cs: str | None = None,
) -> PointSet:
    if not rows:
        raise InputFileError(name, "contains no points")
    arr = np.array(rows, dtype=np.float64).reshape(len(rows), 3)
    bad = np.nonzero(~np.all(np.isfinite(arr), axis=1))[0]
    if bad.size:
        raise InputFileError(name, f"point {int(bad[0]) + 1} has a NaN or infinite coordinate")
    arr.setflags(write=False)
    final = tuple(lab if lab else str(i + 1) for i, lab in enumerate(labels))
    return PointSet(arr, final, source_cs, out_cs)


def _to_float(name: str, where: str, value: object) -> float:
    if isinstance(value, bool):
        raise InputFileError(name, f"{where}: expected a number, got {value!r}")
    if isinstance(value, int | float):
        try:
            v = float(value)
        except OverflowError:  # a JSON integer beyond float range
            raise InputFileError(name, f"{where}: coordinate is out of range") from None
    elif isinstance(value, str):
        try:
            v = float(value.strip())
        except ValueError:
            raise InputFileError(name, f"{where}: {value.strip()!r} is not a number") from None
    else:
        raise InputFileError(name, f"{where}: expected a number, got {value!r}")
    if not math.isfinite(v):
        raise InputFileError(name, f"{where}: coordinate is NaN or infinite")
    return v


def _convert(arr_rows: list[list[float]], source_cs: str, out_cs: str) -> list[list[float]]:
    if source_cs == out_cs:
        return arr_rows
    return [[-r[0], -r[1], r[2]] for r in arr_rows]


def _norm_cs(name: str, where: str, value: object) -> str:
    v = str(value).strip().upper()
    if v in ("RAS", "0"):
        return "RAS"
    if v in ("LPS", "1"):
        return "LPS"
    raise InputFileError(name, f"{where}: unsupported coordinate system {value!r} (expected LPS or RAS)")


# ---------------------------------------------------------------------- Slicer .mrk.json
def _read_mrk_json(name: str, text: str, out_cs: CoordinateSystem) -> PointSet:
    doc = _load_json(name, text)
    if not isinstance(doc, dict) or not isinstance(doc.get("markups"), list):
        raise InputFileError(name, "not a Slicer markups file (no 'markups' list)")
    rows: list[list[float]] = []
    labels: list[str | None] = []
    source: str | None = None
    for mi, markup in enumerate(doc["markups"]):
        where_m = f"markups[{mi}]"
        if not isinstance(markup, dict):
            raise InputFileError(name, f"{where_m}: expected an object")
        cs = _norm_cs(name, f"{where_m}.coordinateSystem", markup.get("coordinateSystem", "LPS"))
        units = markup.get("coordinateUnits", "mm")
        if units != "mm":
            raise InputFileError(name, f"{where_m}.coordinateUnits: {units!r} is not supported (need 'mm')")
        if source is None:
            source = cs
        elif source != cs:
            source = "mixed"
        cps = markup.get("controlPoints", [])
        if not isinstance(cps, list):
            raise InputFileError(name, f"{where_m}.controlPoints: expected a list")
        these: list[list[float]] = []
        for ci, cp in enumerate(cps):
            where = f"{where_m}.controlPoints[{ci}]"
            if not isinstance(cp, dict):
                raise InputFileError(name, f"{where}: expected an object")
            status = cp.get("positionStatus", "defined")
            if status != "defined":
                raise InputFileError(name, f"{where}: position is {status!r}, not 'defined'")
            pos = cp.get("position")
            if not isinstance(pos, list) or len(pos) != 3:
                raise InputFileError(name, f"{where}.position: expected [x, y, z]")
            these.append([_to_float(name, f"{where}.position", v) for v in pos])
            lab = cp.get("label")
            labels.append(str(lab) if lab not in (None, "") else None)
        rows.extend(_convert(these, cs, out_cs))
    return _finish(name, rows, labels, source, out_cs)


# ---------------------------------------------------------------------- Slicer .fcsv
def _read_fcsv(name: str, text: str, out_cs: CoordinateSystem) -> PointSet:
    columns = ["id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock", "label", "desc"]
    cs = "RAS"
    rows: list[list[float]] = []
    labels: list[str | None] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            body = line[1:].strip()
            key, sep, value = body.partition("=")
            if not sep:
                continue
            key = key.strip().lower()
            if key == "coordinatesystem":
                cs = _norm_cs(name, f"line {lineno}", value)
            elif key == "columns":
                columns = [c.strip().lower() for c in value.split(",")]
            continue
        cells = [c.strip() for c in line.split(",")]
        try:
            ix, iy, iz = columns.index("x"), columns.index("y"), columns.index("z")
        except ValueError:
            raise InputFileError(name, "'# columns =' header has no x, y, z columns") from None
        if len(cells) <= max(ix, iy, iz):
            raise InputFileError(name, f"line {lineno}: {len(cells)} fields, expected {len(columns)}")
        rows.append([_to_float(name, f"line {lineno}", cells[i]) for i in (ix, iy, iz)])
        label = None
        if "label" in columns and columns.index("label") < len(cells):
            label = cells[columns.index("label")] or None
        labels.append(label)
    return _finish(name, _convert(rows, cs, out_cs), labels, cs, out_cs)


# ---------------------------------------------------------------------- plain JSON
def _load_json(name: str, text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(name, f"bad JSON (line {exc.lineno}, col {exc.colno}): {exc.msg}") from None
    except ValueError as exc:  # e.g. an integer literal beyond Python's 4300-digit limit
        raise InputFileError(name, f"unusable JSON: {exc}") from None
    except RecursionError:
        raise InputFileError(name, "unusable JSON: nested too deeply") from None


def _read_json(name: str, text: str, out_cs: CoordinateSystem) -> PointSet:
    doc = _load_json(name, text)
    if isinstance(doc, dict):
        if "markups" in doc:  # a Slicer markups file saved without the .mrk.json suffix
            return _read_mrk_json(name, text, out_cs)
        if "points" not in doc:
            raise InputFileError(name, "JSON object has no 'points' key")
        doc = doc["points"]
    if not isinstance(doc, list):
        raise InputFileError(name, "expected a JSON list of points, or {\"points\": [...]}")
    rows: list[list[float]] = []
    labels: list[str | None] = []
    for i, item in enumerate(doc):
        where = f"point {i + 1}"
        if isinstance(item, list):
            if len(item) != 3:
                raise InputFileError(name, f"{where}: expected [x, y, z], got {len(item)} values")
            rows.append([_to_float(name, where, v) for v in item])
            labels.append(None)
        elif isinstance(item, dict):
            if "position" in item:
                pos = item["position"]
                if not isinstance(pos, list) or len(pos) != 3:
                    raise InputFileError(name, f"{where}.position: expected [x, y, z]")
                rows.append([_to_float(name, where, v) for v in pos])
            else:
                missing = [k for k in ("x", "y", "z") if k not in item]
                if missing:
                    raise InputFileError(name, f"{where}: missing {', '.join(missing)}")
                rows.append([_to_float(name, f"{where}.{k}", item[k]) for k in ("x", "y", "z")])
            label = next((item[k] for k in _LABEL_NAMES if k in item), None)
            labels.append(str(label) if label not in (None, "") else None)
        else:
            raise InputFileError(name, f"{where}: expected [x, y, z] or an object with x, y, z")
    return _finish(name, rows, labels)


# ---------------------------------------------------------------------- delimited text
_UNIT_SUFFIX = re.compile(r"[\s_]*(\(mm\)|\[mm\]|mm)$")


def _split(line: str) -> list[str]:
    for delim in (",", ";", "\t"):
        if delim in line:
            return [c.strip().strip('"') for c in line.split(delim)]
    return line.split()


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _read_delimited(name: str, text: str) -> PointSet:
    lines = [
        (n, raw.strip()) for n, raw in enumerate(text.splitlines(), start=1)
        if raw.strip() and not raw.strip().startswith("#")
    ]
    if not lines:
        raise InputFileError(name, "contains no points")
    first_no, first = lines[0]
    first_cells = _split(first)
    ix = iy = iz = -1
    ilabel: int | None = None
    data = lines
    if not all(_is_number(c) for c in first_cells) and sum(_is_number(c) for c in first_cells) < 3:
        header = [_UNIT_SUFFIX.sub("", c.lower()) for c in first_cells]
        if all(k in header for k in ("x", "y", "z")):
            ix, iy, iz = header.index("x"), header.index("y"), header.index("z")
            ilabel = next((header.index(k) for k in _LABEL_NAMES if k in header), None)
            data = lines[1:]
        elif len(first_cells) == 4 and all(_is_number(c) for c in first_cells[1:]):
            pass  # label,x,y,z without a header
        else:
            raise InputFileError(
                name, f"line {first_no}: header must name columns x, y, z (got {', '.join(first_cells)})"
            )
    rows: list[list[float]] = []
    labels: list[str | None] = []
    for lineno, line in data:
        cells = _split(line)
        if ix >= 0:
            if len(cells) <= max(ix, iy, iz):
                raise InputFileError(name, f"line {lineno}: {len(cells)} fields, fewer than the header's")
            xyz = [cells[ix], cells[iy], cells[iz]]
            label = cells[ilabel] if ilabel is not None and ilabel < len(cells) else None
        elif len(cells) == 3:
            xyz, label = cells, None
        elif len(cells) == 4 and not _is_number(cells[0]):
            xyz, label = cells[1:], cells[0]
        elif len(cells) == 4 and not _is_number(cells[3]):
            xyz, label = cells[:3], cells[3]
        else:
            raise InputFileError(
                name, f"line {lineno}: expected x,y,z or label,x,y,z (got {len(cells)} fields)"
            )
        rows.append([_to_float(name, f"line {lineno}", c) for c in xyz])
        labels.append(label or None)
    return _finish(name, rows, labels)
