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
from hil.vision.io import load_grey_image_channels
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
    exclude_outliers: leave flagged views out and re-calibrate (default: flag them only).
    detect_budget_s: time per image after which no further detector is tried. fail_fast_pairs:
    when no image of the first this many pairs shows the board, stop (a wrong ``--board`` size).
    edge_margin_px: a board with a corner closer than this to the image border is partly out of
    view and left out.
    """

    board_cols: int = 6
    board_rows: int = 7
    square_mm: float = 24.0
    outlier_mad: float = 4.0
    outlier_floor_px: float = 0.5
    min_pairs: int = 5
    fix_k3: bool = False
    exclude_outliers: bool = False
    detect_budget_s: float = 5.0
    fail_fast_pairs: int = 3
    edge_margin_px: float = 2.0

    def __post_init__(self) -> None:
        if self.board_cols < 2 or self.board_rows < 2:
            raise CalibrationError(
                f"board must have at least 2x2 inner corners, got {self.board_cols}x{self.board_rows}"
            )
        if not (math.isfinite(self.square_mm) and self.square_mm > 0):
            raise CalibrationError(f"square size must be a positive number, got {self.square_mm}")
        if self.min_pairs < 3:
            raise CalibrationError("min_pairs must be at least 3")
        if not (math.isfinite(self.detect_budget_s) and self.detect_budget_s > 0):
            raise CalibrationError(f"detection time budget must be > 0 s, got {self.detect_budget_s}")

    def to_dict(self) -> dict[str, Any]:
        return {
            "board_inner_corners": [self.board_cols, self.board_rows],
            "square_mm": self.square_mm,
            "outlier_mad": self.outlier_mad,
            "outlier_floor_px": self.outlier_floor_px,
            "min_pairs": self.min_pairs,
            "fix_k3": self.fix_k3,
            "exclude_outliers": self.exclude_outliers,
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
    #: per view used in the first calibration: view, rms_left, rms_right, outlier (bool), used (bool)
    per_view: tuple[dict[str, Any], ...] = ()
    #: pairs left out before calibration: view, reason
    left_out: tuple[tuple[str, str], ...] = ()
    #: per image: file, detector (fast / robust / sb / None), ms, tried
    detections: tuple[dict[str, Any], ...] = ()

    def summary(self) -> dict[str, Any]:
        """The JSON summary ``hil calibrate`` prints (docs/calibrate.md)."""
        cal = self.calibration
        return {
            "pairs_found": self.pairs_found,
            "pairs_used": self.pairs_used,
            "rms_left": self.rms_left,
            "rms_right": self.rms_right,
            "rms_stereo": self.rms_stereo,
            "baseline": cal.baseline_mm,
            "T": [float(v) for v in cal.t_right_from_left_mm],
            "per_view": list(self.per_view),
            "views_left_out": [{"view": v, "reason": r} for v, r in (*self.left_out, *self.rejected)],
            "rejected_views": [{"view": v, "reason": r} for v, r in self.rejected],
            "board_not_found": list(self.missing),
            "detections": list(self.detections),
            "elapsed_s": self.elapsed_s,
        }


#: the detection cascade: name -> OpenCV call. "fast": the classic detector with a quick pre-check
#: (adaptive threshold, then global); "robust": the classic detector with OpenCV's default flags
#: (adaptive threshold + image normalisation, no pre-check: slower, finds boards under uneven
#: light); "sb": the sector-based detector (findChessboardCornersSB; blur, noise, low contrast).
DETECTORS = ("fast", "robust", "sb")


@dataclass(frozen=True)
class BoardDetection:
    """One image's board search: corners (N, 2) (None: not found), the detector that found them,
    the detectors tried, the time spent (ms) and whether the time budget stopped the cascade."""

    corners: FloatArray | None
    detector: str | None
    tried: tuple[str, ...]
    elapsed_ms: float
    out_of_budget: bool = False

    def to_dict(self, file: str) -> dict[str, Any]:
        return {"file": file, "detector": self.detector, "tried": list(self.tried), "ms": self.elapsed_ms,
                "out_of_budget": self.out_of_budget}


def _run_detector(img: U8Image, name: str, size: tuple[int, int]) -> tuple[bool, Any]:
    if name == "fast":
        for flags in (cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_FAST_CHECK, cv2.CALIB_CB_FAST_CHECK):
            found, corners = cv2.findChessboardCorners(img, size, flags=flags)
            if found and corners is not None:
                return True, corners
        return False, None
    if name == "robust":
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(img, size, flags=flags)
        return bool(found) and corners is not None, corners
    found, corners = cv2.findChessboardCornersSB(img, size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
    return bool(found) and corners is not None, corners


def _canonical_order(c: FloatArray) -> FloatArray:
    """Row-major corners with the first corner the one nearer the image's top-left (the detectors
    may return a board turned by 180 degrees; both views of a pair must agree)."""
    d = c[-1] - c[0]
    return c[::-1].copy() if d[0] + d[1] < 0 else c


def detect_chessboard(
    img: U8Image, cols: int, rows: int, budget_s: float = 5.0, detectors: Sequence[str] = DETECTORS
) -> BoardDetection:
    """Search ``img`` for the board with each detector of :data:`DETECTORS` in turn until one
    finds it; a detector is not started once ``budget_s`` has passed (OpenCV calls cannot be
    interrupted, so one slow call can overrun the budget; the time is reported). Classic-detector
    corners are refined to sub-pixel (``cornerSubPix``); SB corners are sub-pixel already. Pure CPU.
    """
    t0 = time.perf_counter()
    tried: list[str] = []
    for name in detectors:
        if tried and time.perf_counter() - t0 > budget_s:
            return BoardDetection(None, None, tuple(tried), (time.perf_counter() - t0) * 1e3, True)
        tried.append(name)
        found, corners = _run_detector(img, name, (cols, rows))
        if not found:
            continue
        c = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        if name != "sb":
            # window: a third of the smallest corner spacing, at least 2 px
            spacing = float(np.min(np.linalg.norm(np.diff(c.reshape(rows, cols, 2), axis=1), axis=2)))
            win = int(max(2, min(11, spacing / 3)))
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
            start = c.astype(np.float32).reshape(-1, 1, 2)
            refined = cv2.cornerSubPix(img, start, (win, win), (-1, -1), crit)
            c = np.asarray(refined.reshape(-1, 2), dtype=np.float64)
        c = _canonical_order(c)
        return BoardDetection(c, name, tuple(tried), (time.perf_counter() - t0) * 1e3)
    return BoardDetection(None, None, tuple(tried), (time.perf_counter() - t0) * 1e3)


def find_chessboard(img: U8Image, cols: int, rows: int) -> FloatArray | None:
    """Inner corners (cols*rows, 2) refined to sub-pixel, or None when the board is not found
    (:func:`detect_chessboard` with the default budget)."""
    return detect_chessboard(img, cols, rows).corners


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


#: stop criteria of the mono and stereo optimisations
_CALIB_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-9)


def _corner_views(
    corners_left: Sequence[ArrayLike],
    corners_right: Sequence[ArrayLike],
    settings: CalibrationSettings,
    names: Sequence[str] | None,
) -> tuple[list[str], list[NDArray[np.float32]], list[NDArray[np.float32]]]:
    """View names and the left/right corners (px) as OpenCV's (N, 1, 2) float32, checked.

    Raises:
        CalibrationError: different left/right counts, a wrong shape or non-finite corners
            (naming the view), fewer than ``settings.min_pairs`` pairs.
    """
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
    return views, L, R


def _calibrate_camera(
    obj: NDArray[np.float32], pts: list[NDArray[np.float32]], image_size: tuple[int, int], flags: int
) -> tuple[float, FloatArray, FloatArray, FloatArray]:
    """Zhang calibration of one camera: RMS (px), K, the 5 distortion coefficients, per-view RMS (px).

    ``obj`` is the board's corners (mm, board frame), the same for every view. Raises cv2.error.
    """
    rms, K, d, _, _, _, _, per_view = cv2.calibrateCameraExtended(
        [obj] * len(pts), pts, image_size, np.eye(3), np.zeros(5), flags=flags, criteria=_CALIB_CRITERIA
    )
    return (
        float(rms),
        np.asarray(K, np.float64),
        np.asarray(d, np.float64).reshape(-1)[:5],
        np.asarray(per_view, np.float64).reshape(-1),
    )


def _outlier_reasons(
    ev_l: FloatArray, ev_r: FloatArray, bad: NDArray[np.bool_]
) -> dict[np.signedinteger[Any], str]:
    """View index -> why it is an outlier, for every flagged view (per-view RMS in px)."""
    return {
        i: f"reprojection error left {ev_l[i]:.3f} px, right {ev_r[i]:.3f} px is far above the "
        f"median ({float(np.median(ev_l)):.3f} / {float(np.median(ev_r)):.3f} px)"
        for i in np.nonzero(bad)[0]
    }


def _stereo_extrinsics(
    obj: NDArray[np.float32],
    L: list[NDArray[np.float32]],
    R: list[NDArray[np.float32]],
    left: tuple[FloatArray, FloatArray],
    right: tuple[FloatArray, FloatArray],
    image_size: tuple[int, int],
) -> Any:
    """OpenCV's stereo calibration with the intrinsics ``(K, dist)`` of each camera held fixed;
    returns ``cv2.stereoCalibrateExtended``'s tuple unchanged. Raises cv2.error."""
    return cv2.stereoCalibrateExtended(
        [obj] * len(L),
        L,
        R,
        left[0],
        left[1],
        right[0],
        right[1],
        image_size,
        np.eye(3),
        np.zeros((3, 1)),
        flags=cv2.CALIB_FIX_INTRINSIC,
        criteria=_CALIB_CRITERIA,
    )


