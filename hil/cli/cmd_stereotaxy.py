"""``hil stereotaxy SPOTS_FILE --frame FRAME_FILE`` — single-slice CT registration of a rod frame.

Seed 004 §IV: the spots where a stereotactic frame's rods cut one CT slice give the rigid transform
between the frame and the scanner (Plücker-line formulation, SVD solution, rotation correction by
SVD; ``--refine`` adds the Levenberg-Marquardt stage). Prints one JSON object on stdout::

    {"method", "frame", "spots_file", "n_spots", "pixel_mm", "pixel_mm_source" (given | file |
     estimated), "slice_z_mm", "T_scanner_from_frame" (4x4: frame points -> scanner mm),
     "T_frame_from_scanner", "rotation_deg", "translation_mm", "residual_rms_mm",
     "residual_max_mm", "rank", "structural_rank", "condition_number", "singular_values",
     "orthonormality_defect", "iterations",
     "spots": [{"rod", "u_px", "v_px", "residual_mm", "in_slice_residual_mm", "lambda_mm",
                "within_rod_bounds"}],
     "warnings": [...], and with --target: "target_frame_mm", "target_scanner_mm",
     "target_error_box_mm" (half-widths for --spot-error-px)}

Scanner frame: x along the image columns (u), y along the rows (v), mm from the centre of pixel
(0, 0), z along the slice normal (the slice at ``slice_z_mm``). The pixel size comes from
``--pixel-mm``, else from the spots file, else it is estimated (needs 5 or more rods).
Bad input exits 2 with one line on stderr naming the file and the problem.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import numpy as np

from hil.cli.argtypes import xyz_mm
from hil.errors import DegenerateConfigurationError, GeometryError, InputFileError
from hil.geometry.stereotaxy import (
    Rod,
    SliceSpots,
    StereotacticFrame,
    StereotaxyResult,
    error_box_mm,
    load_frame,
    load_spots,
    register_single_slice,
    robot_from_image_via_frame,
)
from hil.geometry.transform import RigidTransform
from hil.log import get_logger

_log = get_logger(__name__)


def _pair(text: str) -> tuple[float, float]:
    parts = text.split(",")
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected SX,SY in mm per pixel, got {text!r}") from None
    if len(vals) != 2 or not all(math.isfinite(v) and v > 0 for v in vals):
        raise argparse.ArgumentTypeError(f"expected two positive numbers SX,SY, got {text!r}")
    return vals[0], vals[1]


def _finite(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of mm, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def _nonneg(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"expected a finite non-negative number, got {text!r}")
    return v


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "stereotaxy",
        help="single-slice CT registration of a rod (line-fiducial) frame (prints JSON)",
        description=(
            "Register a stereotactic frame of rods to the CT scanner from the spots its rods make in ONE "
            "slice (seed 004 section IV). SPOTS_FILE: JSON (schema hil.ct_slice_spots) or CSV "
            "'rod,u_px,v_px'; FRAME_FILE: JSON (schema hil.stereotactic_frame). See docs/pose004.md."
        ),
    )
    p.add_argument("spots", metavar="SPOTS_FILE", help="spot positions of one slice, with their rod ids")
    p.add_argument("--frame", required=True, metavar="FRAME_FILE", help="the frame's rod definitions")
    p.add_argument("--pixel-mm", type=_pair, metavar="SX,SY", help="pixel size, mm (overrides the file)")
    p.add_argument(
        "--slice-z-mm", type=_finite, metavar="Z", help="slice position along scanner z (default: file or 0)"
    )
    p.add_argument("--refine", action="store_true", help="add the Levenberg-Marquardt (Newton) refinement")
    p.add_argument("--bounds-margin-mm", type=_nonneg, default=1.0, metavar="MM", help="rod-bounds tolerance")
    p.add_argument(
        "--target", type=xyz_mm, metavar="X,Y,Z", help="a frame point to map into the scanner, mm"
    )
    p.add_argument(
        "--spot-error-px", type=_nonneg, default=0.25, metavar="PX", help="spot error for the --target box"
    )
    p.add_argument(
        "--robot-tcp-pose", type=_pose6, metavar="X,Y,Z,RX,RY,RZ",
        help="robot TCP pose when the slice was taken (mm, rotation vector in rad): also print "
        "T_robot_from_image, the image->robot registration through the frame the robot carries",
    )
    p.add_argument(
        "--tcp-from-frame", type=_pose6, metavar="X,Y,Z,RX,RY,RZ",
        help="the frame's mounting on the tool, T_tcp_from_frame (mm, rad; default: identity)",
    )
    p.set_defaults(func=run)


def _pose6(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected six numbers X,Y,Z,RX,RY,RZ, got {text!r}") from None
    if len(vals) != 6 or not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"expected six finite numbers X,Y,Z,RX,RY,RZ, got {text!r}")
    return vals


def _r(x: float) -> float | None:
    return round(float(x), 6) if math.isfinite(float(x)) else None


def _rl(a: Any) -> Any:
    return [_r(v) for v in np.asarray(a, dtype=np.float64).reshape(-1)]


def _frame_rods(frame: StereotacticFrame, spots: SliceSpots, args: argparse.Namespace) -> list[Rod]:
    """The frame's rod of each spot, in spot order.

    Raises:
        InputFileError: a spot names a rod the frame does not define (names the spots file).
    """
    rods = []
    for rid in spots.rod_ids:
        try:
            rods.append(frame.rod(rid))
        except GeometryError:
            raise InputFileError(
                args.spots, f"spot on rod {rid!r}, which frame {args.frame} does not define"
            ) from None
    return rods


def _pixel_size(args: argparse.Namespace, spots: SliceSpots) -> tuple[tuple[float, float] | None, str]:
    """The pixel size (mm) to register with and where it comes from: ``--pixel-mm`` ("given"),
    the spots file ("file"), or None ("estimated" by the registration)."""
    if args.pixel_mm is not None:
        return args.pixel_mm, "given"
    if spots.pixel_mm is not None:
        return spots.pixel_mm, "file"
    return None, "estimated"


def _register(
    args: argparse.Namespace,
    rods: list[Rod],
    spots: SliceSpots,
    pixel: tuple[float, float] | None,
    slice_z: float,
) -> StereotaxyResult:
    """:func:`register_single_slice` with the command's options.

    Raises:
        InputFileError: the spots cannot be registered (degenerate or invalid; names the spots file).
    """
    try:
        return register_single_slice(
            rods,
            spots.uv_px,
            pixel,
            slice_z_mm=slice_z,
            refine=args.refine,
            bounds_margin_mm=args.bounds_margin_mm,
        )
    except DegenerateConfigurationError as exc:
        raise InputFileError(args.spots, f"cannot register: {exc}") from None
    except GeometryError as exc:
        raise InputFileError(args.spots, str(exc)) from None


def _spot_rows(spots: SliceSpots, res: StereotaxyResult) -> list[dict[str, Any]]:
    """The JSON ``spots`` rows: each spot's pixel position and residuals (mm) on its rod."""
    return [
        {
            "rod": rid,
            "u_px": _r(spots.uv_px[j, 0]),
            "v_px": _r(spots.uv_px[j, 1]),
            "residual_mm": _r(res.residuals_mm[j]),
            "in_slice_residual_mm": _r(res.in_slice_residuals_mm[j]),
            "lambda_mm": _r(res.lambdas_mm[j]),
            "within_rod_bounds": bool(res.within_bounds[j]),
        }
        for j, rid in enumerate(spots.rod_ids)
    ]


