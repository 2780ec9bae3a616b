"""Stereo calibration from chessboard image pairs (seed 001 section 4.1: Zhang's method).

Inner corners are found with OpenCV and refined to sub-pixel; each camera is calibrated (radial
k1, k2, k3 and tangential p1, p2 distortion), views whose reprojection error is an outlier are
rejected (named) and the cameras re-calibrated without them, then the stereo extrinsics are
estimated with the intrinsics fixed, and the rectification follows from the result.
"""

from __future__ import annotations

import glob
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import CalibrationError, InputFileError
from hil.vision.camera_model import StereoCalibration
from hil.vision.io import load_grey_image
from hil.vision.render import chessboard_corners_mm

FloatArray = NDArray[np.float64]
U8Image = NDArray[np.uint8]
Progress = Callable[[int, int, str], None]


@dataclass(frozen=True)
class CalibrationSettings:
    """board_cols x board_rows inner corners (seed 001: a 7x8-square board = 6x7 inner corners),
    square_mm the square size (the unit of the result's translation). outlier_mad: a view is an
    outlier when its RMS exceeds median + outlier_mad * 1.4826 * MAD and ``outlier_floor_px``.
    min_pairs: fewest usable pairs. fix_k3: estimate only k1, k2 radially (more stable with few views).
    """

    board_cols: int = 6
    board_rows: int = 7
    square_mm: float = 24.0
    outlier_mad: float = 4.0
    outlier_floor_px: float = 0.5
    min_pairs: int = 5
    fix_k3: bool = False

    def __post_init__(self) -> None:
        if self.board_cols < 2 or self.board_rows < 2:
            raise CalibrationError(
                f"board must have at least 2x2 inner corners, got {self.board_cols}x{self.board_rows}"
            )
        if not (math.isfinite(self.square_mm) and self.square_mm > 0):
            raise CalibrationError(f"square size must be a positive number, got {self.square_mm}")
        if self.min_pairs < 3:
            raise CalibrationError("min_pairs must be at least 3")

    def to_dict(self) -> dict[str, Any]:
        return {
            "board_inner_corners": [self.board_cols, self.board_rows],
            "square_mm": self.square_mm,
            "outlier_mad": self.outlier_mad,
            "outlier_floor_px": self.outlier_floor_px,
            "min_pairs": self.min_pairs,
            "fix_k3": self.fix_k3,
        }


@dataclass(frozen=True)
class CalibrationResult:
    calibration: StereoCalibration
    pairs_found: int
    pairs_used: int
    rms_left: float
    rms_right: float
    rms_stereo: float
    rejected: tuple[tuple[str, str], ...] = ()
    missing: tuple[str, ...] = ()
    elapsed_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """The JSON summary ``hil calibrate`` prints."""
        cal = self.calibration
        return {
            "pairs_found": self.pairs_found,
            "pairs_used": self.pairs_used,
            "rms_left": self.rms_left,
            "rms_right": self.rms_right,
            "rms_stereo": self.rms_stereo,
            "baseline": cal.baseline_mm,
            "T": [float(v) for v in cal.t_right_from_left_mm],
            "rejected_views": [{"view": v, "reason": r} for v, r in self.rejected],
            "board_not_found": list(self.missing),
            "elapsed_s": self.elapsed_s,
        }


def find_chessboard(img: U8Image, cols: int, rows: int) -> FloatArray | None:
    """Inner corners (cols*rows, 2) refined to sub-pixel, or None when the board is not found."""
    # adaptive threshold first, then the plain one; CALIB_CB_NORMALIZE_IMAGE is left out: it makes
    # a failed search (wrong --board) take seconds per image
    corners = None
    for flags in (cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_FAST_CHECK, cv2.CALIB_CB_FAST_CHECK):
        found, corners = cv2.findChessboardCorners(img, (cols, rows), flags=flags)
        if found and corners is not None:
            break
    else:
        return None
    # window: a third of the smallest corner spacing, at least 2 px
    c = corners.reshape(-1, 2)
    spacing = float(np.min(np.linalg.norm(np.diff(c.reshape(rows, cols, 2), axis=1), axis=2)))
    win = int(max(2, min(11, spacing / 3)))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    refined = cv2.cornerSubPix(img, corners.astype(np.float32), (win, win), (-1, -1), crit)
    return np.asarray(refined.reshape(-1, 2), dtype=np.float64)


