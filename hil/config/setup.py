"""The setup model: which device fills each role, and everything around them.

A setup is one TOML file (``configs/*.toml``). Device sections are validated against the model
the driver registry holds for their ``driver``; :func:`hil.config.loader.load_setup` does that.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, PrivateAttr, field_validator, model_validator

from drivers.interfaces.robot import MotionLimits
from hil.config.faults import FaultChannelConfig, FaultSpec
from hil.config.simulation import SimulationConfig
from hil.config.types import STRICT, ConfigPath, TransformConfig, Vec3
from hil.controller.config import ProcedureConfig
from hil.igtl.config import IgtlConfig
from hil.rigcal.config import RigCalibrationConfig

#: Largest accepted camera / tracker watchdog age, ms (stale data beyond this cannot guide a needle).
MAX_WATCHDOG_AGE_MS = 2000.0
#: Largest accepted robot-state watchdog age, ms (a UR streams state at 125-500 Hz).
MAX_ROBOT_STATE_AGE_MS = 1000.0


class SafetyConfig(BaseModel):
    """``[safety]``: hard motion limits (checked before any command reaches a robot) and the
    watchdog ages beyond which data counts as missing."""

    model_config = STRICT

    workspace_min_mm: Vec3 = Field((-500.0, -500.0, -100.0), description="TCP box, robot base frame")
    workspace_max_mm: Vec3 = Field((500.0, 500.0, 600.0), description="TCP box, robot base frame")
    max_speed_mm_s: float = Field(100.0, gt=0, le=1000, description="TCP linear speed")
    max_accel_mm_s2: float = Field(500.0, gt=0, le=5000, description="TCP linear acceleration")
    max_angular_speed_rad_s: float = Field(1.0, gt=0, le=6.3, description="TCP angular speed")
    # Upper bounds: data older than this is useless for guiding a needle; a larger age would
    # quietly turn the watchdog off.
    camera_frame_max_age_ms: float = Field(200.0, gt=0, le=MAX_WATCHDOG_AGE_MS,
                                           description="watchdog: newest stereo pair")
    tracker_max_age_ms: float = Field(200.0, gt=0, le=MAX_WATCHDOG_AGE_MS,
                                      description="watchdog: newest tracker sample")
    robot_state_max_age_ms: float = Field(50.0, gt=0, le=MAX_ROBOT_STATE_AGE_MS,
                                          description="watchdog: newest robot state")
    camera_silence_ms: float | None = Field(
        None, gt=0, le=MAX_WATCHDOG_AGE_MS,
        description="how long no stereo pair may arrive before the camera counts as lost, ms (unset: 4 "
                    "frame periods, at least 200 ms); set it with camera_frame_max_age_ms for a camera or "
                    "simulator that is slower than its frame rate")
    # Camera cross-check of the robot's reported pose (docs/safety.md; GATE, COMPENSATE, LOCK).
    camera_discrepancy_mm: float = Field(
        2.0, gt=0, le=50,
        description="camera cross-check: camera-measured vs robot-reported TCP, translation bound, mm")
    camera_discrepancy_deg: float = Field(2.0, gt=0, le=30,
                                          description="camera cross-check: rotation bound, degrees")
    camera_discrepancy_s: float = Field(
        0.3, gt=0, le=5,
        description="camera cross-check: how long a discrepancy beyond a bound is tolerated, s")
    # Following-error supervision (docs/safety.md): unset = the robot model's own bounds.
    following_error_mm: float | None = Field(
        None, gt=0, le=50, description="following error: translation bound, mm (unset: the robot model's; "
                                       "UR3/UR3e and the simulated arm: 2 mm)")
    following_error_deg: float | None = Field(
        None, gt=0, le=30, description="following error: rotation bound, degrees (unset: the robot model's; "
                                       "UR3/UR3e and the simulated arm: 1.5 deg)")
    following_error_duration_s: float | None = Field(
        None, gt=0, le=2, description="following error: how long a divergence beyond a bound is tolerated, s "
                                      "(unset: the robot model's; UR3/UR3e and the simulated arm: 0.1 s)")

    @model_validator(mode="after")
    def _box(self) -> SafetyConfig:
        for axis, lo, hi in zip("xyz", self.workspace_min_mm, self.workspace_max_mm, strict=True):
            if lo >= hi:
                raise ValueError(f"workspace {axis}: min {lo} must be below max {hi}")
        return self

    def motion_limits(self) -> MotionLimits:
        return MotionLimits(
            workspace_min_mm=self.workspace_min_mm, workspace_max_mm=self.workspace_max_mm,
            max_speed_mm_s=self.max_speed_mm_s, max_accel_mm_s2=self.max_accel_mm_s2,
            max_angular_speed_rad_s=self.max_angular_speed_rad_s,
            following_error_mm=self.following_error_mm, following_error_deg=self.following_error_deg,
            following_error_duration_s=self.following_error_duration_s,
        )


class FramesConfig(BaseModel):
    """``[frames]``: fixed transforms of the rig."""

    model_config = STRICT

    T_flange_from_guide: TransformConfig = Field(
        TransformConfig(translation_mm=(0.0, 0.0, 60.0), rotvec_rad=(0.0, 0.0, 0.0)),
        description="needle-guide axis frame in the flange (tool0) frame; guide z = needle direction")
    flange_markers_mm: tuple[Vec3, ...] = Field(
        ((40.0, 90.0, 10.0), (-35.0, 105.0, 10.0), (-10.0, 140.0, 10.0), (30.0, 150.0, 25.0)),
        description="ring-marker centres on the flange plate, flange frame, mm (>= 3)")
    flange_marker_normal: Vec3 = Field((0.0, 0.0, -1.0), description="marker plate normal, flange frame")

    @field_validator("flange_markers_mm")
    @classmethod
    def _enough(cls, v: tuple[Vec3, ...]) -> tuple[Vec3, ...]:
        if len(v) < 3:
            raise ValueError(f"at least 3 flange markers needed, got {len(v)}")
        return v


class CalibrationConfig(BaseModel):
    """``[calibration]``: calibration files (relative to the config file)."""

    model_config = STRICT

    stereo: ConfigPath | None = Field(None, description="stereo calibration JSON (hil.vision format)")
    rig: ConfigPath | None = Field(
        None, description="rig calibration JSON (hil rig-calibrate): flange-marker layout and time offsets")


class ServoConfig(BaseModel):
    """Where the servo loop runs (docs/architecture.md, "The servo loop")."""

    model_config = STRICT

    process: Literal["auto", "on", "off"] = Field(
        "auto", description="run the servo loop in its own process owning the robot driver: auto = "
                            "whenever the setup runs on the wall clock (hil run, console, soak); off = "
                            "in the supervisor's process (simulated runs on the manual clock always are)")
    realtime: bool = Field(True, description="ask for SCHED_FIFO, a pinned CPU and locked memory for the "
                                             "servo process (granted as root; reported either way)")
    priority: int = Field(80, ge=1, le=99, description="SCHED_FIFO priority of the servo process")
    cpu: int | None = Field(None, ge=0, description="CPU to pin the servo process to (default: the last)")
    reserve_cpu: bool = Field(True, description="while the loop runs pinned at SCHED_FIFO, keep the "
                                                "supervisor and the perception process off its CPU when "
                                                "another CPU remains (hil/servo/reserve.py); false: they "
                                                "may use every CPU")


class PerceptionConfig(BaseModel):
    """Where the camera is grabbed and the markers located (docs/architecture.md, "Perception
    process")."""

    model_config = STRICT

    process: Literal["auto", "on", "off"] = Field(
        "auto", description="grab, locate and triangulate in a process of its own that publishes marker "
                           "sets through shared memory: auto = whenever the setup runs on the wall clock "
                           "and it can (no needle check; a simulated world needs the servo process) on a "
                           "machine with 2 or more usable CPUs (the servo loop's; supervisor and "
                           "perception); on = also with fewer CPUs; off = in the supervisor's process "
                           "(simulated runs on the manual clock always are)")
    cpu: int | None = Field(None, ge=0, description="CPU to keep the perception process on, among the "
                                                    "supervisor's (default: the supervisor's CPUs - with "
                                                    "[servo] reserve_cpu, all but the real-time servo loop's "
                                                    "- less the loop's when two or more remain)")


class SetupConfig(BaseModel):
    """A whole hardware setup. Build it with :func:`hil.config.load_setup` (TOML file) or
    :func:`hil.config.parse_setup` (a mapping): device sections need the driver registry.

    ``camera``, ``robot``, ``tracker`` hold instances of the driver's own config model.
    """

    model_config = STRICT

    name: str = Field("", description="free text shown in logs")
    camera: Any = Field(description="stereo camera: driver = name + that driver's keys")
    robot: Any = Field(description="robot arm: driver = name + that driver's keys")
    tracker: Any = Field(None, description="optional magnetic tracker: driver = name + its keys")
    calibration: CalibrationConfig = Field(CalibrationConfig(), description="calibration files")
    safety: SafetyConfig = Field(SafetyConfig(), description="motion limits and watchdog ages")
    frames: FramesConfig = Field(FramesConfig(), description="fixed transforms of the rig")
    simulation: SimulationConfig = Field(SimulationConfig(), description="the simulated world")
    procedure: ProcedureConfig = Field(ProcedureConfig(), description="controller tolerances and policies")
    faults: tuple[FaultSpec, ...] = Field((), description="scheduled faults ([[faults]] tables)")
    fault_channel: FaultChannelConfig | None = Field(
        None, description="the UR emulator's fault channel, for [[faults]] with transport (tools/ursim only)")
    igtl: IgtlConfig = Field(IgtlConfig(), description="OpenIGTLink streaming to 3D Slicer (docs/igtl.md)")
    servo: ServoConfig = Field(ServoConfig(), description="the servo loop's process and real-time set-up")
    perception: PerceptionConfig = Field(PerceptionConfig(), description="the perception process")
    rig_calibration: RigCalibrationConfig = Field(
        RigCalibrationConfig(), description="hil rig-calibrate: poses, bounds, temporal motion")
    _config_dir: Path = PrivateAttr(default_factory=Path.cwd)

    @property
    def config_dir(self) -> Path:
        """Directory of the setup file (relative paths were resolved against it)."""
        return self._config_dir

    @field_validator("camera", "robot", "tracker")
    @classmethod
    def _driver_model(cls, v: Any) -> Any:
        if v is None:
            return v
        if not isinstance(v, BaseModel) or "driver" not in type(v).model_fields:
            raise ValueError("must be a driver config model instance (load the file with load_setup)")
        return v

    @model_validator(mode="after")
    def _target_sensor(self) -> SetupConfig:
        why = target_sensor_problem(self)
        if why is not None:
            raise ValueError(why)
        return self

    def device_sections(self) -> dict[str, BaseModel]:
        """The configured device sections by role (tracker only when present)."""
        out: dict[str, BaseModel] = {"camera": self.camera, "robot": self.robot}
        if self.tracker is not None:
            out["tracker"] = self.tracker
        return out

    def resolved(self) -> dict[str, Any]:
        """JSON-ready dump of the whole resolved setup (paths absolute, defaults filled)."""
        data: dict[str, Any] = self.model_dump(mode="json", exclude={"camera", "robot", "tracker"})
        for role, section in self.device_sections().items():
            data[role] = section.model_dump(mode="json")
        return data


def target_sensor_problem(setup: SetupConfig) -> str | None:
    """What is wrong with ``[procedure.tracking] target_sensor`` in ``setup`` (None: nothing): it
    must name a sensor of the setup's tracker, or the controller would never see it and keep the
    model without saying why. A driver whose config declares no sensor names is not checked."""
    name = setup.procedure.tracking.target_sensor
    if name is None:
        return None
    if setup.tracker is None:
        return f"procedure.tracking.target_sensor = {name!r} needs a tracker: the setup has no [tracker]"
    names = _sensor_names(setup.tracker)
    if names is not None and name not in names:
        return (f"procedure.tracking.target_sensor = {name!r}: the tracker has no such sensor (its sensors: "
                f"{', '.join(names)})")
    return None


def _sensor_names(tracker: BaseModel) -> list[str] | None:
    """The sensor names a tracker driver's config declares (a mapping of name to port, or
    entries with a ``name``), or None when it declares none."""
    sensors = getattr(tracker, "sensors", None)
    if isinstance(sensors, dict):
        return [str(k) for k in sensors]
    if isinstance(sensors, (tuple, list)):
        return [str(getattr(x, "name", x)) for x in sensors]
    return None
