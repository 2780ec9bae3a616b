"""REGISTER: image -> optical from the skin markers, robot -> optical from the flange markers.

- Patient (seed 000 section 2.2, eqs 13-21; seed 002 eq 24): N frames of triangulated markers
  are identified against the CT fiducials (correspondence-free matching), averaged per
  fiducial, and registered with Horn's method: ``T_optical_from_image``, FRE, and the expected
  TRE at the target (Fitzpatrick-West-Maurer). The averaged marker set is the **reference marker
  state** (recorded during a breath-hold) used by the gate and the compensation.
- Robot (seed 000 eqs 7-11 in spirit — markers on the robot end seen by the camera — solved
  with Horn on the whole flange marker layout): the flange markers are known in the TCP frame;
  the robot reports ``T_robot_from_tcp``; their optical positions give ``T_robot_from_optical``.
  Frames from several robot poses may be stacked.
- The chain (seed 000 eq 12, seed 002 eq 24): ``T_robot_from_image = T_robot_from_optical @
  T_optical_from_image``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from hil.controller.config import RegistrationConfig, StereotaxyRegistrationConfig
from hil.controller.plan_file import ProcedurePlan
from hil.errors import GeometryError, HilError
from hil.geometry import native
from hil.geometry.matching import match_markers
from hil.geometry.registration import register_horn
from hil.geometry.stereotaxy import load_frame, load_spots, register_single_slice, robot_from_image_via_frame
from hil.geometry.transform import RigidTransform
from hil.geometry.tre import expected_tre_mm

if TYPE_CHECKING:
    from hil.controller.registration_breathing import RegistrationBreathing

FloatArray = NDArray[np.float64]


class RegistrationFailedError(HilError):
    """Registration cannot be accepted; ``reason`` says why."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(f"registration failed: {reason}")


def identify(points_mm: FloatArray, model_mm: FloatArray, tolerance_mm: float,
             min_matched: int = 3) -> FloatArray | None:
    """Rows of ``points_mm`` put in model order (NaN rows for model markers not found), or
    None when no consistent match of ``min_matched`` markers exists."""
    if points_mm.shape[0] < min_matched:
        return None
    try:
        m = match_markers(points_mm, model_mm, tolerance_mm=tolerance_mm, min_matched=min_matched)
    except GeometryError:
        return None
    if m.ambiguous:
        return None
    out = np.full((model_mm.shape[0], 3), np.nan)
    for model_i, meas_i in m.model_to_measured.items():
        out[model_i] = points_mm[meas_i]
    return out


def track(points_mm: FloatArray, predicted_mm: FloatArray, tolerance_mm: float) -> FloatArray:
    """Fast frame-to-frame identification: each predicted marker (NaN rows skipped) takes the
    nearest measured point within ``tolerance_mm``, uniquely (greedy by distance). Rows with
    no point stay NaN. Runs compiled (:mod:`hil.geometry.native`) for (N, 3) float64 input,
    else :func:`track_numpy`; the two agree exactly (tests/geometry/test_native.py)."""
    k = native.active()
    if (k is not None and points_mm.dtype == np.float64 and predicted_mm.dtype == np.float64
            and points_mm.ndim == 2 and predicted_mm.ndim == 2
            and points_mm.shape[1] == 3 and predicted_mm.shape[1] == 3):
        out = np.empty(predicted_mm.shape)
        if k.track(np.ascontiguousarray(points_mm), np.ascontiguousarray(predicted_mm), float(tolerance_mm),
                   out):
            return out
    return track_numpy(points_mm, predicted_mm, tolerance_mm)


