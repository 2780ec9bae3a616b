"""Collect still poses for the hand-eye calibration, through the driver interfaces only.

For each generated pose: the operator confirms (or ``--auto``), the arm moves there
(speed-limited, blocking), waits ``settle_s``, then frames are taken until ``still_frames`` in a
row show the flange markers identified and not moving (spread under ``still_tolerance_mm``)
while the arm reports itself steady. The markers are averaged over those frames; the robot pose is
the one it reported for each frame's time (its state history interpolated at the frame stamp, the
stamps corrected by the devices' time offsets when the devices are wrapped by
:mod:`hil.rigcal.time_align`), averaged too. Any failure stops the arm and raises one error.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.camera import StereoCamera, StereoFrame
from drivers.interfaces.errors import DriverError
from drivers.interfaces.robot import Robot, RobotState
from hil.clock import Clock
from hil.controller.registration import identify
from hil.geometry.transform import RigidTransform
from hil.log import get_logger
from hil.rigcal.config import RigCalibrationConfig
from hil.rigcal.handeye import PoseSample, RigCalibrationError

FloatArray = NDArray[np.float64]
_log = get_logger(__name__)

EV_POSE_REACHED = "rigcal_pose_reached"
EV_POSE_SAMPLED = "rigcal_pose_sampled"
EV_ABORTED = "rigcal_aborted"


class RigCalibrationAbortedError(RigCalibrationError):
    """The operator aborted; the arm was stopped and nothing was written."""


class Confirm(Protocol):
    """Asks the operator before each move: True to go, False to abort."""

    def __call__(self, prompt: str) -> bool: ...


def auto_confirm(prompt: str) -> bool:
    """``--auto``: every move confirmed."""
    return True


@dataclass
class Collected:
    """The collected samples and what happened per pose (for the JSON output and the file)."""

    samples: list[PoseSample] = field(default_factory=list)
    frames_used: int = 0
    log: list[dict[str, object]] = field(default_factory=list)


def _pose_at(history: list[RobotState], t_ns: int) -> RigidTransform:
    """The reported TCP pose at ``t_ns``: the nearest sample of a still arm's history."""
    best = min(history, key=lambda s: abs(s.t_ns - t_ns))
    return best.T_robot_from_tcp


def _mean_pose(poses: list[RigidTransform]) -> RigidTransform:
    R = sum((p.R for p in poses), np.zeros((3, 3)))
    u, _, vt = np.linalg.svd(R)
    Rm = u @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt)))]) @ vt
    return RigidTransform(Rm, np.mean([p.t for p in poses], axis=0))


