"""``hil tracker-calibrate`` — pivot calibration of a stylus and tracker -> optical registration.

Two ways in:

* ``--poses FILE``: recorded poses (format in :mod:`hil.tracking.session`), no device needed.
* ``--setup SETUP.toml``: the setup's ``[tracker]`` is opened and the user is walked through a
  pivot calibration and one stylus touch per marker of ``--markers FILE`` (the markers'
  positions in the optical frame, any point-file format of ``hil register``). ``--record FILE``
  keeps the raw poses so the calibration can be recomputed with ``--poses``.

Writes the calibration JSON to ``--out`` (default with ``--setup``: ``tracker_calibration.json``
next to the setup file) and prints a JSON summary on stdout: the tip offset and its pivot RMS,
the registration's FRE and per-marker residuals. Prompts and progress go to stderr. Bad input
exits 2 with one line naming the file and the problem.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from drivers.interfaces.tracker import PoseTracker
from hil.clock import MonotonicClock
from hil.errors import ConfigError, InputFileError
from hil.io.points import read_points
from hil.tracking.session import (
    RecordedSession,
    calibrate,
    collect_interactive,
    load_recorded_session,
    save_json,
)


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "tracker-calibrate", help="pivot-calibrate a stylus and register the EM tracker to the cameras",
        description=__doc__.split("\n\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--poses", type=Path, help="recorded poses (JSON) instead of a live tracker")
    src.add_argument("--setup", type=Path, help="setup TOML whose [tracker] to open (interactive)")
    p.add_argument("--markers", type=Path, help="marker positions in the optical frame (point file)")
    p.add_argument("--stylus", default="stylus", help="sensor name of the stylus (default: stylus)")
    p.add_argument("--reference", help="sensor fixed to the pivot base (poses taken relative to it)")
    p.add_argument("--pivot-samples", type=int, default=200, help="samples while swivelling (default 200)")
    p.add_argument("--touch-samples", type=int, default=20, help="samples per marker touch (default 20)")
    p.add_argument("--settle-samples", type=int, default=5,
                   help="samples dropped after each Enter while the hand settles (default 5)")
    p.add_argument("--max-touch-spread-mm", type=float, default=1.0,
                   help="refuse a touch whose tip samples spread more, RMS (default 1.0)")
    p.add_argument("--out", type=Path, help="calibration JSON to write")
    p.add_argument("--record", type=Path, help="interactive: also save the raw poses here")
    p.set_defaults(func=run)


def _interactive(args: argparse.Namespace, labels: list[str]) -> RecordedSession:
    from hil.config import load_setup
    from plugins.manager import default_registry
    from plugins.registry import DriverContext

    setup = load_setup(args.setup)
    if setup.tracker is None:
        raise ConfigError(str(args.setup), ["tracker: the setup has no [tracker] section"])
    info = default_registry().get("tracker", str(setup.tracker.driver))
    clock = MonotonicClock()
    ctx = DriverContext(role="tracker", clock=clock, limits=setup.safety.motion_limits(),
                        config_dir=setup.config_dir)
    tracker = info.factory(setup.tracker, ctx)
    if not isinstance(tracker, PoseTracker):
        raise ConfigError(str(args.setup), [f"tracker.driver: {info.name} did not build a tracker"])

    def ask(message: str) -> None:
        print(message, file=sys.stderr, flush=True)
        sys.stdin.readline()

    def say(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    tracker.open()
    try:
        return collect_interactive(tracker, clock, stylus=args.stylus, labels=labels, ask=ask, say=say,
                                   reference=args.reference, pivot_samples=args.pivot_samples,
                                   touch_samples=args.touch_samples,
                                   settle_samples=args.settle_samples)
    finally:
        tracker.close()


def run(args: argparse.Namespace) -> int:
    optical = None
    labels: list[str] = []
    if args.markers is not None:
        points = read_points(args.markers)
        optical = np.asarray(points.points_mm, dtype=np.float64)
        labels = list(points.labels)
    if args.poses is not None:
        session = load_recorded_session(args.poses)
        out = args.out
        if out is None:
            raise InputFileError(str(args.poses), "give --out for the calibration file")
    else:
        if args.markers is None:
            raise InputFileError(str(args.setup),
                                 "interactive calibration needs --markers (optical positions)")
        out = args.out or args.setup.parent / "tracker_calibration.json"
        session = _interactive(args, labels)
        if args.record is not None:
            save_json(args.record, session.to_json())
    if optical is not None and len(session.touches) != optical.shape[0]:
        raise InputFileError(str(args.markers),
                             f"{optical.shape[0]} markers for {len(session.touches)} touches")
    result = calibrate(session, optical, max_touch_spread_mm=args.max_touch_spread_mm)
    doc = result.to_json()
    save_json(out, doc)
    summary: dict[str, Any] = {"out": str(out), "stylus": result.stylus, "pivot": doc["pivot"]}
    if result.registration is not None:
        reg = result.registration
        summary["registration"] = {
            "fre_rms_mm": reg.fre_rms_mm,
            "n_markers": len(reg.labels),
            "residuals_mm": {lab: float(r) for lab, r in zip(reg.labels, reg.residuals_mm, strict=True)},
            "T_optical_from_tracker": reg.T_optical_from_tracker.as_matrix().tolist(),
        }
    print(json.dumps(summary, indent=2))
    return 0
