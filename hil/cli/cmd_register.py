"""``hil register FIXED MOVING`` — paired-point rigid registration of two point files.

Prints one JSON object on stdout::

    {"method", "fixed", "moving", "n_points", "T" (4x4, maps MOVING points into FIXED's frame),
     "fre_rms_mm", "residuals_mm", "rotation_deg", "rotation_axis", "translation_mm",
     "quaternion_wxyz", "fle_mm", "fle_source", "fre_expected_mm" (with --fle),
     and with --target: "target_moving", "target_mapped", "tre_expected_mm"}

``--fle`` is the RMS 3-D fiducial localisation error (combined over both files); without it the
FLE is estimated from the observed FRE (``FLE = FRE / sqrt(1 - 2/N)``, FWM 1998) and
``fle_source`` says so. ``--method affine4`` (seed 000 eqs 2-12) needs exactly 4 non-coplanar
points, returns a general affine ``T`` (``rigid: false``; rotation/translation are those of the
nearest rigid transform) and no TRE prediction (the FWM model is for rigid least squares).

Bad input exits 2 with one line on stderr naming the file and the problem.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from hil.cli.argtypes import xyz_mm
from hil.errors import DegenerateConfigurationError, GeometryError, InputFileError
from hil.geometry.affine4 import affine_frame, register_affine4
from hil.geometry.registration import check_point_configuration, register
from hil.geometry.transform import RigidTransform
from hil.geometry.tre import expected_fre_mm, expected_tre_mm, fle_from_fre_mm
from hil.io.points import read_points
from hil.log import get_logger

_log = get_logger(__name__)


def _fle(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of mm, got {text!r}") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"FLE must be a finite non-negative number, got {text!r}")
    return v


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "register",
        help="rigid registration of two paired point files (prints JSON)",
        description=(
            "Register MOVING onto FIXED (paired points, same order): prints the 4x4 T mapping MOVING "
            "points into FIXED's frame, FRE and residuals, and with --target the mapped target and its "
            "expected TRE. Files: CSV (x,y,z columns), JSON, 3D Slicer .mrk.json/.fcsv (read as LPS). "
            "Write a negative target as --target=-1,2,3."
        ),
    )
    p.add_argument("fixed", metavar="FIXED", help="point file in the frame to map into")
    p.add_argument("moving", metavar="MOVING", help="the same points in the frame to map from")
    p.add_argument("--target", type=xyz_mm, metavar="X,Y,Z", help="a point in MOVING's frame to map, mm")
    p.add_argument("--method", choices=["horn", "svd", "affine4"], default="horn", help="default: horn")
    p.add_argument("--fle", type=_fle, metavar="MM", help="RMS fiducial localisation error, mm")
    p.set_defaults(func=run)


def _check_file(path: str, pts: np.ndarray[Any, Any], method: str) -> None:
    try:
        if method == "affine4":
            affine_frame(pts, "points")
        else:
            check_point_configuration(pts, "points")
    except DegenerateConfigurationError as exc:
        reason = str(exc).removeprefix("points: ")
        raise InputFileError(path, reason) from None
    except GeometryError as exc:
        raise InputFileError(path, str(exc).removeprefix("points: ")) from None


def _r(x: float) -> float:
    return round(float(x), 6)


def _rl(a: Any) -> Any:
    return np.round(np.asarray(a, dtype=np.float64), 6).tolist()


def run(args: argparse.Namespace) -> int:
    fixed_set = read_points(args.fixed)
    moving_set = read_points(args.moving)
    n_f, n_m = len(fixed_set), len(moving_set)
    if args.method == "affine4":
        for path, n in ((args.fixed, n_f), (args.moving, n_m)):
            if n != 4:
                raise InputFileError(path, f"has {n} points; --method affine4 needs exactly 4")
    else:
        for path, n in ((args.fixed, n_f), (args.moving, n_m)):
            if n < 3:
                raise InputFileError(path, f"has {n} point(s); registration needs at least 3")
    if n_f != n_m:
        raise InputFileError(
            args.moving, f"has {n_m} points but {args.fixed} has {n_f}; the files must pair point for point"
        )
    _check_file(args.fixed, fixed_set.points_mm, args.method)
    _check_file(args.moving, moving_set.points_mm, args.method)

    out: dict[str, Any] = {"method": args.method, "fixed": args.fixed, "moving": args.moving, "n_points": n_f}
    if args.method == "affine4":
        aff = register_affine4(fixed_set.points_mm, moving_set.points_mm)
        rigid: RigidTransform = aff.nearest_rigid
        out["rigid"] = False
        out["T"] = aff.matrix_fixed_from_moving.tolist()
        fre = aff.fre_rms_mm
        residuals = aff.residuals_mm
    else:
        reg = register(fixed_set.points_mm, moving_set.points_mm, method=args.method)
        rigid = reg.T_fixed_from_moving
        out["rigid"] = True
        out["T"] = rigid.as_matrix().tolist()  # full precision: callers reuse it
        fre = reg.fre_rms_mm
        residuals = reg.residuals_mm
    rotvec = rigid.as_rotvec()
    angle = float(np.linalg.norm(rotvec))
    out["fre_rms_mm"] = _r(fre)
    out["residuals_mm"] = _rl(residuals)
    out["rotation_deg"] = _r(math.degrees(rigid.rotation_angle_rad()))
    out["rotation_axis"] = _rl(rotvec / angle) if angle > 0 else None
    out["translation_mm"] = _rl(rigid.t)
    out["quaternion_wxyz"] = _rl(rigid.as_quaternion())
    if args.method != "affine4":
        if args.fle is not None:
            fle, source = args.fle, "given"
        else:
            fle, source = fle_from_fre_mm(n_f, fre), "estimated_from_fre"
        out["fle_mm"] = _r(fle)
        out["fle_source"] = source
        if args.fle is not None:  # with an estimated FLE the expected FRE is the observed one
            out["fre_expected_mm"] = _r(expected_fre_mm(n_f, fle))
    if args.target is not None:
        target = np.asarray(args.target, dtype=np.float64)
        out["target_moving"] = _rl(target)
        if args.method == "affine4":
            out["target_mapped"] = _rl(aff.apply(target))
            out["tre_expected_mm"] = None
        else:
            out["target_mapped"] = _rl(rigid.apply(target))
            out["tre_expected_mm"] = _r(expected_tre_mm(moving_set.points_mm, target, out["fle_mm"]))
    _log.info(
        "register_done", method=args.method, n_points=n_f, fre_rms_mm=out["fre_rms_mm"],
        rotation_deg=out["rotation_deg"], tre_expected_mm=out.get("tre_expected_mm"),
    )
    sys.stdout.write(format_json(out))
    return 0


def format_json(obj: dict[str, Any]) -> str:
    """One key per line, values (matrices included) compact: valid JSON that reads well."""
    lines = [f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in obj.items()]
    return "{\n" + ",\n".join(lines) + "\n}\n"
