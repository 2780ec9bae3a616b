"""Unsynchronised pose streams made into pose pairs: the time offset, then interpolation.

1. Time offset: the magnitude of each stream's angular speed, ``|omega|(t) = angle(R_i^T
   R_{i+k}) / (t_{i+k} - t_i)`` at the middle of each ``k``-step window (``SPEED_WINDOW_S``), is
   the same signal in both streams whatever the set-up (the camera turns with the hand, or the
   target with the flange; the magnitude does not depend on the frame). The slower stream's
   signal is fitted against the faster one's with the live temporal calibration's delay estimator
   (:func:`hil.rigcal.delay.estimate_delay`: least-squares gain and bias per candidate delay on a
   1 ms grid, parabola through the best, Gauss-Newton sigma), the faster signal sampled without a
   hold model (:class:`SampledSignal`).
2. Pairs: the faster stream interpolated at each slower sample's time minus the offset
   (rotation by slerp, Shoemake 1985; translation linearly), where the faster stream has samples
   on both sides at most ``max_gap_steps`` of its median step apart.

``time_offset_ms`` is the camera stream's stamp minus the robot stream's stamp of the same
instant (positive: the camera's stamps are late).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from hil.rigcal.delay import DelayEstimate, Reference, estimate_delay
from hil.rigcal.handeye import RigCalibrationError
from hil.rigcal.samples import FloatArray, PosePairs, PoseStream, RecordedStreams, SamplesError

#: the offset is searched within +- this, ms
MAX_OFFSET_MS = 1000.0
#: the angular speed is taken over this time base, s (a camera's pose jitter swamps the speed
#: from one frame to the next: on the ETH arm recording the correlation is 0.11 frame to frame,
#: 0.90 over 0.2 s)
SPEED_WINDOW_S = 0.2


class SampledSignal(Reference):
    """A sampled signal, linear between its samples (a :class:`Reference` without the command
    hold's half-step shift: these samples are measurements, not held commands)."""

    def __init__(self, t_ns: FloatArray, values: FloatArray) -> None:
        order = np.argsort(t_ns, kind="stable")
        self.t = np.asarray(t_ns, dtype=np.float64)[order]
        self.v = np.asarray(values, dtype=np.float64)[order]


@dataclass(frozen=True)
class AlignedPairs:
    """Pairs made from two streams.

    Attributes:
        pairs: one per usable sample of the slower stream (its time, the faster interpolated).
        time_offset_ms: camera stamp minus robot stamp of the same instant, ms.
        delay: the estimator's result (sigma, correlation) for the slower stream.
        interpolated: ``robot`` or ``camera``, the stream that was interpolated.
    """

    pairs: PosePairs
    time_offset_ms: float
    delay: DelayEstimate
    interpolated: str


def angular_speed(s: PoseStream, window_s: float = SPEED_WINDOW_S) -> tuple[FloatArray, FloatArray]:
    """``(t_mid_s, |omega| rad/s)`` of a stream: the rotation angle between samples ``k`` steps
    apart (``k`` = ``window_s`` over the median step, at least 1) over their time difference,
    stamped at their middle (module doc)."""
    k = max(1, round(window_s / float(np.median(np.diff(s.t_s)))))
    k = min(k, len(s.t_s) - 1)
    R = s.T[:, :3, :3]
    rel = np.einsum("nji,njk->nik", R[:-k], R[k:])
    c = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    dt = s.t_s[k:] - s.t_s[:-k]
    return 0.5 * (s.t_s[:-k] + s.t_s[k:]), np.arccos(c) / dt


def interpolate(s: PoseStream, t_s: FloatArray,
                max_gap_steps: float = 3.0) -> tuple[FloatArray, NDArray[np.bool_]]:
    """``(T (M, 4, 4), ok (M,) bool)``: the stream at times ``t_s`` (slerp + linear), ``ok`` False
    where ``t_s`` is outside the stream or its bracketing samples are more than ``max_gap_steps``
    median steps apart."""
    step = float(np.median(np.diff(s.t_s)))
    k = np.searchsorted(s.t_s, t_s, side="right") - 1
    ok = (k >= 0) & (k < len(s.t_s) - 1)
    kk = np.clip(k, 0, len(s.t_s) - 2)
    ok &= (s.t_s[kk + 1] - s.t_s[kk]) <= max_gap_steps * step
    tq = np.clip(t_s, s.t_s[0], s.t_s[-1])
    rots = Slerp(s.t_s, Rotation.from_matrix(s.T[:, :3, :3]))(tq).as_matrix()
    a = ((tq - s.t_s[kk]) / (s.t_s[kk + 1] - s.t_s[kk]))[:, None]
    trans = (1.0 - a) * s.T[kk, :3, 3] + a * s.T[kk + 1, :3, 3]
    T = np.tile(np.eye(4), (len(t_s), 1, 1))
    T[:, :3, :3] = rots
    T[:, :3, 3] = trans
    return T, ok


def align_streams(streams: RecordedStreams, path: str, max_offset_ms: float = MAX_OFFSET_MS) -> AlignedPairs:
    """Pose pairs and the time offset from two unsynchronised streams (module doc).

    Raises:
        SamplesError: the streams overlap less than 1 s, the offset cannot be estimated (too few
            samples, no rotation, offset beyond ``+-max_offset_ms``) or no sample of the slower
            stream can be paired.
    """
    rob, cam = streams.robot, streams.camera
    lo, hi = max(rob.t_s[0], cam.t_s[0]), min(rob.t_s[-1], cam.t_s[-1])
    if hi - lo < 1.0:
        raise SamplesError(path, f"the streams overlap for {max(hi - lo, 0.0):.2f} s only (robot "
                                 f"{rob.t_s[0]:.3f}..{rob.t_s[-1]:.3f} s, camera {cam.t_s[0]:.3f}.."
                                 f"{cam.t_s[-1]:.3f} s; need >= 1 s)")
    robot_faster = len(rob.t_s) / np.ptp(rob.t_s) >= len(cam.t_s) / np.ptp(cam.t_s)
    fast, slow = (rob, cam) if robot_faster else (cam, rob)
    tf, wf = angular_speed(fast)
    ts, ws = angular_speed(slow)
    try:
        d = estimate_delay(SampledSignal(tf * 1e9, wf), ts * 1e9, ws, max_offset_ms,
                           "camera" if robot_faster else "robot")
    except RigCalibrationError as exc:
        raise SamplesError(path, f"time offset between the streams: {exc}") from None
    offset_ms = d.delay_ms if robot_faster else -d.delay_ms
    T_fast, ok = interpolate(fast, slow.t_s - d.delay_ms * 1e-3)
    if not ok.any():
        raise SamplesError(path, "no sample of the slower stream falls within the faster one "
                                 "after the time offset")
    idx = np.nonzero(ok)[0]
    T_slow = slow.T[idx]
    where = tuple(slow.where[i] for i in idx)
    T_rob, T_cam = (T_fast[idx], T_slow) if robot_faster else (T_slow, T_fast[idx])
    pairs = PosePairs(T_rob, T_cam, where, slow.t_s[idx])
    return AlignedPairs(pairs, float(offset_ms), d, "robot" if robot_faster else "camera")