def track_numpy(points_mm: FloatArray, predicted_mm: FloatArray, tolerance_mm: float) -> FloatArray:
    """:func:`track` in numpy (the reference of the compiled code)."""
    out = np.full(predicted_mm.shape, np.nan)
    if points_mm.shape[0] == 0:
        return out
    valid = np.all(np.isfinite(predicted_mm), axis=1)
    d = np.linalg.norm(predicted_mm[:, None, :] - points_mm[None, :, :], axis=2)
    d[~valid] = np.inf
    used_r: set[int] = set()
    used_c: set[int] = set()
    for flat in np.argsort(d, axis=None):
        r, c = divmod(int(flat), points_mm.shape[0])
        if d[r, c] > tolerance_mm:
            break
        if r in used_r or c in used_c:
            continue
        out[r] = points_mm[c]
        used_r.add(r)
        used_c.add(c)
    return out


def average_identified(sets: Sequence[FloatArray], min_fraction: float = 0.5) -> FloatArray:
    """Per-marker mean over frames (rows in model order, NaN = not seen); a marker seen in fewer
    than ``min_fraction`` of the frames stays NaN."""
    stack = np.stack(sets)  # (F, N, 3)
    seen = np.all(np.isfinite(stack), axis=2)  # (F, N)
    count = seen.sum(axis=0)
    out = np.full(stack.shape[1:], np.nan)
    for i in range(stack.shape[1]):
        if count[i] >= max(1, min_fraction * stack.shape[0]):
            out[i] = stack[seen[:, i], i].mean(axis=0)
    return out


@dataclass(frozen=True)
class PatientRegistration:
    """Image -> optical registration and the reference marker state.

    Attributes:
        T_optical_from_image: the registration: Horn's fit of the fiducials, or, with a 4D CT's
            breathing model, the plan's path moved to the breathing state at registration
            (hil/controller/registration_breathing.py; Horn's is then in ``breathing``).
        fre_rms_mm: fiducial registration error (Horn's fit).
        tre_expected_mm: expected RMS TRE at the target for the configured FLE.
        reference_optical_mm: (N, 3) averaged marker positions, CT fiducial order (NaN: unseen).
        markers_used: how many fiducials entered the registration.
        frames: how many frames were averaged.
        breathing: the breathing state found at registration and what it changed (None without a
            4D CT's breathing model).
    """

    T_optical_from_image: RigidTransform
    fre_rms_mm: float
    tre_expected_mm: float
    reference_optical_mm: FloatArray
    markers_used: int
    frames: int
    breathing: RegistrationBreathing | None = None


def register_patient(frames_identified: Sequence[FloatArray], plan: ProcedurePlan,
                     cfg: RegistrationConfig) -> PatientRegistration:
    """Average the identified frames and register image -> optical; check FRE and expected TRE.

    Raises:
        RegistrationFailedError: too few markers, degenerate layout, FRE or TRE over threshold.
    """
    if not frames_identified:
        raise RegistrationFailedError("no frame with identified skin markers")
    ref = average_identified(frames_identified)
    ok = np.all(np.isfinite(ref), axis=1)
    n = int(ok.sum())
    if n < cfg.min_markers:
        raise RegistrationFailedError(f"only {n} skin markers identified reliably (need {cfg.min_markers})")
    try:
        reg = register_horn(ref[ok], plan.fiducials_mm[ok])
    except GeometryError as exc:
        raise RegistrationFailedError(f"skin markers do not fix a transform: {exc}") from None
    tre = expected_tre_mm(plan.fiducials_mm[ok], plan.target_mm, cfg.fle_rms_mm)
    if reg.fre_rms_mm > cfg.fre_max_mm:
        raise RegistrationFailedError(f"FRE {reg.fre_rms_mm:.3f} mm exceeds {cfg.fre_max_mm} mm")
    if tre > cfg.tre_max_mm:
        raise RegistrationFailedError(f"expected TRE at the target {tre:.3f} mm exceeds {cfg.tre_max_mm} mm")
    return PatientRegistration(reg.T_fixed_from_moving, reg.fre_rms_mm, tre, ref, n, len(frames_identified))


