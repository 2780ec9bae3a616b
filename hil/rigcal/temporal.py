"""Temporal calibration: each device's time offset from a short sinusoidal motion of the arm.

The arm is servoed (at its control rate, between camera frames) along ``axis`` (robot base frame)
by ``A sin(2 pi f t)`` about its start pose, eased in and out over one period, for ``cycles``
periods. Recorded: every command (send time, commanded displacement), every robot state (its
stamp, the reported displacement), every stereo pair (its stamp, the TCP position the flange
markers give, Horn on the layout), every tracker sample of the flange sensor (its stamp,
position). The camera and tracker positions are reduced to one coordinate along their principal
direction. Each device's delay against the commands is estimated (:mod:`hil.rigcal.delay`);
the arm follows its commands ``actuation_lag_s`` late (``[procedure.compensation]``, the
controller's own model of it), so a device's time offset -- its stamp minus the true time of what
it reports -- is its delay minus that lag. With that definition the controller's prediction
horizon (frame age + actuation lag) comes out right whatever the lag model's error: the error
enters the offset and the lag with opposite signs.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.camera import StereoCamera, StereoFrame
from drivers.interfaces.errors import DriverError
from drivers.interfaces.robot import Robot
from drivers.interfaces.tracker import PoseTracker
from hil.clock import Clock
from hil.controller.registration import identify
from hil.errors import GeometryError
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform
from hil.log import get_logger
from hil.rigcal.collect import Confirm, RigCalibrationAbortedError
from hil.rigcal.config import TemporalConfig
from hil.rigcal.delay import DelayEstimate, Reference, estimate_delay
from hil.rigcal.handeye import RigCalibrationError
from hil.rigcal.rigfile import TimeOffset

FloatArray = NDArray[np.float64]
_log = get_logger(__name__)
EV_TEMPORAL_DONE = "rigcal_temporal_done"


@dataclass
class Recording:
    """Timed signals of one temporal-calibration motion (stamps in ns, positions in mm)."""

    command: list[tuple[int, float]] = field(default_factory=list)
    robot: list[tuple[int, float]] = field(default_factory=list)
    camera: list[tuple[int, FloatArray]] = field(default_factory=list)
    tracker: list[tuple[int, FloatArray]] = field(default_factory=list)


def displacement_mm(t_s: float, cfg: TemporalConfig) -> float:
    """Commanded displacement along the axis at ``t_s`` after the start: the sinusoid, eased in
    over the first period and out over the last (``(1 - cos) / 2`` envelope)."""
    period = 1.0 / cfg.frequency_hz
    total = cfg.cycles * period
    if t_s <= 0.0 or t_s >= total:
        return 0.0
    env = min(1.0, t_s / period, (total - t_s) / period)
    env = 0.5 * (1.0 - math.cos(math.pi * env))
    return cfg.amplitude_mm * env * math.sin(2.0 * math.pi * cfg.frequency_hz * t_s)


def _principal(points: FloatArray) -> FloatArray:
    """Coordinates of ``points`` (N, 3) along their principal direction."""
    c = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    out: FloatArray = c @ vt[0]
    return out


class TemporalRecorder:
    """Runs the motion and records the signals (see the module doc).

    Args:
        camera, robot, tracker: ACTIVE devices, raw (not time-corrected: their own stamps are
            what is calibrated); tracker may be None.
        clock: their clock.
        locate: stereo pair -> marker centres (optical, mm).
        layout_tcp_mm: the flange-marker layout in the TCP frame.
        cfg: ``[rig_calibration.temporal]``.
        match_tolerance_mm: marker identification tolerance.
        confirm: the operator's confirmation before the motion.
    """

    def __init__(self, camera: StereoCamera, robot: Robot, tracker: PoseTracker | None, clock: Clock,
                 locate: Callable[[StereoFrame], FloatArray], layout_tcp_mm: FloatArray,
                 cfg: TemporalConfig, match_tolerance_mm: float, confirm: Confirm) -> None:
        self.camera, self.robot, self.tracker, self.clock = camera, robot, tracker, clock
        self.locate, self.layout, self.cfg = locate, np.asarray(layout_tcp_mm, dtype=np.float64), cfg
        self.tol, self.confirm = match_tolerance_mm, confirm
        a = np.asarray(cfg.axis, dtype=np.float64)
        self.axis = a / np.linalg.norm(a)

    def _camera_sample(self, frame: StereoFrame, rec: Recording) -> None:
        pts = np.asarray(self.locate(frame), dtype=np.float64).reshape(-1, 3)
        fl = identify(pts, self.layout, self.tol)
        if fl is None:
            return
        ok = np.all(np.isfinite(fl), axis=1)
        if int(ok.sum()) < 3:
            return
        try:
            T = register_horn(fl[ok], self.layout[ok]).T_fixed_from_moving
        except GeometryError:
            return
        rec.camera.append((frame.left.t_ns, T.t))

    def _tracker_sample(self, rec: Recording) -> None:
        if self.tracker is None or self.cfg.sensor is None:
            return
        s = self.tracker.latest().get(self.cfg.sensor)
        if s is None or s.missing or s.T_tracker_from_sensor is None:
            return
        if not rec.tracker or rec.tracker[-1][0] != s.t_ns:
            rec.tracker.append((s.t_ns, s.T_tracker_from_sensor.t))

    def record(self) -> Recording:
        """Confirm, run the motion, return the signals; the arm ends where it started.

        Raises:
            RigCalibrationAbortedError: the operator said no (nothing moved).
            RigCalibrationError: a device failed (the arm is stopped first).
        """
        c = self.cfg
        if not self.confirm(f"temporal calibration: move the TCP +-{c.amplitude_mm:g} mm along "
                            f"{np.round(self.axis, 2).tolist()} at {c.frequency_hz:g} Hz for "
                            f"{c.cycles / c.frequency_hz:g} s?"):
            raise RigCalibrationAbortedError("operator aborted before the temporal calibration motion: "
                                        "nothing moved, nothing was written")
        try:
            return self._record()
        except DriverError as exc:
            with contextlib.suppress(DriverError):
                self.robot.stop()
            raise RigCalibrationError(f"temporal calibration: {exc}; the arm was stopped, "
                                      "nothing was written") from None

    def _record(self) -> Recording:
        c = self.cfg
        rec = Recording()
        start = self.robot.state_now().T_robot_from_tcp
        period_ns = round(1e9 / self.robot.control_rate_hz)
        frame_ns = round(1e9 / self.camera.frame_rate_hz)
        total_ns = round(c.cycles / c.frequency_hz * 1e9) + 4 * frame_ns
        t0 = self.clock.now_ns()
        last_cmd = t0 - period_ns
        while self.clock.now_ns() - t0 < total_ns:
            frame = self.camera.grab(timeout_s=1.0)
            self._camera_sample(frame, rec)
            next_frame_ns = self.clock.now_ns() + frame_ns - period_ns // 2
            while True:
                now = self.clock.now_ns()
                d = displacement_mm((now - t0) * 1e-9, c)
                # the step is checked against the time since the previous command (a frame wait
                # can make it longer than one period)
                self.robot.servo(RigidTransform(start.R, start.t + d * self.axis),
                                 max(now - last_cmd, period_ns) * 1e-9)
                last_cmd = now
                rec.command.append((now, d))
                st = self.robot.state_now()
                if not rec.robot or rec.robot[-1][0] != st.t_ns:
                    rec.robot.append((st.t_ns, float(self.axis @ (st.T_robot_from_tcp.t - start.t))))
                self._tracker_sample(rec)
                if now + period_ns > next_frame_ns:
                    break
                self.clock.sleep(period_ns * 1e-9)
        self.robot.stop()
        return rec


def offsets_from_recording(rec: Recording, cfg: TemporalConfig,
                           actuation_lag_s: float) -> tuple[dict[str, TimeOffset], dict[str, DelayEstimate]]:
    """Each device's time offset (its delay minus ``actuation_lag_s``) and the raw delays.

    Raises:
        RigCalibrationError: a device's signal is unusable (see :func:`estimate_delay`).
    """
    ref = Reference(np.array([t for t, _ in rec.command], dtype=np.float64),
                    np.array([v for _, v in rec.command]))
    signals: dict[str, tuple[FloatArray, FloatArray]] = {
        "robot": (np.array([t for t, _ in rec.robot], dtype=np.float64), np.array([v for _, v in rec.robot]))}
    if len(rec.camera) >= 3:
        signals["camera"] = (np.array([t for t, _ in rec.camera], dtype=np.float64),
                             _principal(np.array([p for _, p in rec.camera])))
    else:
        raise RigCalibrationError("temporal calibration: the flange markers were seen in fewer than 3 "
                                  "frames during the motion")
    if len(rec.tracker) >= 3:
        signals["tracker"] = (np.array([t for t, _ in rec.tracker], dtype=np.float64),
                              _principal(np.array([p for _, p in rec.tracker])))
    delays = {dev: estimate_delay(ref, t, y, cfg.max_offset_ms, dev) for dev, (t, y) in signals.items()}
    lag_ms = actuation_lag_s * 1e3
    offsets = {dev: TimeOffset(d.delay_ms - lag_ms, d.sigma_ms) for dev, d in delays.items()}
    _log.info(EV_TEMPORAL_DONE, **{f"{k}_offset_ms": round(v.offset_ms, 3) for k, v in offsets.items()})
    return offsets, delays
