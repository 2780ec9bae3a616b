"""Perception for the controller: stereo frame -> ring-marker centres in the optical frame, and the
needle-axis check (seed 004 §III contour lines, or §II-A collinear beads) against the plan."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.camera import StereoFrame
from hil.controller.located import LocatedMarkers
from hil.controller.series import SampleSeries
from hil.geometry.projective import ProjectiveCorrection
from hil.vision.beads import BeadAxisMeasurement, measure_bead_axis
from hil.vision.camera_model import StereoCalibration
from hil.vision.detect import RingDetection
from hil.vision.lines import NeedleAxisMeasurement, measure_needle_axis
from hil.vision.pipeline import locate_markers
from hil.vision.tracking import MarkerTracker, TrackingParams

FloatArray = NDArray[np.float64]


def _centres_px(detections: Sequence[RingDetection]) -> FloatArray:
    """The detections' centres (N, 2), px."""
    return np.array([d.center_px for d in detections], dtype=np.float64).reshape(-1, 2)


class StereoMarkerLocator:
    """The real vision pipeline (detect, pair, triangulate; seed 001 sections 3.3-4) as a
    :data:`hil.controller.pipeline.MarkerLocator`. Identification is left to the controller
    (it knows the reference state and the flange layout).

    With ``tracking`` the markers are searched in windows around their predicted positions between
    full-frame searches (:class:`hil.vision.tracking.MarkerTracker`, which keeps the state); without,
    every pair gets a full-frame search. With ``correction`` (a rig calibration's
    ``optical_correction``) every triangulated point is mapped through it: the stereo calibration's
    error, as the arm's motion measured it, undone (a few microseconds per pair). Either way the
    time of each call (wall clock, ms) is kept in a :class:`~hil.controller.series.SampleSeries`
    (its memory allocated here, once: a deque of the newest 100,000 grew the soak's supervisor by
    one float a pair, ~1.7 MB an hour at 15 Hz; issue 45): :meth:`locate_ms` gives its p50 / p95,
    exact up to 32,768 calls and a uniform sample of the whole run beyond. Calls must
    not overlap (the controller's thread or the frame prefetcher's, one at a time); a lock makes
    overlapping calls wait rather than corrupt the tracking state.

    Raises (when called):
        VisionError: an image does not fit the calibration.
    """

    def __init__(self, calibration: StereoCalibration, tracking: TrackingParams | None = None,
                 correction: ProjectiveCorrection | None = None) -> None:
        self.calibration = calibration
        self.correction = correction
        self.tracker = None if tracking is None else MarkerTracker(calibration, tracking)
        self._lock = threading.Lock()
        self._locate_ms = SampleSeries()

    def use_tracking(self, tracking: TrackingParams | None) -> None:
        """Switch to region-of-interest tracking with ``tracking`` (None: full-frame searches); the
        next call starts with a full-frame search."""
        with self._lock:
            self.tracker = None if tracking is None else MarkerTracker(self.calibration, tracking)

    def __call__(self, frame: StereoFrame) -> FloatArray:
        """The triangulated marker centres of ``frame`` (M, 3), optical frame, mm, any order."""
        return np.array(self.locate_pair(frame).points_mm, dtype=np.float64)

    def locate_pair(self, frame: StereoFrame) -> LocatedMarkers:
        """The markers of ``frame``: the ring centres detected in each image (px) and the
        triangulated centres (optical frame, mm), any order (:class:`LocatedMarkers`)."""
        with self._lock:
            t0 = time.perf_counter_ns()
            if self.tracker is None:
                res = locate_markers(self.calibration, frame.left.image, frame.right.image)
            else:
                res = self.tracker.locate(frame.left.image, frame.right.image, frame.left.t_ns * 1e-9)
            self._locate_ms.append((time.perf_counter_ns() - t0) * 1e-6)
        points = res.points_mm if self.correction is None else self.correction.apply(res.points_mm)
        return LocatedMarkers.of(frame, points, _centres_px(res.detections_left),
                                 _centres_px(res.detections_right))

    def locate_ms(self) -> dict[str, float | None]:
        """p50 and p95 of the time per call so far (ms, wall clock; None before the first call)."""
        with self._lock:
            samples = np.array(self._locate_ms, copy=True)
        if not samples.size:
            return {"p50": None, "p95": None}
        return {"p50": float(np.percentile(samples, 50)), "p95": float(np.percentile(samples, 95))}


