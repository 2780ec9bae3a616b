"""Read recorded respiratory motion: skin points, 1-D surrogates and tumour traces (docs/traces.md).

Formats (``TraceFormat``; :func:`read_trace` detects them when ``format`` is None):

- ``points-csv`` — the project's CSV for a user's own skin-marker recordings: a header row
  ``time_s`` then, per recorded point, ``NAME_x_mm,NAME_y_mm,NAME_z_mm`` (NAME of
  ``[A-Za-z0-9_-]+``), positions in the image frame, mm. Where each point sits on the skin comes
  from the optional sidecar ``<file>.points.json`` = ``{"NAME": [x_mm, y_mm], ...}`` (image-frame
  x, y), which must name exactly the CSV's points.
- ``surrogate`` — 2 columns (whitespace or comma): time (s), amplitude (arbitrary units); the
  InterACT ``*_resp*.txt`` files.
- ``6dof`` — 7 columns: time (s), 3 translations (mm), 3 rotations (deg), as the InterACT 6-DoF
  tumour traces (IntERAct, "Selected Traces and Robot Coordinate System"): columns are IEC 61217
  x (+ patient's left), y (+ superior), z (+ anterior), rotations about x, y, z, anticlockwise
  positive looking along the axis. That is this project's image frame, so the columns map 1:1.
- ``paired`` — a directory holding one tumour file (7 columns) and one ``*resp*`` surrogate file;
  both are cut to their common time stamps. A tumour file with a single non-zero translation
  column and no rotation (the InterACT LIGHT SABR / LARK files: superior-inferior motion, which
  the source plays along its phantom's third axis) is superior-inferior motion: that column goes
  to image y. Otherwise its columns are read as ``6dof``.

Image frame (mm): x = patient's left, y = superior (cranial), z = anterior.

Auto-detection: a directory is ``paired``; a first line starting with ``time_s`` is
``points-csv``; a first data line of 2 numbers is ``surrogate``, of 7 numbers ``6dof``; anything
else is refused. Blank lines and lines starting with ``#`` are skipped in every format.

Every problem raises :class:`TraceError` (``"<path>:<line>: <problem>"``): malformed lines, empty
files, non-increasing time, NaN/inf, too short, unknown format, units that cannot be told, a
missing file. Nothing here logs, blocks on anything but file reads, or keeps files open.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray

from hil.errors import InputFileError

FloatArray = NDArray[np.float64]
TraceFormat = Literal["points-csv", "surrogate", "6dof", "paired"]
TRACE_FORMATS: tuple[TraceFormat, ...] = get_args(TraceFormat)

#: The sidecar naming where each recorded point of ``rec.csv`` sits on the skin: ``rec.csv.points.json``.
SIDECAR_SUFFIX = ".points.json"
#: Headerless files (surrogate, 6dof) carry time in seconds; a median step outside this range
#: (s) means the time column is in other units (ms, minutes) and the file is refused.
TIME_STEP_RANGE_S = (1e-4, 1.0)
#: Largest |translation| (mm) a tumour trace may hold; larger values mean cm/µm mix-ups or not a
#: tumour trace (tumours move up to a few cm, Keall et al. AAPM TG-76).
MAX_TRANSLATION_MM = 100.0
#: Largest |rotation| (deg) a 6-DoF tumour trace may hold.
MAX_ROTATION_DEG = 90.0

_SPLIT_ANY = re.compile(r"[,\s]+")
_COLUMN = re.compile(r"^(?P<name>[A-Za-z0-9_-]+)_(?P<axis>[xyz])(?:_(?P<unit>[A-Za-z]+))?$")
_AXES = ("x", "y", "z")
_IMAGE_AXES = "image frame: x = patient's left, y = superior, z = anterior"


class TraceError(InputFileError):
    """A trace file (or directory) cannot be read or holds doubtful data.

    The message is ``"<path>:<line>: <reason>"``, or ``"<path>: <reason>"`` when the problem is
    not about one line.

    Attributes:
        path: the file or directory, as the user named it.
        line: 1-based line number in ``path``, or None.
        reason: what is wrong, in plain words.
    """

    def __init__(self, path: str, reason: str, line: int | None = None) -> None:
        super().__init__(path, reason)
        self.line = line
        if line is not None:
            self.args = (f"{path}:{line}: {reason}",)


@dataclass(frozen=True)
class Trace:
    """One recorded trace, as read (arrays read-only, float64).

    Attributes:
        path: the file (directory for ``paired``) as given.
        format: which reader read it.
        time_s: (N,) strictly increasing, seconds as in the file (not shifted to 0).
        points_mm: points-csv: recorded skin point name -> (N, 3) image-frame mm; else ``{}``.
        point_places_mm: where each recorded point sits on the skin, image-frame (x, y) mm, from
            the sidecar; None without one.
        surrogate: (N,) respiratory surrogate, arbitrary units (surrogate, paired); else None.
        target_mm: (N, 3) internal target (tumour) displacement, image-frame mm (6dof, paired).
        target_rotation_deg: (N, 3) 6dof rotations about image x, y, z as recorded, deg; else None.
        units: how the columns were understood (``time``, ``position``, ``rotation``,
            ``surrogate``, ``axes``) plus notes (``note``, ``resampled``, the paired files).
    """

    path: str
    format: TraceFormat
    time_s: FloatArray
    points_mm: dict[str, FloatArray]
    point_places_mm: dict[str, tuple[float, float]] | None
    surrogate: FloatArray | None
    target_mm: FloatArray | None
    target_rotation_deg: FloatArray | None
    units: dict[str, str]

    @property
    def duration_s(self) -> float:
        """Last minus first time stamp, s."""
        return float(self.time_s[-1] - self.time_s[0])

    @property
    def rate_hz(self) -> float:
        """Sample rate: 1 / the median sample interval, Hz."""
        return float(1.0 / np.median(np.diff(self.time_s)))

    def gaps(self, factor: float = 1.5) -> list[tuple[float, float]]:
        """Intervals longer than ``factor`` x the median interval, as (start_s, length_s).

        Raises:
            ValueError: ``factor`` is not a finite number > 1.
        """
        if not math.isfinite(factor) or factor <= 1.0:
            raise ValueError(f"gap factor must be a finite number > 1, got {factor}")
        dt = np.diff(self.time_s)
        long = np.flatnonzero(dt > factor * float(np.median(dt)))
        return [(float(self.time_s[i]), float(dt[i])) for i in long]


# ---------------------------------------------------------------------------------------------
# Reading text


def _data_lines(path: str) -> list[tuple[int, str]]:
    """The file's non-blank, non-comment lines as (1-based line number, stripped text)."""
    p = Path(path)
    if not p.exists():
        raise TraceError(path, "no such file or directory")
    if p.is_dir():
        raise TraceError(path, "is a directory (only the paired format reads a directory)")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise TraceError(path, "not a text file (not UTF-8)") from None
    except OSError as exc:
        raise TraceError(path, f"cannot be read ({exc.strerror or exc})") from None
    out = [(i, s.strip()) for i, s in enumerate(text.splitlines(), start=1)]
    out = [(i, s) for i, s in out if s and not s.startswith("#")]
    if not out:
        raise TraceError(path, "empty file: no data rows")
    return out