def _registration_json(
    args: argparse.Namespace,
    rods: list[Rod],
    spots: SliceSpots,
    res: StereotaxyResult,
    pixel_source: str,
    slice_z: float,
) -> dict[str, Any]:
    """The printed JSON's registration part (docs): transforms, residuals (mm) and conditioning."""
    T = res.T_scanner_from_frame
    return {
        "method": res.method,
        "frame": args.frame,
        "spots_file": args.spots,
        "n_spots": len(rods),
        "pixel_mm": _rl(res.pixel_mm),
        "pixel_mm_source": pixel_source,
        "slice_z_mm": _r(slice_z),
        "T_scanner_from_frame": T.as_matrix().tolist(),
        "T_frame_from_scanner": res.T_frame_from_scanner.as_matrix().tolist(),
        "rotation_deg": _r(math.degrees(T.rotation_angle_rad())),
        "translation_mm": _rl(T.t),
        "residual_rms_mm": _r(res.rms_mm),
        "residual_max_mm": _r(float(res.residuals_mm.max())),
        "rank": res.rank,
        "structural_rank": res.structural_rank,
        "condition_number": _r(res.condition_number),
        "singular_values": _rl(res.singular_values),
        "orthonormality_defect": _r(res.orthonormality_defect),
        "iterations": res.iterations,
        "spots": _spot_rows(spots, res),
        "warnings": list(res.warnings),
    }


def run(args: argparse.Namespace) -> int:
    frame = load_frame(args.frame)
    spots = load_spots(args.spots)
    rods = _frame_rods(frame, spots, args)
    pixel, source = _pixel_size(args, spots)
    slice_z = args.slice_z_mm if args.slice_z_mm is not None else spots.slice_z_mm
    res = _register(args, rods, spots, pixel, slice_z)
    T = res.T_scanner_from_frame
    out = _registration_json(args, rods, spots, res, source, slice_z)
    if args.target is not None:
        box = error_box_mm(
            rods,
            spots.uv_px,
            res.pixel_mm,
            args.target,
            spot_error_px=args.spot_error_px,
            slice_z_mm=slice_z,
            refine=args.refine,
        )
        out["target_frame_mm"] = _rl(args.target)
        out["target_scanner_mm"] = _rl(T.apply(np.asarray(args.target, dtype=np.float64)))
        out["target_error_box_mm"] = _rl(box)
        out["spot_error_px"] = _r(args.spot_error_px)
    if args.tcp_from_frame is not None and args.robot_tcp_pose is None:
        raise InputFileError(args.spots, "--tcp-from-frame needs --robot-tcp-pose")
    if args.robot_tcp_pose is not None:
        T_robot_from_tcp = RigidTransform.from_rotvec(args.robot_tcp_pose[3:], args.robot_tcp_pose[:3])
        mount = args.tcp_from_frame or (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        T_tcp_from_frame = RigidTransform.from_rotvec(mount[3:], mount[:3])
        T_robot_from_image = robot_from_image_via_frame(T, T_robot_from_tcp, T_tcp_from_frame)
        out["T_robot_from_image"] = T_robot_from_image.as_matrix().tolist()
    _log.info("stereotaxy_registered", n_spots=len(rods), rms_mm=res.rms_mm, method=res.method)
    print(json.dumps(out, indent=2))
    return 0