class PoseCollector:
    """Visits poses and records still samples.

    Args:
        camera, robot: ACTIVE devices (possibly time-aligned wrappers).
        clock: their clock.
        locate: stereo pair -> marker centres (optical frame, mm).
        layout_tcp_mm: (M, 3) the CAD flange-marker layout in the TCP frame (for identification).
        cfg: ``[rig_calibration]``.
        match_tolerance_mm: marker identification tolerance.
        confirm: the operator's confirmation per move.
    """

    def __init__(self, camera: StereoCamera, robot: Robot, clock: Clock,
                 locate: Callable[[StereoFrame], FloatArray], layout_tcp_mm: FloatArray,
                 cfg: RigCalibrationConfig, match_tolerance_mm: float, confirm: Confirm) -> None:
        self.camera, self.robot, self.clock, self.locate = camera, robot, clock, locate
        self.layout = np.asarray(layout_tcp_mm, dtype=np.float64)
        self.cfg, self.tol, self.confirm = cfg, match_tolerance_mm, confirm
        self.speed = min(cfg.speed_mm_s, robot.limits.max_speed_mm_s)
        self.accel = min(cfg.accel_mm_s2, robot.limits.max_accel_mm_s2)

    def stop(self, why: str) -> None:
        """Stop the arm, swallowing a second failure (the first error is the one reported)."""
        try:
            self.robot.stop()
        except DriverError as exc:
            _log.warning("rigcal_stop_failed", reason=why, error=str(exc))

    def move(self, i: int, n: int, T: RigidTransform, what: str) -> None:
        """Confirm, then move to ``T`` (blocking).

        Raises:
            RigCalibrationAbortedError: the operator said no.
            RigCalibrationError: the arm could not get there (limits, safety stop, transport).
        """
        prompt = f"{what} {i + 1}/{n}: move the TCP to {np.round(T.t, 1).tolist()} mm?"
        if not self.confirm(prompt):
            self.stop("operator abort")
            _log.warning(EV_ABORTED, pose=i, poses=n)
            raise RigCalibrationAbortedError(f"operator aborted at {what} {i + 1} of {n}: the arm was "
                                        "stopped, nothing was written")
        try:
            self.robot.move_linear(T, self.speed, self.accel, blocking=True)
        except DriverError as exc:
            self.stop("move failed")
            raise RigCalibrationError(f"{what} {i} at {np.round(T.t, 1).tolist()} mm cannot be "
                                      f"reached: {exc}; the arm was stopped, nothing was written") from None
        _log.info(EV_POSE_REACHED, pose=i, tcp_mm=np.round(T.t, 2).tolist())

    def still_sample(self, i: int) -> tuple[PoseSample, int]:
        """Frames at the current pose until ``still_frames`` in a row are still; their mean.

        Raises:
            RigCalibrationError: markers not seen, or never still, within ``still_timeout_s``.
        """
        c = self.cfg
        if c.settle_s > 0:
            self.clock.sleep(c.settle_s)
        deadline = self.clock.now_ns() + round(c.still_timeout_s * 1e9)
        run: list[tuple[FloatArray, RigidTransform]] = []
        history: list[RobotState] = []
        seen_any = 0
        grabbed = 0
        while self.clock.now_ns() < deadline:
            frame = self.camera.grab(timeout_s=1.0)
            grabbed += 1
            st = self.robot.state_now()
            history = [*history[-20:], st]
            pts = np.asarray(self.locate(frame), dtype=np.float64).reshape(-1, 3)
            fl = identify(pts, self.layout, self.tol)
            steady = st.tcp_speed_mm_s < 0.5
            if fl is None or int(np.all(np.isfinite(fl), axis=1).sum()) < 3 or not steady:
                run = []
                continue
            seen_any += 1
            pose = _pose_at(history, frame.left.t_ns)
            if run and float(np.nanmax(np.linalg.norm(fl - run[0][0], axis=1))) > c.still_tolerance_mm:
                run = []
            run.append((fl, pose))
            if len(run) >= c.still_frames:
                stack = np.stack([m for m, _ in run])
                with np.errstate(invalid="ignore"):
                    markers = np.nanmean(stack, axis=0) if np.isfinite(stack).any() else stack[0]
                seen = np.all(np.isfinite(stack), axis=2).sum(axis=0) >= max(1, len(run) // 2)
                markers[~seen] = np.nan
                sample = PoseSample(i, _mean_pose([p for _, p in run]), markers)
                _log.info(EV_POSE_SAMPLED, pose=i, frames=len(run), markers=int(seen.sum()))
                return sample, grabbed
        self.stop("not still")
        if seen_any == 0:
            raise RigCalibrationError(
                f"markers not seen at pose {i}: no frame in {c.still_timeout_s:g} s showed 3 or more "
                "flange markers; check the camera's view of the plate and [rig_calibration] "
                "cone_half_angle_deg; the arm was stopped, nothing was written")
        raise RigCalibrationError(f"pose {i} never still: the flange markers moved more than "
                                  f"{c.still_tolerance_mm} mm between frames for {c.still_timeout_s:g} s; "
                                  "the arm was stopped, nothing was written")

    def collect(self, poses: list[RigidTransform], home: RigidTransform) -> Collected:
        """Visit ``poses`` in order, sample each, and return to ``home``.

        Raises:
            RigCalibrationAbortedError, RigCalibrationError: see :meth:`move` and :meth:`still_sample`;
                also a device failure while sampling (the arm is stopped first).
        """
        out = Collected()
        n = len(poses)
        for i, T in enumerate(poses):
            self.move(i, n, T, "pose")
            try:
                sample, frames = self.still_sample(i)
            except DriverError as exc:
                self.stop("device failed")
                raise RigCalibrationError(
                    f"pose {i}: {exc}; the arm was stopped, nothing was written") from None
            out.samples.append(sample)
            out.frames_used += frames
            seen = int(np.all(np.isfinite(sample.markers_optical_mm), axis=1).sum())
            out.log.append({"pose": i, "tcp_mm": np.round(T.t, 3).tolist(), "markers_seen": seen})
        self.move(0, 1, home, "return to the start pose")
        return out
