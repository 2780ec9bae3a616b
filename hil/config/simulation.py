"""``[simulation]``: the simulated world (patient phantom, scripted motion, device placements).

Only used when a simulated driver is configured. Every random quantity derives from ``seed``;
the same seed and the same requests give the same world, bit for bit.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, Field, model_validator

from hil.config.body import BodyConfig
from hil.config.types import STRICT, TransformConfig, Vec3


class PatientConfig(BaseModel):
    """The phantom, in the image (CT) frame: x lateral, y cranio-caudal, z anterior (up), mm.

    The skin is a cylinder of radius ``torso_radius_mm`` (axis along y) whose top line is z = 0;
    ring markers sit on it in a golden-angle layout inside ``marker_spread_mm`` of the origin.
    """

    model_config = STRICT

    marker_count: int = Field(6, ge=3, le=12, description="skin ring markers")
    marker_spread_mm: float = Field(80.0, gt=20, le=200, description="markers lie within this radius")
    torso_radius_mm: float = Field(180.0, gt=50, description="curvature radius of the skin surface")
    marker_outer_diameter_mm: float = Field(7.0, gt=0)
    marker_inner_diameter_mm: float = Field(3.0, gt=0)
    entry_xy_mm: tuple[float, float] = Field((5.0, -10.0), description="skin entry point (x, y)")
    target_offset_mm: Vec3 = Field((10.0, 8.0, -75.0), description="target = entry + this, mm")
    T_optical_from_image: TransformConfig = Field(
        TransformConfig(translation_mm=(60.0, 0.0, 1000.0), rotvec_rad=(math.pi, 0.0, 0.0)),
        description="where the phantom lies at rest, seen from the left camera")

    @model_validator(mode="after")
    def _check(self) -> PatientConfig:
        if self.marker_inner_diameter_mm >= self.marker_outer_diameter_mm:
            raise ValueError("marker_inner_diameter_mm must be smaller than marker_outer_diameter_mm")
        need = 1.4 * self.marker_outer_diameter_mm * math.sqrt(self.marker_count)
        if self.marker_spread_mm < need:
            raise ValueError(f"marker_spread_mm {self.marker_spread_mm} is too small for "
                             f"{self.marker_count} markers of {self.marker_outer_diameter_mm} mm "
                             f"(needs >= {need:.1f}: markers would touch)")
        if self.target_offset_mm[2] >= 0:
            raise ValueError("target_offset_mm z must be negative (the target is under the skin)")
        return self


class BreathingConfig(BaseModel):
    """Lujan et al. 1999 breathing: ``d = A cos^(2n)(pi (s - 1/2))`` over the active part of each
    cycle (s in [0, 1]), then ``end_exhale_dwell_s`` at exhale (d = 0). Each cycle's amplitude and
    period vary by up to ``irregularity`` (fraction), seeded."""

    model_config = STRICT

    enabled: bool = True
    amplitude_mm: float = Field(6.0, ge=0, le=40, description="exhale-to-inhale displacement")
    period_s: float = Field(4.0, gt=0.5, le=20, description="mean cycle length")
    shape_n: int = Field(2, ge=1, le=6, description="Lujan exponent n (cos^2n)")
    end_exhale_dwell_s: float = Field(0.8, ge=0, description="rest at exhale, part of the period")
    irregularity: float = Field(0.1, ge=0, le=0.5, description="per-cycle amplitude/period spread")
    direction: Vec3 = Field((0.0, 0.3, 1.0), description="displacement direction (image frame)")
    baseline_wander_mm: float = Field(0.0, ge=0, le=20,
                                      description="slow end-exhale baseline wander along direction (0: off)")
    baseline_period_s: float = Field(45.0, gt=5, le=600, description="main period of the baseline wander")
    cough_rate_per_min: float = Field(0.0, ge=0, le=10, description="mean coughs per minute (0: none)")
    cough_amplitude_mm: float = Field(8.0, ge=0, le=40, description="peak displacement of a cough")
    cough_duration_s: float = Field(0.6, gt=0.05, le=5, description="length of one cough")

    @model_validator(mode="after")
    def _check(self) -> BreathingConfig:
        if self.end_exhale_dwell_s >= self.period_s * (1 - self.irregularity) * 0.9:
            raise ValueError("end_exhale_dwell_s must be well below the shortest period")
        if math.hypot(*self.direction) < 1e-9:
            raise ValueError("direction must not be zero")
        return self


class DriftConfig(BaseModel):
    """Slow patient drift on the table (image frame), clamped to ``max_mm``."""

    model_config = STRICT

    velocity_mm_s: Vec3 = (0.0, 0.0, 0.0)
    max_mm: float = Field(10.0, ge=0)


class ShiftConfig(BaseModel):
    """A sudden shift (the patient moves): a rigid step about the image origin, ramped."""

    model_config = STRICT

    at_s: float = Field(ge=0)
    translation_mm: Vec3 = (0.0, 0.0, 0.0)
    rotvec_rad: Vec3 = (0.0, 0.0, 0.0)
    ramp_s: float = Field(0.05, ge=0)


class TremorConfig(BaseModel):
    """Small fast motion: three sinusoids per axis around ``frequency_hz``, seeded phases."""

    model_config = STRICT

    amplitude_mm: float = Field(0.05, ge=0, le=5)
    frequency_hz: float = Field(8.0, gt=0, le=50)


class BreathHoldConfig(BaseModel):
    """A scripted breath-hold: breathing eases to ``level`` (0 exhale .. 1 inhale) and stays."""

    model_config = STRICT

    start_s: float = Field(ge=0)
    duration_s: float = Field(gt=0)
    level: float = Field(0.0, ge=0, le=1)


class RigErrorsConfig(BaseModel):
    """``[simulation.rig_errors]``: how the simulated rig differs from what the controller is told,
    as a real rig does. Every knob defaults to zero/off: a perfect rig, the simulator as it always
    was. Random parts are drawn once per world from ``[simulation] seed``.

    Time offsets follow one convention (docs/rig-calibration.md): a device's offset is its
    reported timestamp minus the true time of what it reports, ms.
    """

    model_config = STRICT

    flange_marker_error_mm: float = Field(
        0.0, ge=0, le=5,
        description="sigma per axis of each flange marker's true offset from [frames] flange_markers_mm")
    camera_calibration_error_px: float = Field(
        0.0, ge=0, le=5,
        description="the true cameras differ from the calibration file by about this reprojection RMS")
    camera_timestamp: Literal["exposure", "reception"] = Field(
        "exposure", description="what the simulated camera stamps its frames with")
    camera_reception_offset_ms: float = Field(
        0.0, ge=0, le=200, description="reception stamps: mean of stamp minus exposure")
    camera_timestamp_jitter_ms: float = Field(
        0.0, ge=0, le=20,
        description="reception stamps: sigma of the per-frame jitter (truncated at 3 sigma)")
    robot_state_latency_ms: float = Field(
        0.0, ge=0, le=100, description="the arm reports the pose it had this long before the stamp")
    robot_joint_offset_error_rad: float = Field(
        0.0, ge=0, le=0.01,
        description="sigma of the true joint zero offsets (kinematic error of the reported pose)")
    tracker_clock_offset_ms: float = Field(
        0.0, ge=-200, le=200, description="the tracker's stamps minus the true sample times")
    camera_clock_rate_error_ppm: float = Field(
        0.0, ge=-500, le=500,
        description="the camera's frame clock runs this much fast (negative: slow) against the host's")

    @model_validator(mode="after")
    def _check(self) -> RigErrorsConfig:
        if self.camera_timestamp == "exposure" and (self.camera_reception_offset_ms > 0
                                                     or self.camera_timestamp_jitter_ms > 0):
            raise ValueError("camera_reception_offset_ms / camera_timestamp_jitter_ms need "
                             'camera_timestamp = "reception"')
        return self


class SimulationConfig(BaseModel):
    """The simulated world."""

    model_config = STRICT

    seed: int = Field(0, ge=0, description="every random quantity derives from it")
    real_time: bool = Field(False, description="run on the wall clock (console) instead of a manual clock")
    patient: PatientConfig = PatientConfig()
    breathing: BreathingConfig = BreathingConfig()
    drift: DriftConfig = DriftConfig()
    shifts: tuple[ShiftConfig, ...] = ()
    tremor: TremorConfig = TremorConfig()
    body: BodyConfig = Field(BodyConfig(), description="rigid or deformable body, trace-driven or not")
    rig_errors: RigErrorsConfig = Field(RigErrorsConfig(), description="rig errors unknown to the controller")
    breath_holds: tuple[BreathHoldConfig, ...] = ()
    hold_ramp_s: float = Field(0.4, ge=0, description="ease in/out of a breath-hold")
    hold_reaction_s: float = Field(1.0, ge=0, description="delay before a requested hold starts")
    T_optical_from_robot: TransformConfig = Field(
        TransformConfig(translation_mm=(60.0, 300.0, 1120.0), rotvec_rad=(math.pi, 0.0, 0.0)),
        description="true robot base pose seen from the left camera (unknown to the controller)")
    T_optical_from_tracker: TransformConfig = Field(
        TransformConfig(translation_mm=(-190.0, 0.0, 1100.0), rotvec_rad=(math.pi, 0.0, 0.0)),
        description="true EM transmitter pose seen from the left camera")