def _numbers(path: str, lineno: int, fields: list[str], n_columns: int) -> list[float]:
    """Parse one row of ``n_columns`` finite numbers (TraceError naming the line otherwise)."""
    if len(fields) != n_columns:
        raise TraceError(path, f"expected {n_columns} columns, found {len(fields)}", lineno)
    values = []
    for col, text in enumerate(fields, start=1):
        try:
            v = float(text)
        except ValueError:
            raise TraceError(path, f"column {col}: not a number: {text!r}", lineno) from None
        if not math.isfinite(v):
            raise TraceError(path, f"column {col}: not a finite number: {text!r}", lineno)
        values.append(v)
    return values


def _table(path: str, rows: list[tuple[int, str]], n_columns: int, comma_only: bool) -> FloatArray:
    """(N, n_columns) numbers from ``rows`` (comma-separated, or whitespace and/or commas)."""
    data = []
    for lineno, text in rows:
        fields = [f.strip() for f in text.split(",")] if comma_only else _SPLIT_ANY.split(text)
        data.append(_numbers(path, lineno, fields, n_columns))
    return np.asarray(data, dtype=np.float64).reshape(len(rows), n_columns)


def _check_time(path: str, time_s: FloatArray, linenos: list[int]) -> None:
    """Strictly increasing time, else TraceError at the first offending line."""
    dt = np.diff(time_s)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        prev, now = float(time_s[i - 1]), float(time_s[i])
        what = "repeats" if now == prev else "goes back from"
        raise TraceError(path, f"time {now:g} s {what} the previous sample's {prev:g} s", linenos[i])


