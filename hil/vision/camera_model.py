"""Stereo camera model: intrinsics, lens distortion, extrinsics, rectification, calibration file.

The optical frame is the left camera's frame (seed 001 section 4.1: "the left camera's optical
centre is used as the origin"): x right, y down, z along the optical axis, millimetres.
The right camera sees a point as ``p_right = R_right_from_left @ p_left + t_right_from_left_mm``
(seed 001 reports T ~ (-120, 0, -0.5) mm for its rig).

Lens distortion follows the Brown-Conrady model in OpenCV's order ``(k1, k2, p1, p2, k3)``
(seed 001 eq 9 keeps the radial terms; the tangential ones are kept here because Zhang's
calibration estimates them anyway).

The calibration file is versioned JSON; its schema is documented in docs/calibration-format.md.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import CalibrationError, InputFileError
from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]

CALIBRATION_SCHEMA = "hil.stereo_calibration"
CALIBRATION_VERSION = 1


def _mat(value: ArrayLike, shape: tuple[int, ...], name: str) -> FloatArray:
    arr = np.array(value, dtype=np.float64, copy=True)
    if arr.shape != shape:
        if arr.size == int(np.prod(shape)) and name.startswith("dist"):
            arr = arr.reshape(shape)
        else:
            raise CalibrationError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{name} contains NaN or infinite values")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class Rectification:
    """Rectifying rotations and projections (OpenCV ``stereoRectify`` conventions).

    ``R1``/``R2`` rotate the left/right camera frames into the rectified frames; ``P1``/``P2`` are
    the 3x4 projections of the rectified cameras (pixels, mm); ``Q`` maps (u, v, disparity, 1) to
    homogeneous 3D in the rectified left frame. After rectification corresponding points share
    the same row (seed 001 section 4.1, "binocular correction").
    """

    R1: FloatArray
    R2: FloatArray
    P1: FloatArray
    P2: FloatArray
    Q: FloatArray


@dataclass(frozen=True)
class RigConstants:
    """Matrices derived from a calibration, computed once (read-only): the projections of
    :meth:`StereoCalibration.P_left` / ``P_right``, the inverse intrinsics, the right camera's
    centre in the optical frame (mm) and whether each camera has lens distortion."""

    P_left: FloatArray
    P_right: FloatArray
    K_left_inv: FloatArray
    K_right_inv: FloatArray
    right_center_mm: FloatArray
    distorted_left: bool
    distorted_right: bool


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """A calibrated stereo rig. Immutable; arrays are read-only float64.

    Attributes:
        image_size: (width, height) in pixels, the same for both cameras.
        K_left, K_right: 3x3 intrinsic matrices (pixels).
        dist_left, dist_right: (5,) distortion ``(k1, k2, p1, p2, k3)``.
        R_right_from_left: 3x3 rotation, left camera frame -> right camera frame.
        t_right_from_left_mm: (3,) translation, mm.
        quality: calibration figures (rms, per-view errors), free-form, saved with the file.
        settings: the settings the calibration was computed with, free-form.

    Raises:
        CalibrationError: any matrix of the wrong shape, non-finite, or a non-rotation.
    """

    image_size: tuple[int, int]
    K_left: FloatArray
    dist_left: FloatArray
    K_right: FloatArray
    dist_right: FloatArray
    R_right_from_left: FloatArray
    t_right_from_left_mm: FloatArray
    quality: dict[str, Any] = field(default_factory=dict)
    settings: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        w, h = self.image_size
        if int(w) != w or int(h) != h or w <= 0 or h <= 0:
            raise CalibrationError(f"image_size must be two positive integers, got {self.image_size}")
        object.__setattr__(self, "image_size", (int(w), int(h)))
        for name, shape in (
            ("K_left", (3, 3)),
            ("dist_left", (5,)),
            ("K_right", (3, 3)),
            ("dist_right", (5,)),
            ("R_right_from_left", (3, 3)),
            ("t_right_from_left_mm", (3,)),
        ):
            object.__setattr__(self, name, _mat(getattr(self, name), shape, name))
        for name in ("K_left", "K_right"):
            K = getattr(self, name)
            if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
                raise CalibrationError(f"{name} is not an intrinsic matrix (fx, fy > 0, last row 0 0 1)")
        R = self.R_right_from_left
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise CalibrationError("R_right_from_left is not a proper rotation")
        if float(np.linalg.norm(self.t_right_from_left_mm)) <= 0.0:
            raise CalibrationError("t_right_from_left_mm is zero: the two cameras coincide")

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def synthetic(
        cls,
        f_px: float = 1394.0,
        baseline_mm: float = 120.0,
        image_size: tuple[int, int] = (1920, 1080),
        dist: ArrayLike | None = None,
    ) -> StereoCalibration:
        """A seed-001-like rig: two identical parallel cameras, principal point at the image centre,
        the right camera translated along +x of the left one by ``baseline_mm``.

        ``dist`` (5,) applies to both cameras; None means no distortion.
        """
        w, h = image_size
        K = np.array([[f_px, 0.0, (w - 1) / 2.0], [0.0, f_px, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        d = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
        return cls(
            image_size=(w, h),
            K_left=K,
            dist_left=d,
            K_right=K.copy(),
            dist_right=d.copy(),
            R_right_from_left=np.eye(3),
            t_right_from_left_mm=np.array([-baseline_mm, 0.0, 0.0]),
            settings={"source": "synthetic", "f_px": f_px, "baseline_mm": baseline_mm},
        )

    # ---- geometry -----------------------------------------------------------------------
    @property
    def T_right_from_left(self) -> RigidTransform:
        return RigidTransform(self.R_right_from_left, self.t_right_from_left_mm)

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.t_right_from_left_mm))

    @property
    def right_center_mm(self) -> FloatArray:
        """The right camera's optical centre in the optical (left) frame, mm."""
        return np.asarray(-self.R_right_from_left.T @ self.t_right_from_left_mm, dtype=np.float64)

    def P_left(self) -> FloatArray:
        """3x4 projection of the left (undistorted) camera: pixels from optical-frame mm."""
        return np.asarray(self.K_left @ np.hstack([np.eye(3), np.zeros((3, 1))]), dtype=np.float64)

    def P_right(self) -> FloatArray:
        """3x4 projection of the right (undistorted) camera: pixels from optical-frame mm."""
        Rt = np.hstack([self.R_right_from_left, self.t_right_from_left_mm.reshape(3, 1)])
        return np.asarray(self.K_right @ Rt, dtype=np.float64)

    def camera(self, side: str) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """(K, dist, R_cam_from_optical, t_cam_from_optical_mm) of ``side`` ("left"/"right")."""
        if side == "left":
            return self.K_left, self.dist_left, np.eye(3), np.zeros(3)
        if side == "right":
            return self.K_right, self.dist_right, self.R_right_from_left, self.t_right_from_left_mm
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")

    def project(self, points_optical_mm: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Project (N, 3) optical-frame points into both images, with lens distortion.

        Returns (uv_left (N, 2), uv_right (N, 2)) in pixels. Points behind a camera give NaN.
        """
        p = np.asarray(points_optical_mm, dtype=np.float64).reshape(-1, 3)
        uv_l = project_points(p, self.K_left, self.dist_left)
        p_r = p @ self.R_right_from_left.T + self.t_right_from_left_mm
        uv_r = project_points(p_r, self.K_right, self.dist_right)
        return uv_l, uv_r

    def undistort_points(self, side: str, uv_px: ArrayLike) -> FloatArray:
        """Remove lens distortion from (N, 2) pixel points of ``side``; returns ideal pixels (N, 2)."""
        K, dist, _, _ = self.camera(side)
        return undistort_pixels(np.asarray(uv_px, dtype=np.float64).reshape(-1, 2), K, dist)

    @cached_property
    def constants(self) -> RigConstants:
        """The derived matrices of :class:`RigConstants` (computed on first use)."""
        def frozen(a: ArrayLike) -> FloatArray:
            out = np.array(a, dtype=np.float64)
            out.setflags(write=False)
            return out

        return RigConstants(
            frozen(self.P_left()), frozen(self.P_right()), frozen(np.linalg.inv(self.K_left)),
            frozen(np.linalg.inv(self.K_right)), frozen(self.right_center_mm),
            bool(np.any(self.dist_left)), bool(np.any(self.dist_right)),
        )

    @cached_property
    def rectification(self) -> Rectification:
        """Rectification (computed once, with ``alpha=0`` and zero disparity at infinity)."""
        R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(
            self.K_left,
            self.dist_left,
            self.K_right,
            self.dist_right,
            self.image_size,
            self.R_right_from_left,
            self.t_right_from_left_mm.reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=0.0,
        )
        return Rectification(*(np.asarray(m, dtype=np.float64) for m in (R1, R2, P1, P2, Q)))


# ---- distortion -------------------------------------------------------------------------
def distort_normalized(xy: FloatArray, dist: FloatArray) -> FloatArray:
    """Apply Brown-Conrady distortion ``(k1, k2, p1, p2, k3)`` to (N, 2) normalised coordinates."""
    k1, k2, p1, p2, k3 = (float(v) for v in dist)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def undistort_normalized(xy_d: FloatArray, dist: FloatArray, iterations: int = 20) -> FloatArray:
    """Invert :func:`distort_normalized` by fixed-point iteration (exact to ~1e-12 for lens-like
    distortion within the image). (N, 2) -> (N, 2).

    The iteration is OpenCV's ``undistortPoints`` with an identity camera and a fixed iteration
    count (the same fixed point ``x = (x_d - tangential(x)) / radial(x)``, in C++)."""
    if not np.any(dist) or xy_d.shape[0] == 0:
        return np.array(xy_d, dtype=np.float64, copy=True)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-15)
    eye = np.eye(3)
    pts = np.ascontiguousarray(xy_d, dtype=np.float64).reshape(-1, 1, 2)
    out = cv2.undistortPoints(pts, eye, np.asarray(dist, dtype=np.float64), R=eye, P=eye, criteria=crit)
    return np.asarray(out.reshape(-1, 2), dtype=np.float64)


def project_points(points_cam_mm: FloatArray, K: FloatArray, dist: FloatArray) -> FloatArray:
    """Pinhole + distortion projection of (N, 3) camera-frame points to (N, 2) pixels.

    Points with z <= 0 give NaN (behind the camera).
    """
    z = points_cam_mm[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = points_cam_mm[:, :2] / z[:, None]
    xy[z <= 0] = np.nan
    xy_d = distort_normalized(xy, dist) if np.any(dist) else xy
    u = K[0, 0] * xy_d[:, 0] + K[0, 1] * xy_d[:, 1] + K[0, 2]
    v = K[1, 1] * xy_d[:, 1] + K[1, 2]
    return np.stack([u, v], axis=1)


def pixels_to_normalized(uv_px: FloatArray, K: FloatArray) -> FloatArray:
    y = (uv_px[:, 1] - K[1, 2]) / K[1, 1]
    x = (uv_px[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return np.stack([x, y], axis=1)


def undistort_pixels(uv_px: FloatArray, K: FloatArray, dist: FloatArray) -> FloatArray:
    """Distorted pixels -> ideal (undistorted) pixels of the same K. (N, 2) -> (N, 2)."""
    if not np.any(dist):
        return uv_px.astype(np.float64, copy=True)
    xy = undistort_normalized(pixels_to_normalized(uv_px, K), dist)
    u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
    v = K[1, 1] * xy[:, 1] + K[1, 2]
    return np.stack([u, v], axis=1)


def distort_pixels(uv_px: FloatArray, K: FloatArray, dist: FloatArray) -> FloatArray:
    """Ideal (undistorted) pixels -> distorted pixels of the same K. (N, 2) -> (N, 2)."""
    if not np.any(dist):
        return uv_px.astype(np.float64, copy=True)
    xy = distort_normalized(pixels_to_normalized(uv_px, K), dist)
    u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
    v = K[1, 1] * xy[:, 1] + K[1, 2]
    return np.stack([u, v], axis=1)


# ---- file -------------------------------------------------------------------------------
def _tolist(a: FloatArray) -> Any:
    return np.asarray(a, dtype=np.float64).tolist()


def calibration_to_dict(cal: StereoCalibration) -> dict[str, Any]:
    """The JSON document of ``cal`` (schema in docs/calibration-format.md)."""
    rect = cal.rectification
    return {
        "schema": CALIBRATION_SCHEMA,
        "version": CALIBRATION_VERSION,
        "units": {"length": "mm", "image": "px"},
        "image_size": {"width": cal.image_size[0], "height": cal.image_size[1]},
        "left": {"K": _tolist(cal.K_left), "dist": _tolist(cal.dist_left)},
        "right": {"K": _tolist(cal.K_right), "dist": _tolist(cal.dist_right)},
        "R_right_from_left": _tolist(cal.R_right_from_left),
        "t_right_from_left_mm": _tolist(cal.t_right_from_left_mm),
        "rectification": {
            "R1": _tolist(rect.R1),
            "R2": _tolist(rect.R2),
            "P1": _tolist(rect.P1),
            "P2": _tolist(rect.P2),
            "Q": _tolist(rect.Q),
        },
        "quality": cal.quality,
        "settings": cal.settings,
    }


def save_calibration(cal: StereoCalibration, path: str | Path) -> None:
    """Write ``cal`` as versioned JSON to ``path`` (atomically: temp file + rename).

    Raises:
        InputFileError: the file cannot be written.
    """
    p = Path(path)
    text = json.dumps(calibration_to_dict(cal), indent=2, allow_nan=False)
    tmp = p.with_name(p.name + ".tmp")
    try:
        tmp.write_text(text + "\n", encoding="utf-8")
        tmp.replace(p)
    except OSError as exc:
        raise InputFileError(str(path), f"cannot write calibration: {exc.strerror or exc}") from exc


def _field(doc: dict[str, Any], key: str, path: str) -> Any:
    node: Any = doc
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            raise CalibrationError(f"{path}: missing field '{key}'")
        node = node[part]
    return node


def _array_field(doc: dict[str, Any], key: str, shape: tuple[int, ...], path: str) -> FloatArray:
    raw = _field(doc, key, path)
    try:
        arr = np.array(raw, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise CalibrationError(f"{path}: field '{key}' is not a numeric array") from exc
    if arr.shape != shape:
        raise CalibrationError(f"{path}: field '{key}' must have shape {list(shape)}, got {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{path}: field '{key}' contains NaN or infinite values")
    return arr


def calibration_from_dict(doc: Any, path: str = "<calibration>") -> StereoCalibration:
    """Parse a calibration document. Raises CalibrationError naming ``path`` and the field."""
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: top level must be a JSON object")
    schema = doc.get("schema")
    if schema != CALIBRATION_SCHEMA:
        raise CalibrationError(f"{path}: field 'schema' must be '{CALIBRATION_SCHEMA}', got {schema!r}")
    version = doc.get("version")
    if version != CALIBRATION_VERSION:
        raise CalibrationError(
            f"{path}: field 'version' is {version!r}; this program reads version {CALIBRATION_VERSION}"
        )
    w, h = _field(doc, "image_size.width", path), _field(doc, "image_size.height", path)
    if not all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 100_000 for v in (w, h)):
        raise CalibrationError(f"{path}: field 'image_size' must hold integers in 1..100000, got {w!r}x{h!r}")
    quality = doc.get("quality", {})
    settings = doc.get("settings", {})
    if not isinstance(quality, dict) or not isinstance(settings, dict):
        raise CalibrationError(f"{path}: fields 'quality' and 'settings' must be JSON objects")
    try:
        return StereoCalibration(
            image_size=(w, h),
            K_left=_array_field(doc, "left.K", (3, 3), path),
            dist_left=_array_field(doc, "left.dist", (5,), path),
            K_right=_array_field(doc, "right.K", (3, 3), path),
            dist_right=_array_field(doc, "right.dist", (5,), path),
            R_right_from_left=_array_field(doc, "R_right_from_left", (3, 3), path),
            t_right_from_left_mm=_array_field(doc, "t_right_from_left_mm", (3,), path),
            quality=quality,
            settings=settings,
        )
    except CalibrationError as exc:
        msg = str(exc)
        raise CalibrationError(msg if msg.startswith(path) else f"{path}: {msg}") from exc


def load_calibration(path: str | Path) -> StereoCalibration:
    """Read a calibration file written by :func:`save_calibration` (or by hand, same schema).

    Raises:
        InputFileError: the file is missing, unreadable or not JSON.
        CalibrationError: the JSON does not match the schema (names the file and field).
    """
    p = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise InputFileError(p, "calibration file not found") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(p, f"cannot read calibration file: {exc}") from exc
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(p, f"not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from exc
    except ValueError as exc:  # e.g. an integer literal beyond Python's digit limit
        raise InputFileError(p, f"not usable JSON: {exc}") from exc
    except RecursionError as exc:
        raise InputFileError(p, "not usable JSON: nested too deeply") from exc
    return calibration_from_dict(doc, p)


def angle_between_rad(a: ArrayLike, b: ArrayLike) -> float:
    """Angle between two 3-vectors in radians (helper for tests and reports)."""
    va, vb = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c = float(va @ vb / (np.linalg.norm(va) * np.linalg.norm(vb)))
    return math.acos(max(-1.0, min(1.0, c)))