def _first_pass_views(
    views: list[str],
    first_errors: list[tuple[float, float]],
    bad: NDArray[np.bool_],
    keep: list[int],
    per_view_stereo: FloatArray,
) -> tuple[dict[str, Any], ...]:
    """:attr:`CalibrationResult.per_view`: every view of the first calibration with its mono RMS
    (px), its stereo RMS (px, None when not used), whether it is an outlier and whether it was used."""
    final = {k: i for i, k in enumerate(keep)}
    return tuple(
        {
            "view": views[i],
            "rms_left_px": first_errors[i][0],
            "rms_right_px": first_errors[i][1],
            "rms_stereo_px": (
                [float(v) for v in per_view_stereo[final[i]]] if i in final else None
            ),
            "outlier": bool(bad[i]),
            "used": i in final,
        }
        for i in range(len(views))
    )


def _used_views(
    kept_names: list[str], ev_l: FloatArray, ev_r: FloatArray, per_view_stereo: FloatArray
) -> list[dict[str, Any]]:
    """The quality record's ``per_view``: each view of the final calibration with its RMS (px)."""
    return [
        {
            "view": kept_names[i],
            "rms_left_px": float(ev_l[i]),
            "rms_right_px": float(ev_r[i]),
            "rms_stereo_px": [float(v) for v in per_view_stereo[i]],
        }
        for i in range(len(kept_names))
    ]


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
    views, L, R = _corner_views(corners_left, corners_right, settings, names)
    obj = chessboard_corners_mm(settings.board_cols, settings.board_rows, settings.square_mm).astype(
        np.float32
    )
    flags = cv2.CALIB_FIX_K3 if settings.fix_k3 else 0
    if progress:
        progress(0, 3, "calibrating the left and right cameras")
    try:
        rms_l, KL, dL, ev_l = _calibrate_camera(obj, L, image_size, flags)
        rms_r, KR, dR, ev_r = _calibrate_camera(obj, R, image_size, flags)
        bad = _outliers(ev_l, settings) | _outliers(ev_r, settings)
        first_errors = [(float(ev_l[i]), float(ev_r[i])) for i in range(len(L))]
        reasons = _outlier_reasons(ev_l, ev_r, bad)
        excluded = bad if settings.exclude_outliers else np.zeros_like(bad)
        rejected = tuple((views[i], reasons[i]) for i in np.nonzero(excluded)[0])
        keep = [i for i in range(len(L)) if not excluded[i]]
        if len(keep) < settings.min_pairs:
            raise CalibrationError(
                f"only {len(keep)} pair(s) left after rejecting outlier views; "
                f"need at least {settings.min_pairs}"
            )
        if rejected:
            if progress:
                progress(1, 3, f"re-calibrating without {len(rejected)} outlier view(s)")
            L, R = [L[i] for i in keep], [R[i] for i in keep]
            rms_l, KL, dL, ev_l = _calibrate_camera(obj, L, image_size, flags)
            rms_r, KR, dR, ev_r = _calibrate_camera(obj, R, image_size, flags)
        if progress:
            progress(2, 3, "stereo extrinsics")
        out = _stereo_extrinsics(obj, L, R, (KL, dL), (KR, dR), image_size)
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV calibration failed: {exc.err}") from exc
    rms_s = float(out[0])
    Rm, T = np.asarray(out[5], np.float64), np.asarray(out[6], np.float64).reshape(3)
    per_view_stereo = np.asarray(out[-1], np.float64).reshape(len(L), -1)
    per_view = _first_pass_views(views, first_errors, bad, keep, per_view_stereo)
    quality = {
        "rms_left_px": rms_l,
        "rms_right_px": rms_r,
        "rms_stereo_px": rms_s,
        "per_view": _used_views([views[i] for i in keep], ev_l, ev_r, per_view_stereo),
        "rejected_views": [{"view": v, "reason": r} for v, r in rejected],
        "outlier_views": [views[i] for i in np.nonzero(bad)[0]],
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
        cal, len(corners_left), len(L), rms_l, rms_r, rms_s, rejected, elapsed_s=time.perf_counter() - t0,
        per_view=per_view,
    )


