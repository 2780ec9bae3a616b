"""Recorded hand-eye samples: the pose pairs (or unsynchronised pose streams) a file holds, and
the checks every reader applies before anything is solved (docs/rig-calibration.md, "Offline").

Frames and units (the issue 43 conventions):

* robot poses are ``T_base_from_flange`` (the flange, or whatever hand frame the file names, in
  the robot base frame);
* tracker/camera poses are ``T_camera_from_target`` (the target, or marker body, in the camera's
  frame);
* after reading, every translation is in millimetres; files may hold metres or millimetres, told
  apart by the translations' size (:func:`length_scale_to_mm`), never guessed when unclear.

Every problem is an :class:`SamplesError` (a :class:`hil.errors.InputFileError`) whose message is
one line naming the file, the line (or pair index) and the problem.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil.errors import InputFileError
from hil.geometry.transform import matrix_to_rotvec

FloatArray = NDArray[np.float64]

#: tolerance on ``|R^T R - I|`` (max abs entry) and ``|det R - 1|`` of a read rotation matrix
ROTATION_TOL = 1e-3
#: tolerance on ``| |q| - 1 |`` of a read quaternion
QUATERNION_TOL = 1e-3
#: a stream whose median translation norm lies in this range (metres) is read as metres ...
METRE_RANGE = (0.01, 5.0)
#: ... and in this range (millimetres) as millimetres; anything else is refused
MILLIMETRE_RANGE = (20.0, 5000.0)
MIN_PAIRS = 6
#: the rotations must spread over >= this angle (deg) between two robot poses ...
MIN_ROTATION_DEG = 5.0
#: ... and about two clearly different axes (second over first singular value of the rotation
#: vectors between the robot poses)
MIN_AXIS_SPREAD = 0.1


class SamplesError(InputFileError):
    """A samples file cannot be used; ``reason`` names the line or pair and the problem."""


@dataclass(frozen=True)
class PoseStream:
    """One timed pose stream (unsynchronised recordings).

    Attributes:
        t_s: (N,) sample times, seconds, strictly increasing.
        T: (N, 4, 4) poses, translations in mm.
        where: (N,) where each sample is in the file (``"line 12"``), for messages.
    """

    t_s: FloatArray
    T: FloatArray
    where: tuple[str, ...]


@dataclass(frozen=True)
class PosePairs:
    """Synchronised pose pairs.

    Attributes:
        T_base_from_flange: (N, 4, 4) robot poses, mm.
        T_camera_from_target: (N, 4, 4) camera/tracker poses, mm.
        where: (N,) each pair's place in the file (``"line 7"``, ``"pair 3"``), for messages.
        t_s: (N,) pair times (s) when the file has them, else None.
    """

    T_base_from_flange: FloatArray
    T_camera_from_target: FloatArray
    where: tuple[str, ...]
    t_s: FloatArray | None = None

    def __len__(self) -> int:
        return int(self.T_base_from_flange.shape[0])

    def subset(self, idx: NDArray[np.int64]) -> PosePairs:
        """The pairs at ``idx`` (in that order)."""
        return PosePairs(self.T_base_from_flange[idx], self.T_camera_from_target[idx],
                         tuple(self.where[i] for i in idx),
                         None if self.t_s is None else self.t_s[idx])


@dataclass(frozen=True)
class RecordedStreams:
    """Two unsynchronised streams, to be aligned (:mod:`hil.rigcal.streams`)."""

    robot: PoseStream
    camera: PoseStream


def transform(R: FloatArray, t: FloatArray) -> FloatArray:
    """The 4x4 homogeneous matrix of rotation ``R`` and translation ``t``."""
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = t
    return M


def inverse(T: FloatArray) -> FloatArray:
    """Inverse of one (4, 4) or a stack (N, 4, 4) of rigid transforms."""
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = R
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def check_finite(values: FloatArray, path: str, where: str) -> None:
    """Raises SamplesError naming ``where`` when a value is NaN or infinite."""
    if not np.all(np.isfinite(values)):
        raise SamplesError(path, f"{where}: not a finite number (NaN or inf)")


def check_rotation(R: FloatArray, path: str, where: str) -> FloatArray:
    """``R`` when it is a rotation within :data:`ROTATION_TOL` (orthonormal, det +1), projected
    exactly onto SO(3) (SVD); else SamplesError naming ``where``."""
    check_finite(R, path, where)
    ortho = float(np.max(np.abs(R.T @ R - np.eye(3))))
    det = float(np.linalg.det(R))
    if ortho > ROTATION_TOL:
        raise SamplesError(path, f"{where}: the rotation is not orthonormal (|R^T R - I| = {ortho:.2g} "
                                 f"> {ROTATION_TOL:g})")
    if abs(det - 1.0) > ROTATION_TOL:
        raise SamplesError(path, f"{where}: the rotation has determinant {det:.3f}, not +1 "
                                 "(a reflection)")
    u, _, vt = np.linalg.svd(R)
    out: FloatArray = u @ vt
    return out


def quaternion_xyzw_to_matrix(q_xyzw: FloatArray, path: str, where: str) -> FloatArray:
    """The rotation of the Hamilton quaternion ``(qx, qy, qz, qw)`` (scalar last), which must
    have unit norm within :data:`QUATERNION_TOL`; else SamplesError naming ``where``."""
    check_finite(q_xyzw, path, where)
    n = float(np.linalg.norm(q_xyzw))
    if abs(n - 1.0) > QUATERNION_TOL:
        raise SamplesError(path, f"{where}: the quaternion has norm {n:.4f}, not 1 "
                                 f"(tolerance {QUATERNION_TOL:g}; order is qx, qy, qz, qw)")
    x, y, z, w = (q_xyzw / n).tolist()
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def length_scale_to_mm(T: FloatArray, path: str, stream: str) -> float:
    """1000 when the stream's translations are metres, 1 when millimetres, judged from their
    median norm (:data:`METRE_RANGE`, :data:`MILLIMETRE_RANGE`).

    Raises:
        SamplesError: the median norm fits neither range (units cannot be told).
    """
    med = float(np.median(np.linalg.norm(T[:, :3, 3], axis=1)))
    if METRE_RANGE[0] <= med <= METRE_RANGE[1]:
        return 1000.0
    if MILLIMETRE_RANGE[0] <= med <= MILLIMETRE_RANGE[1]:
        return 1.0
    raise SamplesError(path, f"{stream} poses: units cannot be told: the median translation is {med:.4g} "
                             f"(metres expected in {METRE_RANGE[0]:g}..{METRE_RANGE[1]:g}, millimetres "
                             f"in {MILLIMETRE_RANGE[0]:g}..{MILLIMETRE_RANGE[1]:g})")


def to_mm(T: FloatArray, path: str, stream: str) -> FloatArray:
    """A copy of ``T`` (N, 4, 4) with translations in mm (:func:`length_scale_to_mm`)."""
    out = T.copy()
    out[:, :3, 3] *= length_scale_to_mm(T, path, stream)
    return out


def make_pairs(T_robot: FloatArray, T_camera: FloatArray, where: tuple[str, ...], path: str,
               t_s: FloatArray | None = None) -> PosePairs:
    """Pairs from raw poses in the file's units: counts checked, units converted to mm.

    Raises:
        SamplesError: no pairs, mismatched counts, units that cannot be told.
    """
    if len(T_robot) == 0 and len(T_camera) == 0:
        raise SamplesError(path, "no pose pairs in the file")
    if len(T_robot) != len(T_camera):
        raise SamplesError(path, f"mismatched counts: {len(T_robot)} robot poses but {len(T_camera)} "
                                 "camera poses")
    return PosePairs(to_mm(T_robot, path, "robot"), to_mm(T_camera, path, "camera"), where, t_s)


def check_motion(pairs: PosePairs, path: str, min_pairs: int = MIN_PAIRS) -> None:
    """Refuse pair sets that cannot fix a hand-eye calibration: fewer than ``min_pairs``, robot
    rotations spreading less than :data:`MIN_ROTATION_DEG`, or all about one axis (a hand-eye
    rotation axis leaves the translation along it undetermined; Tsai & Lenz 1989, sec. III).

    Raises:
        SamplesError: naming the problem (and the single axis, robot base frame).
    """
    n = len(pairs)
    if n < min_pairs:
        raise SamplesError(path, f"too few pairs: {n} (need >= {min_pairs})")
    R = pairs.T_base_from_flange[:, :3, :3]
    step = max(1, n // 60)
    Rs = R[::step]
    vecs = []
    for i in range(len(Rs)):
        for j in range(i + 1, len(Rs)):
            vecs.append(matrix_to_rotvec(Rs[j] @ Rs[i].T))
    V = np.array(vecs)
    angles = np.linalg.norm(V, axis=1)
    spread = float(np.degrees(angles.max()))
    if spread < MIN_ROTATION_DEG:
        raise SamplesError(path, f"degenerate motion: the robot rotates at most {spread:.2f} deg between "
                                 f"two poses (need >= {MIN_ROTATION_DEG:g} deg)")
    sv = np.linalg.svd(V, compute_uv=False)
    ratio = float(sv[1] / sv[0])
    if ratio < MIN_AXIS_SPREAD:
        _, _, vt = np.linalg.svd(V)
        raise SamplesError(path, "degenerate motion: the robot rotates (almost) only about the axis "
                                 f"{np.round(vt[0], 2).tolist()} (base frame; spread ratio {ratio:.3f} "
                                 f"< {MIN_AXIS_SPREAD:g}); add poses tilted about another axis")

