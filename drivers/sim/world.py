"""The simulated world shared by the simulated devices: phantom, scripted motion, placements.

One world per setup; deterministic for a seed. The world's time is the injected clock: time 0
is the moment the world was created. Ground truth (true marker positions, true transforms) is
available here for tests; the controller never sees it, only device data.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.sim.motion import MotionSample, PatientMotion, stream_rng
from hil.clock import Clock
from hil.config.setup import FramesConfig, SetupConfig
from hil.config.simulation import BreathHoldConfig, PatientConfig, SimulationConfig
from hil.geometry.transform import RigidTransform
from hil.log import get_logger

FloatArray = NDArray[np.float64]
_GOLDEN_ANGLE_RAD = math.pi * (3.0 - math.sqrt(5.0))
FLANGE_MARKER_ID_BASE = 100

_log = get_logger(__name__)


@dataclass(frozen=True)
class Phantom:
    """The phantom in the image (CT) frame, mm: skin markers with outward normals, entry, target."""

    markers_mm: FloatArray
    normals: FloatArray
    entry_mm: FloatArray
    target_mm: FloatArray
    outer_diameter_mm: float
    inner_diameter_mm: float


def _skin(x: float, y: float, radius_mm: float) -> tuple[FloatArray, FloatArray]:
    """Point on the cylinder skin (axis along y, top line z = 0) above (x, y), and its normal."""
    z = math.sqrt(radius_mm**2 - x**2) - radius_mm
    n = np.array([x, 0.0, z + radius_mm]) / radius_mm
    return np.array([x, y, z]), n


def phantom_from_config(cfg: PatientConfig) -> Phantom:
    """The phantom geometry: a pure function of the patient config (no randomness), so a bundled
    plan file stays consistent with the simulator. Markers lie on a golden-angle spiral (no
    symmetry, so marker matching is unambiguous)."""
    n = cfg.marker_count
    c = cfg.marker_spread_mm / math.sqrt(n)
    pts, normals = [], []
    for k in range(n):
        r = c * math.sqrt(k + 0.5)
        a = k * _GOLDEN_ANGLE_RAD + 0.3
        p, nv = _skin(r * math.cos(a), r * math.sin(a), cfg.torso_radius_mm)
        pts.append(p)
        normals.append(nv)
    entry, _ = _skin(cfg.entry_xy_mm[0], cfg.entry_xy_mm[1], cfg.torso_radius_mm)
    return Phantom(
        markers_mm=np.array(pts), normals=np.array(normals), entry_mm=entry,
        target_mm=entry + np.asarray(cfg.target_offset_mm, dtype=np.float64),
        outer_diameter_mm=cfg.marker_outer_diameter_mm, inner_diameter_mm=cfg.marker_inner_diameter_mm,
    )


def plan_document(cfg: PatientConfig) -> dict[str, Any]:
    """The plan a CT of the phantom gives (image frame, mm): the content of ``configs/plans/*.json``."""
    ph = phantom_from_config(cfg)
    return {
        "format": "hil-plan",
        "version": 1,
        "frame": "image",
        "units": "mm",
        "fiducials_mm": np.round(ph.markers_mm, 4).tolist(),
        "entry_mm": np.round(ph.entry_mm, 4).tolist(),
        "target_mm": np.round(ph.target_mm, 4).tolist(),
    }


class FlangeSource(Protocol):
    """What the world needs from a simulated robot: its flange pose at a time."""

    def T_robot_from_flange_at(self, t_ns: int) -> RigidTransform: ...


class SimWorld:
    """The shared world.

    Args:
        sim: the ``[simulation]`` section.
        frames: the ``[frames]`` section (flange marker layout).
        clock: the controller's clock; world time 0 = ``clock.now_ns()`` at construction.
    """

    def __init__(self, sim: SimulationConfig, frames: FramesConfig, clock: Clock) -> None:
        self.sim = sim
        self.frames = frames
        self.clock = clock
        self.seed = sim.seed
        self.t0_ns = clock.now_ns()
        self.phantom = phantom_from_config(sim.patient)
        self.motion = PatientMotion(sim)
        self.T_optical_from_image0 = sim.patient.T_optical_from_image.as_transform()
        self.T_optical_from_robot = sim.T_optical_from_robot.as_transform()
        self.T_optical_from_tracker = sim.T_optical_from_tracker.as_transform()
        self.flange_markers_mm = np.asarray(frames.flange_markers_mm, dtype=np.float64)
        n = np.asarray(frames.flange_marker_normal, dtype=np.float64)
        self.flange_marker_normal: FloatArray = n / np.linalg.norm(n)
        self._robot: FlangeSource | None = None
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ time
    def t_s(self, t_ns: int) -> float:
        """World time (s) of a clock reading."""
        return (t_ns - self.t0_ns) * 1e-9

    def now_s(self) -> float:
        return self.t_s(self.clock.now_ns())

    def rng(self, name: str, *index: int) -> np.random.Generator:
        """A reproducible random stream of this world (seed, name, index...)."""
        return stream_rng(self.seed, name, *index)

    # ------------------------------------------------------------------ scenario requests
    def request_breath_hold(
        self, duration_s: float, level: float = 0.0, delay_s: float | None = None,
    ) -> float:
        """The surgeon asks for a breath-hold: it starts after ``delay_s`` (default the configured
        reaction time) and lasts ``duration_s``. Returns the world time it starts (s)."""
        start = self.now_s() + (self.sim.hold_reaction_s if delay_s is None else delay_s)
        hold = BreathHoldConfig(start_s=start, duration_s=duration_s, level=level)
        with self._lock:
            self.motion.holds.append(hold)
        _log.info("breath_hold_requested", start_s=start, duration_s=duration_s, level=level)
        return start

    def attach_robot(self, robot: FlangeSource) -> None:
        """The simulated robot registers itself so the camera sees its flange markers."""
        self._robot = robot

    # ------------------------------------------------------------------ ground truth
    def motion_at(self, t_ns: int) -> MotionSample:
        with self._lock:
            return self.motion.sample(self.t_s(t_ns))

    def T_optical_from_image(self, t_ns: int) -> RigidTransform:
        """Where the phantom (CT frame) is at ``t_ns``, seen from the left camera."""
        return self.T_optical_from_image0 @ self.motion_at(t_ns).T_image0_from_image

    def patient_markers_optical(self, t_ns: int) -> tuple[FloatArray, FloatArray]:
        """Skin marker centres (N,3) and unit normals (N,3) in the optical frame at ``t_ns``."""
        T = self.T_optical_from_image(t_ns)
        return T.apply(self.phantom.markers_mm), T.apply_vector(self.phantom.normals)

    def target_optical(self, t_ns: int) -> FloatArray:
        return self.T_optical_from_image(t_ns).apply(self.phantom.target_mm)

    def entry_optical(self, t_ns: int) -> FloatArray:
        return self.T_optical_from_image(t_ns).apply(self.phantom.entry_mm)

    def T_optical_from_flange(self, t_ns: int) -> RigidTransform | None:
        if self._robot is None:
            return None
        return self.T_optical_from_robot @ self._robot.T_robot_from_flange_at(t_ns)

    def flange_markers_optical(self, t_ns: int) -> tuple[FloatArray, FloatArray]:
        """Flange marker centres and normals in the optical frame (empty without a robot)."""
        T = self.T_optical_from_flange(t_ns)
        if T is None:
            return np.zeros((0, 3)), np.zeros((0, 3))
        n = T.apply_vector(self.flange_marker_normal[None, :])
        normals = np.repeat(n, len(self.flange_markers_mm), axis=0)
        return T.apply(self.flange_markers_mm), normals


def world_from_setup(setup: SetupConfig, clock: Clock) -> SimWorld:
    """The world factory registered by the built-in plugin."""
    return SimWorld(setup.simulation, setup.frames, clock)