def _expand(pattern: str, side: str) -> list[str]:
    files = sorted(glob.glob(pattern))
    if not files:
        raise InputFileError(pattern, f"no {side} images match this pattern")
    return files


@dataclass
class _ImageSet:
    """What every image of the set must share (the first one read sets it)."""

    size: tuple[int, int] | None = None
    size_file: str = ""
    grey: bool | None = None
    grey_file: str = ""

    def check(self, path: str, img: U8Image, channels: int, partner: str | None) -> None:
        s = (img.shape[1], img.shape[0])
        if self.size is None:
            self.size, self.size_file = s, path
        elif s != self.size:
            other = partner if partner is not None else self.size_file
            raise CalibrationError(
                f"{path}: image is {s[0]}x{s[1]} but {other} is {self.size[0]}x{self.size[1]}; "
                "every image of a calibration must have the same size"
            )
        grey = channels == 1
        if self.grey is None:
            self.grey, self.grey_file = grey, path
        elif grey != self.grey:
            kind = "grey" if grey else f"colour ({channels} channels)"
            first = "grey" if self.grey else "colour"
            raise CalibrationError(
                f"{path}: a {kind} image, but {self.grey_file} is {first}; use one kind for every image"
            )


def _near_border(c: FloatArray, size: tuple[int, int], margin_px: float) -> bool:
    w, h = size
    return bool(
        np.any(c[:, 0] < margin_px) or np.any(c[:, 1] < margin_px)
        or np.any(c[:, 0] > w - 1 - margin_px) or np.any(c[:, 1] > h - 1 - margin_px)
    )


