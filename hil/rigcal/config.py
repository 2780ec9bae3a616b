"""``[rig_calibration]``: how ``hil rig-calibrate`` moves the arm, what it accepts, and the
temporal calibration's motion. Every key has a default; docs/config.md lists them."""

from __future__ import annotations

import math

from pydantic import BaseModel, Field, model_validator

from hil.config.types import STRICT, Vec3


class TemporalConfig(BaseModel):
    """``[rig_calibration.temporal]``: the short sinusoidal motion the time offsets come from."""

    model_config = STRICT

    amplitude_mm: float = Field(15.0, gt=0, le=100, description="sinusoid amplitude along axis")
    frequency_hz: float = Field(0.5, gt=0.05, le=3, description="sinusoid frequency")
    cycles: float = Field(4.0, ge=2, le=20, description="how many periods are recorded")
    axis: Vec3 = Field((1.0, 0.0, 0.0), description="motion direction, robot base frame")
    max_offset_ms: float = Field(250.0, gt=0, le=1000, description="offsets searched within +-this")
    sensor: str | None = Field(
        "needle", description="tracker sensor on the flange (None: tracker not calibrated)")

    @model_validator(mode="after")
    def _check(self) -> TemporalConfig:
        if math.hypot(*self.axis) < 1e-9:
            raise ValueError("axis must not be zero")
        if self.max_offset_ms * 1e-3 >= 0.5 / self.frequency_hz:
            raise ValueError("max_offset_ms must stay under half a period of the sinusoid "
                             "(the delay would be ambiguous)")
        return self


class RigCalibrationConfig(BaseModel):
    """``[rig_calibration]``: poses of the hand-eye calibration and acceptance bounds."""

    model_config = STRICT

    poses: int = Field(16, ge=4, le=200, description="poses visited (a quarter are held out for validation)")
    min_poses: int = Field(8, ge=4, description="fewest usable poses accepted")
    cone_half_angle_deg: float = Field(
        20.0, gt=0, le=45, description="tool-axis tilt cone about the start pose")
    spin_deg: float = Field(30.0, ge=0, le=90, description="rotation about the tool axis, +-")
    radius_mm: float = Field(
        40.0, ge=0, le=200, description="TCP positions within this of the start, per axis")
    speed_mm_s: float = Field(
        50.0, gt=0, le=250, description="TCP speed between poses (also capped by [safety])")
    accel_mm_s2: float = Field(200.0, gt=0, description="TCP acceleration between poses (capped by [safety])")
    settle_s: float = Field(0.5, ge=0, le=10, description="wait after arriving before frames count")
    still_frames: int = Field(5, ge=1, le=100, description="frames averaged per pose")
    still_tolerance_mm: float = Field(0.1, gt=0, description="frames whose markers move more are not still")
    still_timeout_s: float = Field(5.0, gt=0, description="give up on a pose that is not still by then")
    holdout_every: int = Field(4, ge=0, description="every n-th pose is held out for validation (0: none)")
    max_validation_mm: float = Field(
        0.5, gt=0, description="refuse to write a file whose validation RMS is over this")
    outlier_floor_mm: float = Field(
        0.3, gt=0, description="a pose under this RMS residual is never an outlier")
    optical_correction: bool = Field(
        True, description="also fit the stereo calibration's error as a projective warp of space (nine "
                          "numbers) and correct every located point with it (docs/rig-calibration.md)")
    max_optical_correction_mm: float = Field(
        5.0, gt=0, le=50, description="refuse a correction that moves a seen marker further than this "
                                      "(the stereo calibration is then wrong, not slightly off)")
    temporal: TemporalConfig = Field(TemporalConfig(), description="the temporal calibration's motion")

    @model_validator(mode="after")
    def _check(self) -> RigCalibrationConfig:
        if self.min_poses > self.poses:
            raise ValueError(f"min_poses {self.min_poses} is more than poses {self.poses}")
        return self
