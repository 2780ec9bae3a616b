"""``hil traces check FILE [--format F] [--json]`` — read a respiration trace and say what was read.

Prints the format, sample count, duration, rate, the recorded points (skin points of a
points-csv; 1 for a surrogate or a tumour trace), each point's peak-to-peak amplitude along its
principal direction of motion, gaps, and the units as understood (docs/traces.md). ``--json``
prints :func:`hil.io.traces.trace_summary` as one JSON object. A bad file exits 2 with one line
naming the file, the line and the problem.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hil.io.traces import TRACE_FORMATS, read_trace, trace_summary
from hil.log import get_logger

_log = get_logger(__name__)

#: Logged once per checked trace (fields: path, format, samples, duration_s, rate_hz, points, gaps).
EV_TRACE_CHECKED = "trace_checked"


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "traces",
        help="respiration trace files: check what a trace holds (docs/traces.md)",
        description="Respiration trace files (points-csv, surrogate, 6dof, paired): docs/traces.md.",
    )
    tsub = p.add_subparsers(dest="traces_command", metavar="SUBCOMMAND", required=True)
    c = tsub.add_parser(
        "check",
        help="read a trace and print what was read",
        description=(
            "Read FILE (a directory for the paired format) and print its format, samples, duration, "
            "rate, recorded points, peak-to-peak amplitude per point along its principal direction, "
            "gaps and units as understood. Bad input: one line naming file and line, exit 2."
        ),
    )
    c.add_argument("file", metavar="FILE", help="trace file, or a directory holding a paired trace")
    c.add_argument("--format", choices=TRACE_FORMATS, default=None,
                   help="the file's format (default: detected, docs/traces.md)")
    c.add_argument("--json", action="store_true", help="print one JSON object")
    c.set_defaults(func=run_check)


def format_text(summary: dict[str, Any]) -> str:
    """The summary as a short human-readable table (one ``key  value`` row per line)."""
    rows: list[tuple[str, str]] = [
        ("file", str(summary["path"])),
        ("format", str(summary["format"])),
        ("samples", str(summary["samples"])),
        ("duration_s", f"{summary['duration_s']:g} (from {summary['time_start_s']:g} s)"),
        ("rate_hz", f"{summary['rate_hz']:g}"),
        ("points", str(summary["points"])),
    ]
    unit = "mm" if summary["amplitude_units"] == "mm" else "(surrogate units, arbitrary)"
    places = summary["point_places_mm"] or {}
    for i, (name, amp) in enumerate(zip(summary["point_names"], summary["amplitude_mm"], strict=True)):
        where = f"  at skin x, y = {places[name][0]:g}, {places[name][1]:g} mm" if name in places else ""
        rows.append(("amplitude" if i == 0 else "", f"{name}: {amp:.3f} {unit} peak to peak{where}"))
    if summary["surrogate_amplitude"] is not None and summary["format"] == "paired":
        rows.append(("surrogate", f"{summary['surrogate_amplitude']:.3f} peak to peak (arbitrary units)"))
    if summary["rotation_amplitude_deg"] is not None:
        rx, ry, rz = summary["rotation_amplitude_deg"]
        rows.append(("rotation", f"{rx:.3f}, {ry:.3f}, {rz:.3f} deg peak to peak about x, y, z"))
    gaps = summary["gaps"]
    rows.append(("gaps", "none" if not gaps else
                 ", ".join(f"{g['length_s']:g} s at {g['start_s']:g} s" for g in gaps)))
    for i, (key, value) in enumerate(summary["units"].items()):
        rows.append(("units" if i == 0 else "", f"{key}: {value}"))
    return "".join(f"{k:<11} {v}\n" for k, v in rows)


def run_check(args: argparse.Namespace) -> int:
    trace = read_trace(args.file, args.format)
    summary = trace_summary(trace)
    _log.info(EV_TRACE_CHECKED, path=summary["path"], format=summary["format"],
              samples=summary["samples"], duration_s=summary["duration_s"], rate_hz=summary["rate_hz"],
              points=summary["points"], gaps=len(trace.gaps()))
    if args.json:
        sys.stdout.write(json.dumps(summary) + "\n")
    else:
        sys.stdout.write(format_text(summary))
    return 0
