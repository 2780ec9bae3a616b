"""Rigs drawn at random within declared tolerances (issue 43, "accuracy over many rigs").

A device maker states the accuracy a lab can expect as a distribution over rigs built within
tolerances, not as one rig's figure. :class:`RigTolerances` declares, for every knob of
``[simulation.rig_errors]`` and for the camera's and the tracker's placement, the interval a built
rig lies in; :func:`draw_rig` draws one rig from it, a pure function of ``(seed, tolerances)``.

Every numeric knob is drawn **uniformly** in its ``[low, high]`` interval (a tolerance band, the
way a drawing or a data sheet states one; uniform puts as much weight at the edges as anywhere,
the pessimistic choice). Several knobs are themselves spreads the simulated world then draws from
with the rig's seed (``flange_marker_error_mm`` is the per-axis sigma of each marker's offset from
CAD; ``camera_calibration_error_px`` and ``robot_joint_offset_error_rad`` likewise), so a rig is its
knob values *and* its seed, which also becomes ``[simulation] seed``.

Placement: the camera of a drawn rig stands moved from the configured place by a rigid motion
whose translation is uniform in ``+-camera_placement_mm`` per axis and whose rotation vector is
uniform in ``+-camera_placement_deg`` per component (camera frame, about the left camera's
centre); everything the camera sees (robot base, tracker, patient) is seen moved accordingly. The
tracker's transmitter stands moved likewise, in its own frame. In the simulator the controller
learns the robot base from the flange markers at every run, and is given the tracker's true
placement (there is no tracker-registration error knob), so placement changes the geometry the
procedure works in, not what the controller is told.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, Field, ValidationError, model_validator

from hil.config.simulation import RigErrorsConfig, SimulationConfig
from hil.config.types import STRICT, TransformConfig
from hil.errors import InputFileError
from hil.geometry.transform import RigidTransform

#: Mixed into every draw's random stream, so a rig's draw is independent of the world the same
#: seed makes (``[simulation] seed`` drives the simulator's own streams).
DRAW_STREAM = 43


def _ordered(v: tuple[float, float]) -> tuple[float, float]:
    if not v[0] <= v[1]:
        raise ValueError(f"[low, high] must have low <= high, got {list(v)}")
    return v


#: A tolerance band ``[low, high]``, drawn uniformly.
Band = Annotated[tuple[float, float], AfterValidator(_ordered)]

#: The knobs of ``[simulation.rig_errors]`` drawn from a band, in draw order (fixed: the same seed
#: gives the same rig across versions as long as this order stays).
BAND_KNOBS: tuple[str, ...] = (
    "flange_marker_error_mm", "camera_calibration_error_px", "camera_reception_offset_ms",
    "camera_timestamp_jitter_ms", "robot_state_latency_ms", "robot_joint_offset_error_rad",
    "tracker_clock_offset_ms", "camera_clock_rate_error_ppm",
)


class RigTolerances(BaseModel):
    """The tolerances rigs are built within (``tools/bench accuracy --rigs N --tolerances FILE``;
    the defaults describe a lab rig like ``configs/sim_realistic.toml``'s, docs/bringup.md).

    Each ``[low, high]`` band is drawn uniformly; a band must lie inside the bounds of its
    ``[simulation.rig_errors]`` key (docs/config.md).
    """

    model_config = STRICT

    flange_marker_error_mm: Band = Field(
        (0.1, 0.5), description="per-axis sigma of each flange marker's offset from the CAD layout, mm")
    camera_calibration_error_px: Band = Field(
        (0.05, 0.3), description="reprojection RMS the stereo calibration file is off by, px")
    camera_timestamp: Literal["exposure", "reception"] = Field(
        "reception", description="what the camera stamps frames with (not drawn: a camera's design)")
    camera_reception_offset_ms: Band = Field(
        (20.0, 50.0), description="mean frame stamp minus exposure, ms (reception stamps; keep it plus "
                                  "3 jitter sigmas under the sim camera's latency_ms, which caps it)")
    camera_timestamp_jitter_ms: Band = Field(
        (0.0, 2.0), description="sigma of the per-frame stamp jitter, ms (reception stamps)")
    robot_state_latency_ms: Band = Field(
        (2.0, 16.0), description="how late the arm's reported pose is, ms")
    robot_joint_offset_error_rad: Band = Field(
        (0.0, 0.0002), description="sigma of the arm's true joint zero offsets, rad")
    tracker_clock_offset_ms: Band = Field(
        (-40.0, 40.0), description="tracker stamps minus true sample times, ms")
    camera_clock_rate_error_ppm: Band = Field(
        (-100.0, 100.0), description="camera frame clock rate error against the host's, ppm")
    camera_placement_mm: float = Field(
        20.0, ge=0, le=200, description="camera placement: translation uniform in +-this per axis, mm")
    camera_placement_deg: float = Field(
        1.5, ge=0, le=10,
        description="camera placement: rotation vector uniform in +-this per component, deg")
    tracker_placement_mm: float = Field(
        20.0, ge=0, le=200, description="tracker transmitter placement: +-this per axis, mm")
    tracker_placement_deg: float = Field(
        1.5, ge=0, le=10, description="tracker transmitter placement: rotation +-this per component, deg")

    @model_validator(mode="after")
    def _within_knob_bounds(self) -> RigTolerances:
        # both ends of every band must make a valid [simulation.rig_errors]
        for end in (0, 1):
            values = {k: getattr(self, k)[end] for k in BAND_KNOBS}
            try:
                RigErrorsConfig(camera_timestamp=self.camera_timestamp, **values)
            except ValidationError as exc:
                err = exc.errors()[0]
                where = ".".join(str(p) for p in err["loc"])
                which = "high" if end else "low"
                raise ValueError(f"{where}: {err['msg']} (at the band's {which} end)") from None
        return self


class RigDraw(BaseModel):
    """One drawn rig: its seed (also the world's ``[simulation] seed``), its rig errors, and how
    far the camera and the tracker stand from their configured places
    (``T_<drawn>_from_<configured>``, in the device's own frame)."""

    model_config = STRICT

    seed: int = Field(ge=0)
    rig_errors: RigErrorsConfig
    T_camera_from_nominal_camera: TransformConfig
    T_tracker_from_nominal_tracker: TransformConfig


def _uniform(rng: np.random.Generator, band: tuple[float, float]) -> float:
    lo, hi = band
    return min(hi, lo + (hi - lo) * float(rng.random()))


def _placement(rng: np.random.Generator, mm: float, deg: float) -> TransformConfig:
    t = mm * (2.0 * rng.random(3) - 1.0)
    r = math.radians(deg) * (2.0 * rng.random(3) - 1.0)
    return TransformConfig(translation_mm=(float(t[0]), float(t[1]), float(t[2])),
                           rotvec_rad=(float(r[0]), float(r[1]), float(r[2])))


def draw_rig(seed: int, tolerances: RigTolerances) -> RigDraw:
    """Draw rig ``seed`` within ``tolerances``: every band knob uniform in its band (in
    :data:`BAND_KNOBS` order), then the camera's and the tracker's placement. Pure and
    deterministic: the same seed and tolerances give the same rig, on any machine.

    Raises:
        ValueError: ``seed`` is negative.
    """
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    rng = np.random.default_rng([DRAW_STREAM, seed])
    values = {k: _uniform(rng, getattr(tolerances, k)) for k in BAND_KNOBS}
    rig = RigErrorsConfig(camera_timestamp=tolerances.camera_timestamp, **values)
    camera = _placement(rng, tolerances.camera_placement_mm, tolerances.camera_placement_deg)
    tracker = _placement(rng, tolerances.tracker_placement_mm, tolerances.tracker_placement_deg)
    return RigDraw(seed=seed, rig_errors=rig, T_camera_from_nominal_camera=camera,
                   T_tracker_from_nominal_tracker=tracker)


def _config(T: RigidTransform) -> TransformConfig:
    rows = tuple((float(a), float(b), float(c), float(d)) for a, b, c, d in T.as_matrix())
    return TransformConfig(matrix=rows)


def apply_draw(sim: SimulationConfig, draw: RigDraw) -> SimulationConfig:
    """``sim`` with the drawn rig: its seed and rig errors; the robot base, the tracker and the
    patient seen from the moved camera (``T_optical_from_x <- T_camera_from_nominal_camera @
    T_optical_from_x``), the tracker moved in its own frame (``T_optical_from_tracker <- ... @
    T_tracker_from_nominal_tracker^-1``). Placements are written as 4x4 matrices."""
    D = draw.T_camera_from_nominal_camera.as_transform()
    E = draw.T_tracker_from_nominal_tracker.as_transform().inverse()
    patient = sim.patient.model_copy(update={
        "T_optical_from_image": _config(D @ sim.patient.T_optical_from_image.as_transform())})
    return sim.model_copy(update={
        "seed": draw.seed, "rig_errors": draw.rig_errors, "patient": patient,
        "T_optical_from_robot": _config(D @ sim.T_optical_from_robot.as_transform()),
        "T_optical_from_tracker": _config(D @ sim.T_optical_from_tracker.as_transform() @ E),
    })


def load_tolerances(path: Path) -> RigTolerances:
    """Read a tolerances TOML file: the keys of :class:`RigTolerances` at top level (bands as
    ``[low, high]``); missing keys keep their defaults.

    Raises:
        InputFileError: unreadable, not TOML, an unknown key or a bad band (one line, naming it).
    """
    try:
        doc = tomllib.loads(path.read_text())
    except OSError as exc:
        raise InputFileError(str(path), f"cannot read: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputFileError(str(path), f"not TOML: {exc}") from None
    try:
        return RigTolerances.model_validate(doc)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "tolerances"
        raise InputFileError(str(path), f"{where}: {err['msg']}") from None
