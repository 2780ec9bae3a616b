"""What ``hil run`` takes from ``[calibration] rig``: the calibrated flange-marker layout in place of
the CAD one, the optical correction every located point goes through, and the devices wrapped so
their stamps carry the calibrated time offsets."""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
from numpy.typing import NDArray

from hil.config.build import Devices
from hil.config.setup import SetupConfig
from hil.errors import InputFileError
from hil.geometry.projective import ProjectiveCorrection
from hil.log import get_logger
from hil.rigcal.rigfile import RigCalibration, load_rig_calibration
from hil.rigcal.time_align import time_aligned
from hil.session.log import file_sha256

FloatArray = NDArray[np.float64]
_log = get_logger(__name__)
EV_RIG_APPLIED = "rig_calibration_applied"


def rig_calibration(setup: SetupConfig) -> RigCalibration | None:
    """The setup's rig calibration file, or None when ``[calibration] rig`` is not set.

    Raises:
        InputFileError: the file is unreadable or invalid, its layout has a different number of
            markers than ``[frames] flange_markers_mm`` (a file of another rig), or it was made
            through another stereo calibration file than ``[calibration] stereo`` now names (its
            layout and optical correction were measured through that one).
    """
    path = setup.calibration.rig
    if path is None:
        return None
    rig = load_rig_calibration(path)
    _check_stereo(rig, setup, str(path))
    n = len(setup.frames.flange_markers_mm)
    if rig.flange_markers_mm is not None and rig.flange_markers_mm.shape[0] != n:
        raise InputFileError(str(path), f"hand_eye.flange_markers_mm has {rig.flange_markers_mm.shape[0]} "
                                        f"markers, [frames] flange_markers_mm {n}: a file of another rig?")
    return rig


def _check_stereo(rig: RigCalibration, setup: SetupConfig, path: str) -> None:
    made_with = rig.document.get("stereo_calibration_sha256")
    stereo = setup.calibration.stereo
    if not isinstance(made_with, str) or stereo is None:
        return   # a file from before the field, or a camera that knows its own calibration
    try:
        now = file_sha256(stereo)
    except OSError:
        return   # the stereo file's own loader names that problem
    if now != made_with:
        raise InputFileError(path, f"made through another stereo calibration (SHA-256 {made_with[:12]}...) "
                                   f"than [calibration] stereo = {stereo} ({now[:12]}...): its layout and "
                                   "optical correction were measured through that one; run hil rig-calibrate "
                                   "again after a camera calibration")


def flange_markers_mm(setup: SetupConfig) -> FloatArray:
    """The flange-marker layout (flange frame, mm) ``hil run`` uses: the rig calibration's when it
    has a hand-eye part, else ``[frames] flange_markers_mm`` (CAD)."""
    rig = rig_calibration(setup)
    if rig is not None and rig.flange_markers_mm is not None:
        return rig.flange_markers_mm
    return np.asarray(setup.frames.flange_markers_mm, dtype=np.float64)


def optical_correction(setup: SetupConfig) -> ProjectiveCorrection | None:
    """The rig calibration's optical correction (measured -> metric optical points), or None
    without a file or without one in it.

    Raises:
        InputFileError: see :func:`rig_calibration`.
    """
    rig = rig_calibration(setup)
    return None if rig is None else rig.optical_correction


def with_rig_time_offsets(setup: SetupConfig, devices: Devices) -> Devices:
    """``devices`` with camera, robot and tracker wrapped by the rig calibration's time offsets
    (:mod:`hil.rigcal.time_align`; opened or not), or unchanged without a file or offsets."""
    rig = rig_calibration(setup)
    if rig is None or not rig.time_offsets:
        return devices
    cam, rob, trk = time_aligned(devices.camera, devices.robot, devices.tracker, rig)
    _log.info(EV_RIG_APPLIED, **{f"{k}_offset_ms": v.offset_ms for k, v in rig.time_offsets.items()})
    return dataclasses.replace(devices, camera=cam, robot=rob, tracker=trk)


def rig_calibration_sha256(setup: SetupConfig) -> str | None:
    """SHA-256 of the ``[calibration] rig`` file for the session log header (None without one),
    after checking the file is a valid rig calibration.

    Raises:
        InputFileError: see :func:`rig_calibration`.
    """
    if rig_calibration(setup) is None or setup.calibration.rig is None:
        return None
    return hashlib.sha256(setup.calibration.rig.read_bytes()).hexdigest()
