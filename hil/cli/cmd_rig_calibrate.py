"""``hil rig-calibrate CONFIG``: hand-eye (camera -> robot and TCP -> flange markers, from many
poses) and device time offsets, written as a rig calibration file that ``hil run`` uses through
``[calibration] rig`` (docs/rig-calibration.md).

Every move is confirmed by the operator on stdin (``y`` go, anything else aborts) unless
``--auto``. Exit code 0 when the file was written; a refusal or failure is one line on stderr,
exit code 2, the arm stopped and nothing written.

``hil rig-calibrate --samples FILE`` is the offline mode (no devices, no CONFIG): hand-eye from
recorded pose pairs or streams (:mod:`hil.rigcal.offline_run`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, TextIO

from hil.config import build_devices, load_setup
from hil.config.build import clock_for
from hil.errors import InputFileError
from hil.rigcal.collect import Confirm, auto_confirm
from hil.rigcal.offline import SETUPS
from hil.rigcal.offline_run import print_offline_text, run_offline
from hil.rigcal.runner import run_rig_calibration
from hil.rigcal.sample_readers import FORMATS


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "rig-calibrate", help="hand-eye from many robot poses + device time offsets -> rig calibration file",
        description="Move the arm through poses in a safe cone, solve camera->robot and TCP->flange markers "
                    "jointly (per-pose residuals, outlier rejection, held-out validation), then a short "
                    "sinusoidal motion for the camera/robot/tracker time offsets; write the rig calibration "
                    "file (docs/rig-calibration.md) that [calibration] rig points hil run at.")
    p.add_argument("config", nargs="?", help="setup TOML (live mode; not with --samples)")
    p.add_argument("--out", help="rig calibration file to write (default: calibration/<config>_rig.json "
                                 "next to the config); with --samples, the hand-eye result file "
                                 "(default: none written)")
    off = p.add_argument_group("offline, from recorded samples (docs/rig-calibration.md)")
    off.add_argument("--samples", metavar="FILE", help="solve from recorded pose pairs or streams: no "
                                                       "devices, no CONFIG")
    off.add_argument("--setup", choices=SETUPS, help="camera fixed (eye-to-hand) or on the flange "
                                                     "(eye-in-hand); default eye-in-hand for eth, "
                                                     "else eye-to-hand")
    off.add_argument("--format", choices=FORMATS, help="samples format (default: from the file name "
                                                       "and content)")
    p.add_argument("--auto", action="store_true", help="confirm every move automatically (simulation)")
    part = p.add_mutually_exclusive_group()
    part.add_argument("--temporal", action="store_true",
                      help="time offsets only (keeps the hand-eye part of an existing --out file)")
    part.add_argument("--no-temporal", action="store_true", help="hand-eye only")
    p.add_argument("--poses", type=int, help="override [rig_calibration] poses")
    p.add_argument("--seed", type=int, help="override [simulation] seed")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.set_defaults(func=run)


class StdinConfirm:
    """Asks on ``out`` and reads one answer line from ``inp``: ``y`` goes on, anything else aborts."""

    def __init__(self, inp: TextIO | None = None, out: TextIO | None = None) -> None:
        self.inp, self.out = inp, out

    def __call__(self, prompt: str) -> bool:
        out = self.out or sys.stderr
        out.write(f"{prompt} [y]es / [a]bort: ")
        out.flush()
        return (self.inp or sys.stdin).readline().strip().lower().startswith("y")


def default_out(config_path: Path) -> Path:
    return config_path.resolve().parent / "calibration" / f"{config_path.stem}_rig.json"


def _fmt(x: float | None, unit: str) -> str:
    return "n/a" if x is None else f"{x:.3f} {unit}"


def print_text(s: dict[str, Any], out: TextIO) -> None:
    out.write(f"rig calibration  {s['rig_calibration']}\n")
    if s["poses"]:
        out.write(f"poses            {s['poses']} ({s['poses_used']} fitted, "
                  f"outliers {s['outliers'] or 'none'})\n")
        out.write(f"residual         {_fmt(s['residual_mm_rms'], 'mm')} RMS, "
                  f"{_fmt(s['residual_deg_rms'], 'deg')} RMS\n")
        out.write(f"validation       {_fmt(s['validation_mm_rms'], 'mm')} RMS on held-out poses\n")
        if s.get("optical_correction_mm") is not None:
            out.write(f"optical corr.    moves the markers by up to {s['optical_correction_mm']:.3f} mm "
                      "(the stereo calibration's error, undone in every located point)\n")
        for p in s["per_pose"]:
            out.write(f"  pose {p['index']:3d}  {p['residual_mm']:.3f} mm  {p['residual_deg']:.3f} deg  "
                      f"{p['role']}\n")
    for dev, off in s["time_offset_ms"].items():
        out.write(f"time offset      {dev:<8} {off:8.2f} ms +- {s['time_offset_sigma_ms'][dev]:.2f} ms\n")
    if "truth_layout_error_mm_rms" in s:
        out.write(f"truth: layout    {s['truth_layout_error_mm_rms']:.3f} mm RMS from the true layout\n")
    for dev, e in s.get("truth_time_offset_error_ms", {}).items():
        out.write(f"truth: offset    {dev:<8} {e:+.2f} ms from the true offset\n")


_LIVE_ONLY = ("auto", "temporal", "no_temporal", "poses", "seed")


def run(args: argparse.Namespace) -> int:
    if args.samples is not None:
        return run_samples(args)
    if args.config is None:
        raise InputFileError("CONFIG", "give a setup TOML (live) or --samples FILE (offline)")
    if args.setup is not None or args.format is not None:
        raise InputFileError("--setup/--format", "only with --samples FILE")
    config_path = Path(args.config)
    setup = load_setup(config_path)
    if args.seed is not None:
        if args.seed < 0:
            raise InputFileError("--seed", f"must be >= 0, got {args.seed}")
        sim = setup.simulation.model_copy(update={"seed": args.seed})
        setup = setup.model_copy(update={"simulation": sim})
    if args.poses is not None:
        rc = setup.rig_calibration
        if args.poses < rc.min_poses:
            raise InputFileError("--poses", f"too few poses: {args.poses} (need >= {rc.min_poses}, "
                                            "[rig_calibration] min_poses)")
        setup = setup.model_copy(update={"rig_calibration": rc.model_copy(update={"poses": args.poses})})
    out_path = Path(args.out) if args.out else default_out(config_path)
    clock = clock_for(setup)
    devices = build_devices(setup, clock)
    confirm: Confirm = auto_confirm if args.auto else StdinConfirm()
    outcome = run_rig_calibration(setup, config_path, devices, clock, confirm, out_path=out_path,
                                  hand_eye=not args.temporal, temporal=not args.no_temporal)
    if args.json:
        sys.stdout.write(json.dumps(outcome.summary, default=str) + "\n")
    else:
        print_text(outcome.summary, sys.stdout)
    return 0


def run_samples(args: argparse.Namespace) -> int:
    """The offline mode: nothing but the samples file is read, nothing moves."""
    if args.config is not None:
        raise InputFileError(args.config, "give either CONFIG (live) or --samples FILE (offline), not both")
    for name in _LIVE_ONLY:
        if getattr(args, name) not in (None, False):
            raise InputFileError("--" + name.replace("_", "-"), "only in the live mode (not with --samples)")
    s = run_offline(Path(args.samples), args.format, args.setup, Path(args.out) if args.out else None)
    if args.json:
        sys.stdout.write(json.dumps(s) + "\n")
    else:
        print_offline_text(s, sys.stdout)
    return 0
