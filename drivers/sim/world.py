"""The simulated world shared by the simulated devices: phantom, scripted motion, placements.

One world per setup; deterministic for a seed. The world's time is the injected clock: time 0
is the moment the world was created. Ground truth (true marker positions, true transforms) is
available here for tests; the controller never sees it, only device data.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.errors import DriverError
from drivers.interfaces.lifecycle import DeviceState
from drivers.interfaces.robot import Robot
from drivers.sim.body import BodyState, DeformableBody, body_from_config, skin_point
from drivers.sim.motion import MotionSample, PatientMotion, stream_rng
from drivers.sim.patient_faults import PatientFaults
from drivers.sim.rig_errors import true_flange_markers
from hil.clock import Clock
from hil.config.faults import FaultSpec
from hil.config.setup import FramesConfig, SetupConfig
from hil.config.simulation import BreathHoldConfig, PatientConfig, SimulationConfig
from hil.errors import ConfigError
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform
from hil.log import get_logger
from hil.rigcal.truth import RigTruth

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
        p, nv = skin_point(r * math.cos(a), r * math.sin(a), cfg.torso_radius_mm)
        pts.append(p)
        normals.append(nv)
    entry, _ = skin_point(cfg.entry_xy_mm[0], cfg.entry_xy_mm[1], cfg.torso_radius_mm)
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
    """What the world needs from a robot: its flange pose at a time (None: not known yet)."""

    def T_robot_from_flange_at(self, t_ns: int) -> RigidTransform | None: ...


def _interpolate(a: tuple[int, RigidTransform], b: tuple[int, RigidTransform], t_ns: int) -> RigidTransform:
    """Pose at ``t_ns`` between two timed poses: translation linear, rotation along the geodesic."""
    (ta, Ta), (tb, Tb) = a, b
    s = 0.0 if tb <= ta else min(max((t_ns - ta) / (tb - ta), 0.0), 1.0)
    rel = RigidTransform(Ta.R.T @ Tb.R, np.zeros(3))
    R = Ta.R @ RigidTransform.from_rotvec(s * rel.as_rotvec()).R
    return RigidTransform(R, Ta.t + s * (Tb.t - Ta.t))


class RobotPoseFollower:
    """Flange poses of a non-simulated robot driver (e.g. ``ur_rtde`` on the UR emulator), for the
    simulated camera and tracker of a mixed setup.

    A daemon thread samples ``robot.state_now()`` every ``period_s`` (wall time) while the robot is
    ACTIVE and keeps the last ``history`` samples (timestamped by the driver, on the controller
    clock); :meth:`T_robot_from_flange_at` interpolates them at the asked time (the newest sample
    after it, the oldest before it). While the driver cannot report (lost connection, recovery),
    the last known pose stands: the physical arm is somewhere, and the world keeps seeing it
    there. The thread ends when the robot is closed (also one built and never opened).
    The driver's :attr:`~drivers.interfaces.robot.Robot.T_flange_from_tcp` turns the reported TCP
    pose into the flange pose.
    """

    def __init__(self, robot: Robot, period_s: float = 0.01, history: int = 300) -> None:
        self.robot = robot
        self.period_s = period_s
        self.T_tcp_from_flange = robot.T_flange_from_tcp.inverse()
        self._samples: deque[tuple[int, RigidTransform]] = deque(maxlen=history)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.read_errors = 0
        self._thread = threading.Thread(target=self._run, name=f"world-follows-{robot.name}", daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        try:
            st = self.robot.state_now()
        except DriverError:
            self.read_errors += 1
            return
        T = st.T_robot_from_tcp @ self.T_tcp_from_flange
        with self._lock:
            if not self._samples or st.t_ns > self._samples[-1][0]:
                self._samples.append((st.t_ns, T))

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            state = self.robot.state
            if state is DeviceState.ACTIVE:
                self._sample()
            elif state is DeviceState.CLOSED:
                return  # closed (after use, or built and never opened): nothing more to follow

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def T_robot_from_flange_at(self, t_ns: int) -> RigidTransform | None:
        with self._lock:
            samples = list(self._samples)
        if not samples:
            return None
        times = [t for t, _ in samples]
        i = bisect.bisect_left(times, t_ns)
        if i == 0:
            return samples[0][1]
        if i >= len(samples):
            return samples[-1][1]
        return _interpolate(samples[i - 1], samples[i], t_ns)


class SimWorld:
    """The shared world.

    Args:
        sim: the ``[simulation]`` section.
        frames: the ``[frames]`` section (flange marker layout).
        clock: the controller's clock; world time 0 = ``clock.now_ns()`` at construction.
        faults: the setup's ``[[faults]]``; the world plays the patient ones (a cough, a shift, a
            skin marker lost or moved: :mod:`drivers.sim.patient_faults`).
    """

    def __init__(self, sim: SimulationConfig, frames: FramesConfig, clock: Clock,
                 faults: Sequence[FaultSpec] = ()) -> None:
        self.sim = sim
        self.frames = frames
        self.clock = clock
        self.seed = sim.seed
        self.t0_ns = clock.now_ns()
        self.phantom = phantom_from_config(sim.patient)
        self.motion = PatientMotion(sim)
        #: the deformable body (``[simulation.body] model = "deformable"``); None: the rigid body
        self.body: DeformableBody | None = body_from_config(sim, self.phantom, self.motion)
        self.patient_faults = PatientFaults(faults, self.phantom.entry_mm)
        self.T_optical_from_image0 = sim.patient.T_optical_from_image.as_transform()
        self.T_optical_from_robot = sim.T_optical_from_robot.as_transform()
        self.T_optical_from_tracker = sim.T_optical_from_tracker.as_transform()
        self.rig_errors = sim.rig_errors
        # the true layout: the configured (CAD) one moved by [simulation.rig_errors]
        self.flange_markers_mm = true_flange_markers(
            np.asarray(frames.flange_markers_mm, dtype=np.float64), sim.rig_errors.flange_marker_error_mm,
            self.rng("flange_marker_error"))
        n = np.asarray(frames.flange_marker_normal, dtype=np.float64)
        self.flange_marker_normal: FloatArray = n / np.linalg.norm(n)
        self._robot: FlangeSource | None = None
        self._lock = threading.Lock()
        #: called with (start_s, duration_s, level) of every breath-hold requested (a perception
        #: process's copy of this world is told this way)
        self.breath_hold_listeners: list[Callable[[float, float, float], None]] = []

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
        for listener in self.breath_hold_listeners:
            listener(start, duration_s, level)
        return start

    def attach_robot(self, robot: FlangeSource) -> None:
        """The simulated robot registers itself so the camera sees its flange markers."""
        self._robot = robot

    def follow_robot(self, robot: Robot) -> None:
        """Take the flange pose from a non-simulated robot driver (mixed setups such as a simulated
        camera with ``ur_rtde`` on the UR emulator): the setup builder calls this with the
        configured robot (``hil.config.build.RobotFollower``). See :class:`RobotPoseFollower`.

        Raises:
            ConfigError: ``[simulation] real_time = false`` (``hil run`` would then run the world on
                a simulated clock): a real driver lives in real time, so the whole setup must.
        """
        if not self.sim.real_time:
            raise ConfigError("setup", [
                f"simulation.real_time: the robot ({type(robot).__name__}) is not simulated and runs in "
                "real time; set [simulation] real_time = true"])
        if isinstance(self._robot, RobotPoseFollower):
            self._robot.stop()
        self._robot = RobotPoseFollower(robot)
        _log.info("world_follows_robot", robot=robot.name, driver=type(robot).__name__)

    # ------------------------------------------------------------------ ground truth
    def rig_truth(self) -> RigTruth | None:
        """The true rig: flange-marker layout, robot base placement, and each simulated device's
        time offset (``[simulation.rig_errors]``; the camera's is the mean reception offset).
        None when the world follows a non-simulated robot driver: the arm the camera sees is then
        the driver's report, with the driver's own (unknown) latency."""
        if isinstance(self._robot, RobotPoseFollower):
            return None
        e = self.rig_errors
        camera_ms = e.camera_reception_offset_ms if e.camera_timestamp == "reception" else 0.0
        return RigTruth(
            flange_markers_mm=self.flange_markers_mm.copy(), T_optical_from_robot=self.T_optical_from_robot,
            time_offsets_ms={"camera": camera_ms, "robot": e.robot_state_latency_ms,
                             "tracker": e.tracker_clock_offset_ms})

    def motion_at(self, t_ns: int) -> MotionSample:
        with self._lock:
            return self.motion.sample(self.t_s(t_ns))

    def T_optical_from_image(self, t_ns: int) -> RigidTransform:
        """Where the phantom (CT frame) is at ``t_ns``, seen from the left camera: the rigid body's
        whole motion, or the deformable body's rigid part (drift, shifts, tremor)."""
        if self.body is None:
            return self.T_optical_from_image0 @ self.motion_at(t_ns).T_image0_from_image
        with self._lock:
            return self.T_optical_from_image0 @ self.motion.T_rigid(self.t_s(t_ns))

    def body_state(self, t_ns: int) -> BodyState:
        """The body at ``t_ns`` in the optical frame: skin markers, their normals, entry, target."""
        t_s = self.t_s(t_ns)
        with self._lock:
            if self.body is None:
                T = self.T_optical_from_image0 @ self.motion.sample(t_s).T_image0_from_image
                ph = self.phantom
                b = BodyState(markers_mm=ph.markers_mm, normals=ph.normals, entry_mm=ph.entry_mm,
                              target_mm=ph.target_mm)
            else:
                T = self.T_optical_from_image0 @ self.motion.T_rigid(t_s)
                b = self.body.state(t_s)
        if self.patient_faults:
            b = self.patient_faults.apply(t_s, b)
        return BodyState(markers_mm=T.apply(b.markers_mm), normals=T.apply_vector(b.normals),
                         entry_mm=T.apply(b.entry_mm), target_mm=T.apply(b.target_mm))

    def patient_markers_optical(self, t_ns: int) -> tuple[FloatArray, FloatArray]:
        """Skin marker centres (N,3) and unit normals (N,3) in the optical frame at ``t_ns``."""
        b = self.body_state(t_ns)
        return b.markers_mm, b.normals

    def lost_markers(self, t_ns: int) -> frozenset[int]:
        """Skin marker indices the camera cannot see at ``t_ns`` (a ``marker_lost`` patient fault)."""
        return self.patient_faults.lost(self.t_s(t_ns))

    def target_optical(self, t_ns: int) -> FloatArray:
        return self.body_state(t_ns).target_mm

    def entry_optical(self, t_ns: int) -> FloatArray:
        return self.body_state(t_ns).entry_mm

    def body_rigid_residual_mm(self, t_ns: int) -> float:
        """How far the true skin markers are from a rigid copy of the CT's at ``t_ns``: the RMS
        residual of Horn's fit (seed 000 eqs 17-21) of the CT markers onto them, mm (0 for the
        rigid body without patient faults, not computed)."""
        if self.body is None and not self.patient_faults:
            return 0.0
        markers, _ = self.patient_markers_optical(t_ns)
        return float(register_horn(markers, self.phantom.markers_mm).fre_rms_mm)

    def T_optical_from_flange(self, t_ns: int) -> RigidTransform | None:
        if self._robot is None:
            return None
        T = self._robot.T_robot_from_flange_at(t_ns)
        return None if T is None else self.T_optical_from_robot @ T

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
    return SimWorld(setup.simulation, setup.frames, clock, setup.faults)