def _check_seconds(path: str, time_s: FloatArray) -> None:
    """Headerless formats: the time column must look like seconds (TIME_STEP_RANGE_S)."""
    step = float(np.median(np.diff(time_s)))
    lo, hi = TIME_STEP_RANGE_S
    if not lo <= step <= hi:
        raise TraceError(
            path, f"median time step {step:g} is not {lo:g}-{hi:g} s: the time column's unit cannot "
            "be told (expected seconds)",
        )


def _check_length(path: str, time_s: FloatArray, min_duration_s: float, min_samples: int) -> None:
    n = int(time_s.size)
    if n < max(min_samples, 2):
        raise TraceError(path, f"too short: {n} samples (at least {max(min_samples, 2)} needed)")
    duration = float(time_s[-1] - time_s[0])
    if duration < min_duration_s:
        raise TraceError(path, f"too short: {duration:g} s (at least {min_duration_s:g} s needed)")


def _frozen(a: FloatArray) -> FloatArray:
    out = np.array(a, dtype=np.float64, copy=True)
    out.flags.writeable = False
    return out


# ---------------------------------------------------------------------------------------------
# Formats


def _header_points(path: str, lineno: int, header: str) -> tuple[list[str], list[tuple[str, int]]]:
    """Parse a points-csv header: the point names in order, and per column (name, axis index)."""
    cols = [c.strip() for c in header.split(",")]
    if cols[0] != "time_s":
        raise TraceError(path, f"first column is {cols[0]!r}: the time unit cannot be told (expected "
                         "'time_s', seconds)", lineno)
    names: list[str] = []
    layout: list[tuple[str, int]] = []
    for col in cols[1:]:
        m = _COLUMN.match(col)
        if m is None:
            raise TraceError(path, f"column {col!r} is not NAME_x_mm, NAME_y_mm or NAME_z_mm", lineno)
        name, axis, unit = m["name"], _AXES.index(m["axis"]), m["unit"]
        if unit is None:
            raise TraceError(path, f"column {col!r} has no unit: units cannot be told (expected "
                             f"{name}_{m['axis']}_mm)", lineno)
        if unit != "mm":
            raise TraceError(path, f"column {col!r}: unit {unit!r} is not supported (positions are _mm)",
                             lineno)
        if (name, axis) in layout:
            raise TraceError(path, f"column {col!r} appears twice", lineno)
        if name not in names:
            names.append(name)
        layout.append((name, axis))
    if not names:
        raise TraceError(path, "no point columns after time_s (expected NAME_x_mm,NAME_y_mm,NAME_z_mm)",
                         lineno)
    for name in names:
        missing = [f"{name}_{a}_mm" for i, a in enumerate(_AXES) if (name, i) not in layout]
        if missing:
            raise TraceError(path, f"point {name!r} lacks column(s) {', '.join(missing)}", lineno)
    return names, layout


def _read_sidecar(path: str, names: list[str]) -> dict[str, tuple[float, float]] | None:
    """The ``<path>.points.json`` sidecar, checked against the CSV's point ``names``; None if absent."""
    side = path + SIDECAR_SUFFIX
    if not Path(side).is_file():
        return None
    try:
        raw = json.loads(Path(side).read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise TraceError(side, f"not valid JSON: {exc.msg}", exc.lineno) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TraceError(side, f"cannot be read ({exc})") from None
    if not isinstance(raw, dict):
        raise TraceError(side, 'expected an object {"NAME": [x_mm, y_mm], ...}')
    places: dict[str, tuple[float, float]] = {}
    for name, xy in raw.items():
        if name not in names:
            raise TraceError(side, f"names point {name!r}, which {path} does not record")
        ok = isinstance(xy, list) and len(xy) == 2 and all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in xy
        )
        if not ok:
            raise TraceError(side, f"point {name!r}: expected [x_mm, y_mm] (two finite numbers), got {xy!r}")
        places[name] = (float(xy[0]), float(xy[1]))
    missing = [n for n in names if n not in places]
    if missing:
        raise TraceError(side, f"lacks the place of point(s) {', '.join(map(repr, missing))} of {path}")
    return places


