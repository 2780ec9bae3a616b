"""``hil rig-calibrate``'s procedure on a setup's devices: hand-eye poses, temporal motion, the
file, and the figures. Goes through the driver interfaces only (simulator, tools/ursim, a UR).
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hil.clock import Clock
from hil.config.build import Devices
from hil.config.setup import SetupConfig
from hil.controller.assembly import stereo_calibration
from hil.controller.perception import StereoMarkerLocator
from hil.errors import InputFileError
from hil.geometry.transform import RigidTransform
from hil.log import get_logger
from hil.rigcal.collect import Confirm, PoseCollector
from hil.rigcal.handeye import HandEyeResult, PoseSample, RigCalibrationError, SolverSettings, solve_hand_eye
from hil.rigcal.poses import calibration_poses, check_poses
from hil.rigcal.rigfile import (
    SCHEMA,
    VERSION,
    RigCalibration,
    TimeOffset,
    load_rig_calibration,
    save_rig_calibration,
)
from hil.rigcal.temporal import TemporalRecorder, offsets_from_recording
from hil.rigcal.truth import RigTruthSource
from hil.session.log import file_sha256
from hil.vision.camera_model import StereoCalibration

FloatArray = NDArray[np.float64]
_log = get_logger(__name__)
EV_WRITTEN = "rigcal_written"


@dataclass
class RigCalibrationOutcome:
    """What a run gave: the summary (the ``--json`` object) and the file written."""

    summary: dict[str, Any] = field(default_factory=dict)
    document: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None


def _depth_weight(stereo: StereoCalibration, samples: list[PoseSample]) -> float:
    """Baseline over the markers' mean distance: how much better a stereo rig measures across
    than in depth (the weight of the depth residuals)."""
    pts = np.concatenate([s.markers_optical_mm for s in samples])
    z = float(np.nanmean(pts[:, 2]))
    return min(1.0, stereo.baseline_mm / z) if z > 0 else 1.0


def _matrix(T: RigidTransform) -> list[list[float]]:
    out: list[list[float]] = np.round(T.as_matrix(), 9).tolist()
    return out


def _hand_eye_doc(res: HandEyeResult, T_flange_from_tcp: RigidTransform, bound_mm: float) -> dict[str, Any]:
    return {
        "flange_markers_mm": np.round(T_flange_from_tcp.apply(res.markers_tcp_mm), 6).tolist(),
        "T_flange_from_tcp": _matrix(T_flange_from_tcp),
        "T_optical_from_robot": _matrix(res.T_optical_from_robot),
        "poses": len(res.poses), "poses_used": res.poses_used, "outliers": res.outliers,
        "residual_mm_rms": res.residual_mm_rms, "residual_deg_rms": res.residual_deg_rms,
        "validation_mm_rms": res.validation_mm_rms, "validation_deg_rms": res.validation_deg_rms,
        "validation_bound_mm": bound_mm, "rotation_spread_deg": res.rotation_spread_deg,
        "optical_correction": (None if res.optical_correction is None
                               else np.round(res.optical_correction.H_metric_from_measured, 12).tolist()),
        "optical_correction_mm": res.optical_correction_mm,
        "per_pose": [{"index": p.index, "residual_mm": p.residual_mm, "residual_deg": p.residual_deg,
                      "role": p.role} for p in res.poses],
    }


def _previous(path: Path) -> RigCalibration | None:
    if not path.is_file():
        return None
    try:
        return load_rig_calibration(path)
    except InputFileError:
        return None


def _truth(world: object, layout_flange: FloatArray | None,
           offsets: dict[str, TimeOffset]) -> dict[str, Any]:
    """The ``truth_*`` figures against a simulated world (empty on real devices)."""
    if not isinstance(world, RigTruthSource):
        return {}
    t = world.rig_truth()
    if t is None:
        return {}
    out: dict[str, Any] = {}
    if layout_flange is not None:
        d = layout_flange - t.flange_markers_mm
        out["truth_layout_error_mm_rms"] = float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
    if offsets:
        out["truth_time_offset_error_ms"] = {k: v.offset_ms - t.time_offsets_ms[k]
                                             for k, v in offsets.items()}
    out["truth_time_offset_ms"] = dict(t.time_offsets_ms)
    return out


def run_rig_calibration(setup: SetupConfig, config_path: Path, devices: Devices, clock: Clock,
                        confirm: Confirm, *, out_path: Path, hand_eye: bool = True,
                        temporal: bool = True) -> RigCalibrationOutcome:
    """Open ``devices``, calibrate, close them; write ``out_path`` only when everything succeeded
    and the validation error is within ``[rig_calibration] max_validation_mm``.

    Args:
        devices, clock: the setup's devices (CONFIGURED) and the clock they were built with.
        confirm: the operator's confirmation before every move.
        out_path: the rig calibration file.
        hand_eye, temporal: which parts to run; a temporal-only run keeps the hand-eye part of an
            existing valid file at ``out_path``.

    Raises:
        RigCalibrationError: any refusal or failure (one line; the arm stopped, nothing written).
        InputFileError: the stereo calibration is unreadable; the file cannot be written.
        ConfigError: no stereo calibration (the camera knows none and no ``[calibration] stereo``).
        DriverError: a device cannot be opened.
    """
    cfg = setup.rig_calibration
    T_ft = devices.robot.T_flange_from_tcp
    cad_tcp = T_ft.inverse().apply(np.asarray(setup.frames.flange_markers_mm, dtype=np.float64))
    stereo = stereo_calibration(setup, devices.camera)
    locate = StereoMarkerLocator(stereo)
    tol = setup.procedure.registration.match_tolerance_mm
    planning = setup.procedure.planning
    result: HandEyeResult | None = None
    offsets: dict[str, TimeOffset] = {}
    delays: dict[str, Any] = {}
    frames_used = 0
    devices.open_all()
    try:
        robot, camera = devices.robot, devices.camera
        if hand_eye:
            start = robot.state_now().T_robot_from_tcp
            poses = calibration_poses(start, cfg)
            check_poses(poses, robot.limits, robot.name, T_ft,
                        planning.robot_model if planning.check_kinematics else None)
            collector = PoseCollector(camera, robot, clock, locate, cad_tcp, cfg, tol, confirm)
            got = collector.collect(poses, start)
            frames_used = got.frames_used
            result = solve_hand_eye(got.samples, cad_tcp, SolverSettings(
                min_poses=cfg.min_poses, holdout_every=cfg.holdout_every,
                outlier_floor_mm=cfg.outlier_floor_mm,
                depth_weight=_depth_weight(stereo, got.samples),
                optical_correction=cfg.optical_correction,
                max_optical_correction_mm=cfg.max_optical_correction_mm))
            v = result.validation_mm_rms
            if v is not None and v > cfg.max_validation_mm:
                raise RigCalibrationError(
                    f"validation error {v:.3f} mm RMS on the held-out poses is over the bound "
                    f"{cfg.max_validation_mm} mm ([rig_calibration] max_validation_mm): nothing written")
        if temporal:
            layout = result.markers_tcp_mm if result is not None else cad_tcp
            rec = TemporalRecorder(camera, robot, devices.tracker, clock, locate, layout, cfg.temporal,
                                   tol, confirm).record()
            lag_s = setup.procedure.compensation.actuation_lag_s
            offsets, est = offsets_from_recording(rec, cfg.temporal, lag_s)
            delays = {k: {"delay_ms": d.delay_ms, "sigma_ms": d.sigma_ms, "correlation": d.correlation,
                          "samples": d.samples} for k, d in est.items()}
    finally:
        devices.close_all()
    doc = _document(setup, config_path, result, T_ft, offsets, out_path, hand_eye)
    save_rig_calibration(doc, out_path)
    _log.info(EV_WRITTEN, path=str(out_path))
    layout_flange = T_ft.apply(result.markers_tcp_mm) if result is not None else None
    summary = _summary(out_path, result, frames_used, doc, offsets, delays)
    summary.update(_truth(devices.world, layout_flange, offsets))
    return RigCalibrationOutcome(summary, doc, out_path)


def _summary(out_path: Path, result: HandEyeResult | None, frames_used: int, doc: dict[str, Any],
             offsets: dict[str, TimeOffset], delays: dict[str, Any]) -> dict[str, Any]:
    """The outcome's JSON summary (docs): the hand-eye fit's figures (mm, deg; empty/None without
    a hand-eye part), frames used, per-pose rows and the time offsets / delays (ms)."""
    return {
        "rig_calibration": str(out_path),
        "poses": len(result.poses) if result else 0,
        "poses_used": result.poses_used if result else 0,
        "outliers": result.outliers if result else [],
        "residual_mm_rms": result.residual_mm_rms if result else None,
        "residual_deg_rms": result.residual_deg_rms if result else None,
        "validation_mm_rms": result.validation_mm_rms if result else None,
        "validation_deg_rms": result.validation_deg_rms if result else None,
        "rotation_spread_deg": result.rotation_spread_deg if result else None,
        "optical_correction_mm": result.optical_correction_mm if result else None,
        "frames": frames_used,
        "per_pose": doc["hand_eye"]["per_pose"] if doc.get("hand_eye") and result else [],
        "time_offset_ms": {k: v.offset_ms for k, v in offsets.items()},
        "time_offset_sigma_ms": {k: v.sigma_ms for k, v in offsets.items()},
        "delay_vs_command": delays,
    }


def _document(setup: SetupConfig, config_path: Path, result: HandEyeResult | None, T_ft: RigidTransform,
              offsets: dict[str, TimeOffset], out_path: Path, hand_eye: bool) -> dict[str, Any]:
    he: Any = None
    stereo = setup.calibration.stereo
    if result is not None:
        he = _hand_eye_doc(result, T_ft, setup.rig_calibration.max_validation_mm)
    elif not hand_eye:
        prev = _previous(out_path)
        he = prev.document.get("hand_eye") if prev is not None else None
    return {
        "schema": SCHEMA, "version": VERSION,
        "units": {"length": "mm", "time": "ms", "angle": "deg"},
        "created_utc": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "setup": str(config_path), "setup_name": setup.name,
        "stereo_calibration": None if stereo is None else str(stereo),
        "stereo_calibration_sha256": None if stereo is None else file_sha256(stereo),
        "hand_eye": he,
        "time_offsets": ({k: {"offset_ms": v.offset_ms,
                              "sigma_ms": v.sigma_ms if math.isfinite(v.sigma_ms) else None}
                          for k, v in offsets.items()} or None),
    }
