"""``hil calibrate --left GLOB --right GLOB [--board 6x7] [--square 24] --out FILE`` — stereo
calibration from chessboard image pairs (paired by sorted file name; seed 001 section 4.1).

Each image is searched with a detection cascade (the classic detector with a quick pre-check,
then with OpenCV's default flags, then the SB detector; a time budget per image). Writes the
calibration file (versioned JSON, docs/calibration-format.md) and prints one JSON summary on
stdout (every field: docs/calibrate.md): ``pairs_found``, ``pairs_used``, ``rms_left``,
``rms_right``, ``rms_stereo`` (px), ``baseline`` and ``T`` (in the square's units), ``per_view``
(reprojection errors, outlier flag), ``views_left_out`` (which and why), ``detections`` (per
image: detector, time), ``board_not_found``, ``elapsed_s``, ``out``. Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from typing import Any

from hil.vision.calibrate import CalibrationSettings, calibrate_from_files
from hil.vision.camera_model import save_calibration


def _board(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) < 2 or int(m.group(2)) < 2:
        raise argparse.ArgumentTypeError(f"expected COLSxROWS inner corners such as 6x7, got {text!r}")
    return int(m.group(1)), int(m.group(2))


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "calibrate",
        help="stereo calibration from chessboard image pairs (JSON summary)",
        description="Zhang calibration of both cameras (radial + tangential distortion), outlier "
        "view rejection, stereo extrinsics and rectification.",
    )
    p.add_argument("--left", required=True, metavar="GLOB", help="left images (quote the pattern)")
    p.add_argument("--right", required=True, metavar="GLOB", help="right images (same count, same order)")
    p.add_argument(
        "--board",
        type=_board,
        default=(6, 7),
        metavar="COLSxROWS",
        help="inner corners (default 6x7: seed 001's 7x8-square board)",
    )
    p.add_argument("--square", type=_positive, default=24.0, metavar="MM", help="square size (default 24)")
    p.add_argument("--out", required=True, metavar="FILE", help="calibration file to write (JSON)")
    p.add_argument("--min-pairs", type=int, default=5, help="fewest usable pairs (default 5)")
    p.add_argument("--fix-k3", action="store_true", help="do not estimate the k3 radial term")
    p.add_argument(
        "--exclude-outliers",
        action="store_true",
        help="leave views whose reprojection error is far above the median out and re-calibrate "
        "(default: flag them in per_view only)",
    )
    p.add_argument(
        "--detect-budget",
        type=_positive,
        default=5.0,
        metavar="S",
        help="seconds per image after which no further board detector is tried (default 5)",
    )
    p.set_defaults(func=run)


def _progress_printer() -> Any:
    tty = sys.stderr.isatty()

    def progress(i: int, n: int, message: str) -> None:
        if tty:
            width = 30
            done = int(width * i / max(n, 1))
            sys.stderr.write(f"\r[{'#' * done}{'.' * (width - done)}] {i}/{n} {message[:60]:<60}")
            if i >= n:
                sys.stderr.write("\n")
        else:
            sys.stderr.write(f"calibrate: {i}/{n} {message}\n")
        sys.stderr.flush()

    return progress


def run(args: argparse.Namespace) -> int:
    settings = CalibrationSettings(
        board_cols=args.board[0],
        board_rows=args.board[1],
        square_mm=args.square,
        min_pairs=args.min_pairs,
        fix_k3=args.fix_k3,
        exclude_outliers=args.exclude_outliers,
        detect_budget_s=args.detect_budget,
    )
    result = calibrate_from_files(args.left, args.right, settings, _progress_printer())
    save_calibration(result.calibration, args.out)
    for _view, reason in result.left_out:
        print(f"calibrate: left out {reason}", file=sys.stderr)
    for view, reason in result.rejected:
        print(f"calibrate: left out view {view}: {reason}", file=sys.stderr)
    for v in result.per_view:
        if v["outlier"] and v["used"]:
            print(f"calibrate: view {v['view']} is an outlier (kept; --exclude-outliers leaves it out)",
                  file=sys.stderr)
    json.dump({**result.summary(), "out": args.out}, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0