def _read_points_csv(path: str) -> Trace:
    lines = _data_lines(path)
    names, layout = _header_points(path, lines[0][0], lines[0][1])
    rows = lines[1:]
    if not rows:
        raise TraceError(path, "no data rows after the header")
    table = _table(path, rows, 1 + len(layout), comma_only=True)
    time_s = table[:, 0]
    _check_time(path, time_s, [n for n, _ in rows])
    points = {name: np.empty((len(rows), 3)) for name in names}
    for col, (name, axis) in enumerate(layout, start=1):
        points[name][:, axis] = table[:, col]
    units = {"time": "s", "position": "mm", "axes": _IMAGE_AXES}
    places = _read_sidecar(path, names)
    if places is not None:
        units["places"] = f"sidecar {Path(path + SIDECAR_SUFFIX).name}"
    return Trace(path, "points-csv", _frozen(time_s), {k: _frozen(v) for k, v in points.items()},
                 places, None, None, None, units)


def _read_columns(path: str, n_columns: int) -> tuple[FloatArray, FloatArray, list[int]]:
    """A headerless numeric file: (time_s, the other columns, line numbers), time checked."""
    rows = _data_lines(path)
    table = _table(path, rows, n_columns, comma_only=False)
    linenos = [n for n, _ in rows]
    _check_time(path, table[:, 0], linenos)
    if table.shape[0] >= 2:
        _check_seconds(path, table[:, 0])
    return table[:, 0], table[:, 1:], linenos


def _check_pose_units(path: str, pose: FloatArray, linenos: list[int]) -> None:
    """Translations within MAX_TRANSLATION_MM and rotations within MAX_ROTATION_DEG (else
    TraceError at the first line beyond)."""
    for cols, limit, what in ((slice(0, 3), MAX_TRANSLATION_MM, "translation"),
                              (slice(3, 6), MAX_ROTATION_DEG, "rotation")):
        over = np.argwhere(np.abs(pose[:, cols]) > limit)
        if over.size:
            row, col = int(over[0][0]), int(over[0][1])
            unit = "mm" if what == "translation" else "deg"
            raise TraceError(
                path, f"{what} {float(pose[row, cols][col]):g} exceeds {limit:g} {unit}: "
                f"units cannot be told (expected {unit})", linenos[row],
            )


def _read_6dof(path: str) -> Trace:
    time_s, pose, linenos = _read_columns(path, 7)
    _check_pose_units(path, pose, linenos)
    units = {"time": "s", "position": "mm", "rotation": "deg",
             "axes": "IEC 61217 columns x, y, z = " + _IMAGE_AXES}
    return Trace(path, "6dof", _frozen(time_s), {}, None, None,
                 _frozen(pose[:, :3]), _frozen(pose[:, 3:]), units)


def _read_surrogate(path: str) -> Trace:
    time_s, values, _ = _read_columns(path, 2)
    return Trace(path, "surrogate", _frozen(time_s), {}, None, _frozen(values[:, 0]), None, None,
                 {"time": "s", "surrogate": "arbitrary"})


def _paired_files(path: str) -> tuple[str, str]:
    """(tumour file, surrogate file) of a paired directory."""
    p = Path(path)
    if not p.exists():
        raise TraceError(path, "no such file or directory")
    if not p.is_dir():
        raise TraceError(path, "the paired format reads a directory (one tumour file, one *resp* file)")
    files = sorted(f for f in p.iterdir() if f.is_file() and not f.name.startswith("."))
    resp = [f for f in files if "resp" in f.name.lower()]
    tumour = [f for f in files if "resp" not in f.name.lower()]
    if len(resp) != 1 or len(tumour) != 1:
        raise TraceError(
            path, f"a paired directory holds one tumour file and one *resp* file; found "
            f"{len(tumour)} tumour file(s) and {len(resp)} *resp* file(s)",
        )
    return str(tumour[0]), str(resp[0])