class StereoNeedleChecker:
    """The seed-004 needle-axis check (§III, two views) as a
    :data:`hil.controller.needle.NeedleAxisChecker`: the needle's two contour lines in each view,
    searched around the expected segment ``start_mm -> end_mm`` (optical frame, mm), the axis from
    the two views' planes, and its error against the path ``entry_mm -> target_mm`` (optical frame).

    With ``correction`` (the rig calibration's, which the marker locator applies) the four points,
    given in the controller's corrected optical frame, are mapped back to where the stereo
    calibration sees them before the image search; the errors are then measured there (the
    correction changes lengths by parts per thousand).

    Pure CPU (a few tens of ms), no blocking. Raises (when called): VisionError (needle not found
    in a view), DegenerateConfigurationError (axis near an epipolar plane).
    """

    def __init__(self, calibration: StereoCalibration, radius_mm: float | None = None,
                 correction: ProjectiveCorrection | None = None) -> None:
        self.calibration = calibration
        self.radius_mm = radius_mm
        self.correction = correction

    def __call__(self, frame: StereoFrame, start_mm: FloatArray, end_mm: FloatArray, entry_mm: FloatArray,
                 target_mm: FloatArray) -> NeedleAxisMeasurement:
        start_mm, end_mm, entry_mm, target_mm = _camera_space(self.correction, start_mm, end_mm, entry_mm,
                                                              target_mm)
        return measure_needle_axis(self.calibration, frame.left.image, frame.right.image, start_mm, end_mm,
                                   entry_mm, target_mm, radius_mm=self.radius_mm)


def _camera_space(correction: ProjectiveCorrection | None,
                  *points_mm: FloatArray) -> tuple[FloatArray, ...]:
    """``points_mm`` (each (3,), corrected optical frame) where the stereo calibration sees them
    (unchanged without a correction)."""
    if correction is None:
        return points_mm
    seen = correction.to_measured(np.array(points_mm, dtype=np.float64).reshape(-1, 3))
    return tuple(np.array(p) for p in seen)


class CollinearNeedleChecker:
    """The seed-004 needle-axis check from collinear bead markers on the guide tube (§II-A, stereo
    variant checked against the monocular one) as a :data:`hil.controller.needle.NeedleAxisChecker`:
    same call and result shape (``path_error``) as :class:`StereoNeedleChecker`; the direction error
    is oriented (the beads fix which end is the tip).

    ``positions_mm``: the beads' axis coordinates from the tip (>= 3); ``correction`` as for
    :class:`StereoNeedleChecker`. Pure CPU (a few ms), no blocking. Raises (when called):
    VisionError (beads not found, monocular/stereo disagreement over ``max_mono_stereo_deg``),
    DegenerateConfigurationError.
    """

    def __init__(self, calibration: StereoCalibration, positions_mm: tuple[float, ...],
                 max_mono_stereo_deg: float = 10.0, correction: ProjectiveCorrection | None = None) -> None:
        self.calibration = calibration
        self.positions_mm = positions_mm
        self.max_mono_stereo_deg = max_mono_stereo_deg
        self.correction = correction

    def __call__(self, frame: StereoFrame, start_mm: FloatArray, end_mm: FloatArray, entry_mm: FloatArray,
                 target_mm: FloatArray) -> BeadAxisMeasurement:
        start_mm, end_mm, entry_mm, target_mm = _camera_space(self.correction, start_mm, end_mm, entry_mm,
                                                              target_mm)
        return measure_bead_axis(self.calibration, frame.left.image, frame.right.image, start_mm, end_mm,
                                 entry_mm, target_mm, self.positions_mm,
                                 max_mono_stereo_deg=self.max_mono_stereo_deg)
