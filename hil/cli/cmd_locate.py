"""``hil locate --calibration FILE LEFT RIGHT [--markers MARKERSET]`` — find, triangulate and
identify the ring markers of one stereo image pair.

Prints one JSON object on stdout: ``calibration``, ``left``/``right`` (file names),
``detections_left``/``detections_right`` (centre px, centre sigma, ellipses, residuals),
``points`` (3D point in the optical frame, mm, epipolar error px, ray gap mm, the detection
indices), ``rejected_pairs``, ``unmatched_left``/``unmatched_right`` and, with ``--markers``,
``identification`` (model index -> point index, residuals, FRE, T_optical_from_model) or
``identification_error``. Colour images are converted to grey. Bad input exits 2 with one line.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hil.io.points import read_points
from hil.vision.camera_model import load_calibration
from hil.vision.io import load_grey_image
from hil.vision.pipeline import locate_markers
from hil.vision.stereo import StereoParams


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "locate",
        help="find and triangulate ring markers in a stereo image pair (JSON)",
        description="Detect ring markers in both images, pair them on epipolar lines, triangulate "
        "them in the optical (left camera) frame and optionally identify them.",
    )
    p.add_argument("--calibration", required=True, metavar="FILE", help="stereo calibration (JSON)")
    p.add_argument("left", metavar="LEFT_IMAGE")
    p.add_argument("right", metavar="RIGHT_IMAGE")
    p.add_argument("--markers", metavar="MARKERSET", help="marker layout (N x 3 mm) to identify against")
    p.add_argument(
        "--tolerance",
        type=float,
        default=2.0,
        metavar="MM",
        help="identification tolerance in mm (default 2)",
    )
    p.add_argument(
        "--max-gap",
        type=float,
        default=1.0,
        metavar="MM",
        help="reject pairs whose rays pass further apart (default 1 mm)",
    )
    p.add_argument(
        "--epipolar-tol",
        type=float,
        default=2.0,
        metavar="PX",
        help="largest rectified row difference of a pair (default 2 px)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    cal = load_calibration(args.calibration)
    model = read_points(args.markers).points_mm if args.markers else None
    left, right = load_grey_image(args.left), load_grey_image(args.right)
    params = StereoParams(epipolar_tol_px=args.epipolar_tol, max_gap_mm=args.max_gap)
    res = locate_markers(
        cal, left, right, model_mm=model, stereo_params=params, match_tolerance_mm=args.tolerance
    )
    out = {"calibration": args.calibration, "left": args.left, "right": args.right, **res.to_dict()}
    if args.markers:
        out["markers"] = args.markers
    json.dump(out, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0