def _common_span(
    path: str, tumour: tuple[str, FloatArray, list[int]], resp: tuple[str, FloatArray, list[int]]
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], str | None]:
    """Masks selecting the shared time stamps of both files, and a note of what was dropped."""
    (t_name, t_t, t_lines), (r_name, r_t, _) = tumour, resp
    start, end = max(t_t[0], r_t[0]), min(t_t[-1], r_t[-1])
    t_in = (t_t >= start) & (t_t <= end)
    r_in = (r_t >= start) & (r_t <= end)
    a, b = t_t[t_in], r_t[r_in]
    if a.size != b.size or not np.allclose(a, b, rtol=0.0, atol=1e-6):
        k = next((k for k in range(min(a.size, b.size)) if abs(a[k] - b[k]) > 1e-6), min(a.size, b.size))
        where = "the end"
        if k < a.size:
            where = f"{Path(t_name).name} line {t_lines[int(np.flatnonzero(t_in)[k])]}"
        raise TraceError(path, f"{Path(t_name).name} and {Path(r_name).name} do not share time stamps "
                         f"over their common span {start:g}-{end:g} s (first difference at {where})")
    dropped = [f"{int((~m).sum())} sample(s) of {Path(n).name}" for n, m in ((t_name, t_in), (r_name, r_in))
               if (~m).any()]
    note = None
    if dropped:
        note = f"common span {start:g}-{end:g} s: dropped " + " and ".join(dropped)
    return t_in, r_in, note


def _read_paired(path: str) -> Trace:
    t_file, r_file = _paired_files(path)
    t_time, pose, t_lines = _read_columns(t_file, 7)
    _check_pose_units(t_file, pose, t_lines)
    r_time, r_values, r_lines = _read_columns(r_file, 2)
    t_in, r_in, note = _common_span(path, (t_file, t_time, t_lines), (r_file, r_time, r_lines))
    moving = [c for c in range(3) if np.any(pose[:, c] != 0.0)]
    rotating = bool(np.any(pose[:, 3:] != 0.0))
    units = {"time": "s", "position": "mm", "surrogate": "arbitrary",
             "tumour_file": Path(t_file).name, "surrogate_file": Path(r_file).name}
    rotation: FloatArray | None
    if len(moving) == 1 and not rotating:
        target = np.zeros((int(t_in.sum()), 3))
        target[:, 1] = pose[t_in, moving[0]]
        rotation = None
        units["axes"] = (f"superior-inferior motion in column {moving[0] + 2} of 7 -> image y "
                         f"(+ superior); {_IMAGE_AXES}")
    else:
        target, rotation = pose[t_in, :3], _frozen(pose[t_in, 3:])
        units["rotation"] = "deg"
        units["axes"] = "IEC 61217 columns x, y, z = " + _IMAGE_AXES
    if note is not None:
        units["note"] = note
    return Trace(path, "paired", _frozen(t_time[t_in]), {}, None, _frozen(r_values[r_in, 0]),
                 _frozen(target), rotation, units)


def detect_format(path: str | os.PathLike[str]) -> TraceFormat:
    """The format of ``path`` by the rules in the module doc. Raises TraceError (unknown format)."""
    p = str(path)
    if Path(p).is_dir():
        return "paired"
    lineno, first = _data_lines(p)[0]
    if first.startswith("time_s"):
        return "points-csv"
    fields = _SPLIT_ANY.split(first)
    try:
        [float(f) for f in fields]
    except ValueError:
        raise TraceError(p, f"unknown format (first line {first[:60]!r} is neither a time_s header nor "
                         "numbers)", lineno) from None
    if len(fields) == 2:
        return "surrogate"
    if len(fields) == 7:
        return "6dof"
    raise TraceError(p, f"unknown format ({len(fields)} numeric columns; expected a time_s header, 2 "
                     "columns (surrogate) or 7 (6dof))", lineno)


_READERS = {"points-csv": _read_points_csv, "surrogate": _read_surrogate, "6dof": _read_6dof,
            "paired": _read_paired}


def read_trace(
    path: str | os.PathLike[str], format: TraceFormat | None = None, *,
    min_duration_s: float = 5.0, min_samples: int = 10,
) -> Trace:
    """Read a trace file (a directory for ``paired``); ``format=None`` detects it (module doc).

    Args:
        path: the file or directory.
        format: one of TRACE_FORMATS, or None to detect.
        min_duration_s: refuse traces shorter than this (last minus first time stamp), s.
        min_samples: refuse traces with fewer samples.

    Returns:
        The trace, arrays read-only, time in seconds as in the file.

    Raises:
        TraceError: any problem, naming the file, the line where there is one, and what is wrong.
    """
    p = str(path)
    if format is None:
        format = detect_format(p)
    elif format not in TRACE_FORMATS:
        raise TraceError(p, f"unknown format {format!r} (one of {', '.join(TRACE_FORMATS)})")
    trace = _READERS[format](p)
    _check_length(p, trace.time_s, min_duration_s, min_samples)
    return trace