def _pair_reason(
    files: tuple[str, str], dets: tuple[BoardDetection, BoardDetection], settings: CalibrationSettings,
    size: tuple[int, int],
) -> str | None:
    """Why a pair cannot be used (None: usable): a board not found, or partly out of view."""
    board = f"{settings.board_cols}x{settings.board_rows}"
    for path, det in zip(files, dets, strict=True):
        if det.corners is None:
            how = "time budget used up" if det.out_of_budget else "no detector found it"
            return (f"{Path(path).name}: the {board} board was not found "
                    f"(tried {', '.join(det.tried)}; {how}; {det.elapsed_ms:.0f} ms)")
        if _near_border(det.corners, size, settings.edge_margin_px):
            return (f"{Path(path).name}: the board is partly out of view (a corner within "
                    f"{settings.edge_margin_px:g} px of the image border)")
    return None


def _paired_files(left_glob: str, right_glob: str) -> tuple[list[str], list[str]]:
    """The left and right image files, sorted by name (pair ``i`` is ``(left[i], right[i])``).

    Raises:
        InputFileError: a pattern matches nothing.
        CalibrationError: different counts (naming the first file without a partner).
    """
    lf, rf = _expand(left_glob, "left"), _expand(right_glob, "right")
    if len(lf) != len(rf):
        extra = lf[len(rf)] if len(lf) > len(rf) else rf[len(lf)]
        raise CalibrationError(
            f"{extra}: {len(lf)} left images but {len(rf)} right images (paired by sorted name); "
            "this is the first one without a partner"
        )
    return lf, rf