def _as_corners(c: ArrayLike, n: int, name: str) -> NDArray[np.float32]:
    arr = np.asarray(c, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[1] == 1 and arr.shape[2] == 2:
        arr = arr[:, 0, :]
    if arr.ndim != 2 or arr.shape != (n, 2):
        raise CalibrationError(f"{name}: corners must have shape ({n}, 2) or ({n}, 1, 2), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{name}: corners contain NaN or infinite values")
    return arr.astype(np.float32).reshape(-1, 1, 2)


def _outliers(errors: FloatArray, settings: CalibrationSettings) -> NDArray[np.bool_]:
    med = float(np.median(errors))
    mad = float(np.median(np.abs(errors - med))) * 1.4826
    limit = max(med + settings.outlier_mad * max(mad, 0.05 * med), settings.outlier_floor_px)
    return np.asarray(errors > limit, dtype=np.bool_)


def calibrate_from_corners(
    corners_left: Sequence[ArrayLike],
    corners_right: Sequence[ArrayLike],
    image_size: tuple[int, int],
    settings: CalibrationSettings = CalibrationSettings(),
    names: Sequence[str] | None = None,
    progress: Progress | None = None,
) -> CalibrationResult:
    """Calibrate a stereo rig from detected inner corners of the same board in each pair.

    ``corners_*[i]`` is (N, 2) or OpenCV's (N, 1, 2), N = cols*rows, row-major board order.
    Raises CalibrationError for too few pairs, wrong shapes or a failed optimisation.
    """
    t0 = time.perf_counter()
    n_corners = settings.board_cols * settings.board_rows
    if len(corners_left) != len(corners_right):
        raise CalibrationError(f"{len(corners_left)} left views but {len(corners_right)} right views")
    views = list(names) if names is not None else [f"pair {i}" for i in range(len(corners_left))]
    L = [_as_corners(c, n_corners, f"left view {views[i]}") for i, c in enumerate(corners_left)]
    R = [_as_corners(c, n_corners, f"right view {views[i]}") for i, c in enumerate(corners_right)]
    if len(L) < settings.min_pairs:
        raise CalibrationError(
            f"only {len(L)} pair(s) with the board found in both images; need at least {settings.min_pairs}"
        )
    obj = chessboard_corners_mm(settings.board_cols, settings.board_rows, settings.square_mm).astype(
        np.float32
    )
    flags = cv2.CALIB_FIX_K3 if settings.fix_k3 else 0
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-9)

    def mono(pts: list[NDArray[np.float32]]) -> tuple[float, FloatArray, FloatArray, FloatArray]:
        rms, K, d, _, _, _, _, per_view = cv2.calibrateCameraExtended(
            [obj] * len(pts), pts, image_size, np.eye(3), np.zeros(5), flags=flags, criteria=crit
        )
        return (
            float(rms),
            np.asarray(K, np.float64),
            np.asarray(d, np.float64).reshape(-1)[:5],
            np.asarray(per_view, np.float64).reshape(-1),
        )

    if progress:
        progress(0, 3, "calibrating the left and right cameras")
    try:
        rms_l, KL, dL, ev_l = mono(L)
        rms_r, KR, dR, ev_r = mono(R)
        bad = _outliers(ev_l, settings) | _outliers(ev_r, settings)
        rejected = tuple(
            (views[i], f"reprojection error left {ev_l[i]:.3f} px, right {ev_r[i]:.3f} px is an outlier")
            for i in np.nonzero(bad)[0]
        )
        keep = [i for i in range(len(L)) if not bad[i]]
        if len(keep) < settings.min_pairs:
            raise CalibrationError(
                f"only {len(keep)} pair(s) left after rejecting outlier views; "
                f"need at least {settings.min_pairs}"
            )
        if rejected:
            if progress:
                progress(1, 3, f"re-calibrating without {len(rejected)} outlier view(s)")
            L, R = [L[i] for i in keep], [R[i] for i in keep]
            rms_l, KL, dL, ev_l = mono(L)
            rms_r, KR, dR, ev_r = mono(R)
        if progress:
            progress(2, 3, "stereo extrinsics")
        out = cv2.stereoCalibrateExtended(
            [obj] * len(L),
            L,
            R,
            KL,
            dL,
            KR,
            dR,
            image_size,
            np.eye(3),
            np.zeros((3, 1)),
            flags=cv2.CALIB_FIX_INTRINSIC,
            criteria=crit,
        )
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV calibration failed: {exc.err}") from exc
    rms_s = float(out[0])
    Rm, T = np.asarray(out[5], np.float64), np.asarray(out[6], np.float64).reshape(3)
    per_view_stereo = np.asarray(out[-1], np.float64).reshape(len(L), -1)
    kept_names = [views[i] for i in keep]
    quality = {
        "rms_left_px": rms_l,
        "rms_right_px": rms_r,
        "rms_stereo_px": rms_s,
        "per_view": [
            {
                "view": kept_names[i],
                "rms_left_px": float(ev_l[i]),
                "rms_right_px": float(ev_r[i]),
                "rms_stereo_px": [float(v) for v in per_view_stereo[i]],
            }
            for i in range(len(L))
        ],
        "rejected_views": [{"view": v, "reason": r} for v, r in rejected],
    }
    cal = StereoCalibration(
        image_size,
        KL,
        dL,
        KR,
        dR,
        Rm,
        T,
        quality=quality,
        settings={"source": "hil calibrate", **settings.to_dict()},
    )
    if progress:
        progress(3, 3, "done")
    return CalibrationResult(
        cal, len(corners_left), len(L), rms_l, rms_r, rms_s, rejected, elapsed_s=time.perf_counter() - t0
    )