@dataclass(frozen=True)
class RobotRegistration:
    """Robot -> optical registration.

    Attributes:
        T_robot_from_optical: the registration.
        fre_rms_mm: RMS residual of the flange markers (stereotaxy: of the slice's spots to their rods).
        pairs: marker observations (stereotaxy: spots) used.
        method: "flange_markers" or "stereotaxy".
    """

    T_robot_from_optical: RigidTransform
    fre_rms_mm: float
    pairs: int
    method: str = "flange_markers"


def register_robot(flange_optical: Sequence[FloatArray], T_robot_from_tcp: Sequence[RigidTransform],
                   markers_tcp_mm: FloatArray) -> RobotRegistration:
    """Horn on the flange marker layout, stacked over frames.

    Args:
        flange_optical: per frame, (M, 3) flange markers in model order (NaN: unseen), optical.
        T_robot_from_tcp: per frame, the robot's reported TCP pose at that frame's time.
        markers_tcp_mm: (M, 3) the marker layout in the TCP frame.

    Raises:
        RegistrationFailedError: fewer than 3 usable pairs or a degenerate set.
    """
    opt: list[FloatArray] = []
    rob: list[FloatArray] = []
    for pts, T in zip(flange_optical, T_robot_from_tcp, strict=True):
        ok = np.all(np.isfinite(pts), axis=1)
        opt.append(pts[ok])
        rob.append(T.apply(markers_tcp_mm[ok]))
    if not opt or sum(len(o) for o in opt) < 3:
        raise RegistrationFailedError("flange markers not seen (fewer than 3 observations)")
    try:
        reg = register_horn(np.concatenate(rob), np.concatenate(opt))
    except GeometryError as exc:
        raise RegistrationFailedError(f"flange markers do not fix a transform: {exc}") from None
    return RobotRegistration(reg.T_fixed_from_moving, reg.fre_rms_mm, int(sum(len(o) for o in opt)))


def register_robot_via_stereotaxy(cfg: StereotaxyRegistrationConfig,
                                  T_optical_from_image: RigidTransform) -> RobotRegistration:
    """Robot -> optical through the rod frame the robot carried in the scanner (seed 004 §IV, the
    CT-Bot route): ``T_robot_from_image`` from one slice's spots
    (:func:`hil.geometry.stereotaxy.register_single_slice`,
    :func:`hil.geometry.stereotaxy.robot_from_image_via_frame`), then
    ``T_robot_from_optical = T_robot_from_image @ T_image_from_optical`` with the skin-marker
    registration. Reads the two files (blocking, small).

    Raises:
        RegistrationFailedError: a file is unreadable or invalid, a spot names an unknown rod, the
            slice does not fix the pose, or the RMS residual exceeds ``cfg.max_residual_mm``.
    """
    try:
        frame = load_frame(cfg.frame)
        spots = load_spots(cfg.spots)
        rods = [frame.rod(rid) for rid in spots.rod_ids]
        pixel = cfg.pixel_mm if cfg.pixel_mm is not None else spots.pixel_mm
        res = register_single_slice(rods, spots.uv_px, pixel, slice_z_mm=spots.slice_z_mm, refine=cfg.refine)
    except HilError as exc:
        raise RegistrationFailedError(f"stereotaxy: {exc}") from None
    if res.rms_mm > cfg.max_residual_mm:
        raise RegistrationFailedError(
            f"stereotaxy residual {res.rms_mm:.3f} mm RMS exceeds {cfg.max_residual_mm} mm")
    tcp, mount = cfg.robot_tcp_at_scan, cfg.tcp_from_frame
    T_robot_from_image = robot_from_image_via_frame(
        res.T_scanner_from_frame, RigidTransform.from_rotvec(tcp[3:], tcp[:3]),
        RigidTransform.from_rotvec(mount[3:], mount[:3]))
    return RobotRegistration(T_robot_from_image @ T_optical_from_image.inverse(), res.rms_mm, len(rods),
                             "stereotaxy")