def _detect_pair(
    a: str, b: str, images: _ImageSet, settings: CalibrationSettings
) -> tuple[BoardDetection, BoardDetection]:
    """Read one left/right pair, check it against the set (size, grey/colour) and look for the
    board in each image (detection cascade within ``settings.detect_budget_s`` per image).

    Raises:
        InputFileError: an image cannot be read.
        CalibrationError: an image differs in size or kind from the first one.
    """
    ia, ch_a = load_grey_image_channels(a)
    ib, ch_b = load_grey_image_channels(b)
    images.check(a, ia, ch_a, None)
    images.check(b, ib, ch_b, a)
    return (
        detect_chessboard(ia, settings.board_cols, settings.board_rows, settings.detect_budget_s),
        detect_chessboard(ib, settings.board_cols, settings.board_rows, settings.detect_budget_s),
    )


def _fail_fast_if_no_board(
    last_file: str, n_pairs: int, records: list[dict[str, Any]], settings: CalibrationSettings
) -> None:
    """Stop when no image of the first ``n_pairs`` pairs (``records``) showed the board.

    Raises:
        CalibrationError: the board was found in none of them (a wrong ``--board`` size).
    """
    if all(r["detector"] is None for r in records):
        per_image_ms = sum(r["ms"] for r in records) / len(records)
        raise CalibrationError(
            f"{last_file}: the {settings.board_cols}x{settings.board_rows} board was not found in any "
            f"image of the first {n_pairs} pair(s) ({per_image_ms:.0f} ms per image); check --board "
            "(inner corners, COLSxROWS)"
        )


def calibrate_from_files(
    left_glob: str,
    right_glob: str,
    settings: CalibrationSettings = CalibrationSettings(),
    progress: Progress | None = None,
) -> CalibrationResult:
    """Calibrate from image files; left/right are paired by sorted file name.

    Every image is searched with the detection cascade (:func:`detect_chessboard`); a pair is
    used when both images show the whole board. Stops early when no image of the first
    ``settings.fail_fast_pairs`` pairs shows the board (a wrong board size).

    Raises:
        InputFileError: a pattern matches nothing, or an image cannot be read.
        CalibrationError: different left/right counts (naming the first file without a partner),
            an image of another size or another kind (grey / colour) than the first (naming both
            files), the board in none of the first pairs, too few usable pairs.
    """
    t0 = time.perf_counter()
    lf, rf = _paired_files(left_glob, right_glob)
    images = _ImageSet()
    cl: list[FloatArray] = []
    cr: list[FloatArray] = []
    names: list[str] = []
    missing: list[str] = []
    left_out: list[tuple[str, str]] = []
    records: list[dict[str, Any]] = []
    n = len(lf)
    for i, (a, b) in enumerate(zip(lf, rf, strict=True)):
        if progress:
            progress(i, n, f"corners {Path(a).name} / {Path(b).name}")
        dets = _detect_pair(a, b, images, settings)
        records += [dets[0].to_dict(a), dets[1].to_dict(b)]
        name = f"{Path(a).name}|{Path(b).name}"
        assert images.size is not None
        reason = _pair_reason((a, b), dets, settings, images.size)
        if reason is not None:
            if dets[0].corners is None or dets[1].corners is None:
                missing.append(name)
            left_out.append((name, reason))
            if i + 1 == settings.fail_fast_pairs and not cl:
                _fail_fast_if_no_board(a, i + 1, records, settings)
            continue
        ca, cb = dets[0].corners, dets[1].corners
        assert ca is not None
        assert cb is not None
        cl.append(ca)
        cr.append(cb)
        names.append(name)
    if progress:
        progress(n, n, f"board found in {len(cl)} of {n} pairs")
    size = images.size
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
        per_view=res.per_view,
        left_out=tuple(left_out),
        detections=tuple(records),
    )