def resample(trace: Trace, rate_hz: float, *, min_samples: int = 10) -> Trace:
    """The trace on a uniform grid ``time_s[0] + k / rate_hz`` up to its last time stamp.

    Method: linear interpolation (``numpy.interp``) of every series — each point's x, y, z, the
    surrogate, the target's translations and rotations — between the two recorded samples around
    each grid time; no smoothing, no extrapolation. ``units["resampled"]`` records it.

    Raises:
        TraceError: ``rate_hz`` is not a finite number > 0, or the grid holds fewer than
            ``min_samples`` samples.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise TraceError(trace.path, f"resampling rate must be a finite number of Hz > 0, got {rate_hz!r}")
    n = math.floor(trace.duration_s * rate_hz + 1e-9) + 1
    if n < min_samples:
        raise TraceError(trace.path, f"resampling to {rate_hz:g} Hz leaves {n} samples over "
                         f"{trace.duration_s:g} s (at least {min_samples} needed)")
    t_old = trace.time_s
    t_new = t_old[0] + np.arange(n, dtype=np.float64) / rate_hz

    def interp(a: FloatArray | None) -> FloatArray | None:
        if a is None:
            return None
        if a.ndim == 1:
            return _frozen(np.interp(t_new, t_old, a))
        return _frozen(np.column_stack([np.interp(t_new, t_old, a[:, j]) for j in range(a.shape[1])]))

    points = {k: v for k, v in ((k, interp(v)) for k, v in trace.points_mm.items()) if v is not None}
    units = dict(trace.units)
    units["resampled"] = f"linear interpolation to {rate_hz:g} Hz from {trace.rate_hz:g} Hz"
    return replace(trace, time_s=_frozen(t_new), points_mm=points, surrogate=interp(trace.surrogate),
                   target_mm=interp(trace.target_mm), target_rotation_deg=interp(trace.target_rotation_deg),
                   units=units)


def principal_amplitude(positions: FloatArray) -> float:
    """Peak-to-peak motion along the first principal axis of (N, 3) ``positions``: max minus min
    of the centred positions projected on the right singular vector of the largest singular value
    (principal component analysis). Same unit as ``positions``; 0 for a point that never moves."""
    centred = positions - positions.mean(axis=0)
    if not np.any(centred):
        return 0.0
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    proj = centred @ vt[0]
    return float(proj.max() - proj.min())


def _r6(x: float) -> float:
    return round(float(x), 6)


def trace_summary(trace: Trace) -> dict[str, object]:
    """What ``hil traces check --json`` prints (docs/traces.md lists every field).

    ``points`` is the number of recorded skin points, or 1 for a surrogate or tumour trace;
    ``amplitude_mm`` is per point the peak-to-peak motion along its principal direction
    (:func:`principal_amplitude`); for a surrogate it is the surrogate's peak to peak in its own
    (arbitrary) units and ``amplitude_units`` says so.
    """
    if trace.points_mm:
        names = list(trace.points_mm)
        amplitude = [principal_amplitude(trace.points_mm[n]) for n in names]
        amp_units = "mm"
    elif trace.target_mm is not None:
        names, amplitude, amp_units = ["target"], [principal_amplitude(trace.target_mm)], "mm"
    else:
        assert trace.surrogate is not None
        names = ["surrogate"]
        amplitude = [float(np.ptp(trace.surrogate))]
        amp_units = "arbitrary (surrogate units)"
    rot = trace.target_rotation_deg
    return {
        "path": trace.path,
        "format": trace.format,
        "samples": int(trace.time_s.size),
        "time_start_s": _r6(trace.time_s[0]),
        "duration_s": _r6(trace.duration_s),
        "rate_hz": _r6(trace.rate_hz),
        "points": len(names),
        "point_names": names,
        "amplitude_mm": [_r6(a) for a in amplitude],
        "amplitude_units": amp_units,
        "surrogate_amplitude": None if trace.surrogate is None else _r6(float(np.ptp(trace.surrogate))),
        "rotation_amplitude_deg": None if rot is None else [_r6(v) for v in np.ptp(rot, axis=0)],
        "point_places_mm": None if trace.point_places_mm is None
        else {k: [_r6(v[0]), _r6(v[1])] for k, v in trace.point_places_mm.items()},
        "gaps": [{"start_s": _r6(s), "length_s": _r6(n)} for s, n in trace.gaps()],
        "units": dict(trace.units),
    }