def _expand(pattern: str, side: str) -> list[str]:
    files = sorted(glob.glob(pattern))
    if not files:
        raise InputFileError(pattern, f"no {side} images match this pattern")
    return files


def calibrate_from_files(
    left_glob: str,
    right_glob: str,
    settings: CalibrationSettings = CalibrationSettings(),
    progress: Progress | None = None,
) -> CalibrationResult:
    """Calibrate from image files; left/right are paired by sorted file name.

    Raises:
        InputFileError: a pattern matches nothing, or an image cannot be read.
        CalibrationError: different left/right counts, image sizes differ, too few usable pairs.
    """
    t0 = time.perf_counter()
    lf, rf = _expand(left_glob, "left"), _expand(right_glob, "right")
    if len(lf) != len(rf):
        raise CalibrationError(
            f"{len(lf)} left images but {len(rf)} right images; they are paired by sorted name"
        )
    size: tuple[int, int] | None = None
    first = ""
    cl: list[FloatArray] = []
    cr: list[FloatArray] = []
    names: list[str] = []
    missing: list[str] = []
    n = len(lf)
    for i, (a, b) in enumerate(zip(lf, rf, strict=True)):
        if progress:
            progress(i, n, f"corners {Path(a).name} / {Path(b).name}")
        ia, ib = load_grey_image(a), load_grey_image(b)
        for path, img in ((a, ia), (b, ib)):
            s = (img.shape[1], img.shape[0])
            if size is None:
                size, first = s, path
            elif s != size:
                raise CalibrationError(f"{path} is {s[0]}x{s[1]} but {first} is {size[0]}x{size[1]}")
        ca = find_chessboard(ia, settings.board_cols, settings.board_rows)
        cb = find_chessboard(ib, settings.board_cols, settings.board_rows)
        name = f"{Path(a).name}|{Path(b).name}"
        if ca is None or cb is None:
            missing.append(name)
            continue
        cl.append(ca)
        cr.append(cb)
        names.append(name)
    if progress:
        progress(n, n, f"board found in {len(cl)} of {n} pairs")
    assert size is not None
    if len(cl) < settings.min_pairs:
        raise CalibrationError(
            f"the {settings.board_cols}x{settings.board_rows} board was found in both images of only "
            f"{len(cl)} of {n} pair(s); need at least {settings.min_pairs}"
        )
    res = calibrate_from_corners(cl, cr, size, settings, names, progress)
    return CalibrationResult(
        res.calibration,
        len(cl),
        res.pairs_used,
        res.rms_left,
        res.rms_right,
        res.rms_stereo,
        res.rejected,
        tuple(missing),
        time.perf_counter() - t0,
    )
