"""Perception for the controller: stereo frame -> ring-marker centres in the optical frame."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.camera import StereoFrame
from hil.vision.camera_model import StereoCalibration
from hil.vision.pipeline import locate_markers

FloatArray = NDArray[np.float64]


class StereoMarkerLocator:
    """The real vision pipeline (detect, pair, triangulate; seed 001 sections 3.3-4) as a
    :data:`hil.controller.procedure.MarkerLocator`. Identification is left to the controller
    (it knows the reference state and the flange layout).

    Raises (when called):
        VisionError: an image does not fit the calibration.
    """

    def __init__(self, calibration: StereoCalibration) -> None:
        self.calibration = calibration

    def __call__(self, frame: StereoFrame) -> FloatArray:
        res = locate_markers(self.calibration, frame.left.image, frame.right.image)
        pts: FloatArray = np.asarray(res.points_mm, dtype=np.float64).reshape(-1, 3)
        return pts
