"""Assembly: the controller ``hil run``, the console, campaigns and the soak build for a setup —
the marker locator on the setup's calibration, the rig geometry (CAD or the rig calibration
file), the procedure, the ``[safety]`` limits and watchdog ages, the simulated world as coach and
truth, the needle-axis check, the tracker's roles, the runtime plugins (OpenIGTLink included).

One place builds it, so every entry point runs the very same controller. Nothing here blocks
except loading files; errors are the loaders' typed ones (InputFileError, CalibrationError).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.interfaces.camera import StereoCamera
from drivers.interfaces.robot import Robot
from hil.clock import Clock, MonotonicClock
from hil.config import Devices
from hil.config.build import RobotFollower
from hil.config.setup import SetupConfig
from hil.controller.compensation import limiter_args
from hil.controller.controller import Controller
from hil.controller.crosscheck import CrossCheckBounds
from hil.controller.observers import HookCaller, TickObserver
from hil.controller.operator_input import Operator
from hil.controller.perception import CollinearNeedleChecker, StereoMarkerLocator, StereoNeedleChecker
from hil.controller.perception import StereoMarkerLocator as _Locator  # tests may substitute the factory
from hil.controller.plan_file import ProcedurePlan
from hil.controller.planning import RigGeometry
from hil.controller.tracker_use import TrackerUse
from hil.controller.truth import BreathHoldCoach, GroundTruth
from hil.errors import ConfigError, InputFileError
from hil.rigcal.apply import (
    flange_markers_mm,
    optical_correction,
    rig_calibration_sha256,
    with_rig_time_offsets,
)
from hil.session.log import SessionLog, file_sha256
from hil.tracking.session import load_tracker_calibration
from hil.vision.camera_model import StereoCalibration, load_calibration
from hil.vision.tracking import TrackingParams
from plugins.manager import HilPlugins

if TYPE_CHECKING:
    from hil.igtl.server import IgtlServer


def rig_geometry(setup: SetupConfig, robot: Robot) -> RigGeometry:
    """The end effector: the guide on the flange (``[frames]``), the flange markers (``[calibration]
    rig``, else the CAD layout) and the TCP the robot driver reports (its ``T_flange_from_tcp``)."""
    return RigGeometry(setup.frames.T_flange_from_guide.as_transform(),
                       flange_markers_mm(setup), robot.T_flange_from_tcp)


def stereo_calibration(setup: SetupConfig, camera: StereoCamera | None) -> StereoCalibration:
    """The stereo calibration perception uses: the setup's ``[calibration] stereo`` file when
    given, else the one the camera knows (:attr:`StereoCamera.calibration`; the simulator's).

    Raises:
        InputFileError: the calibration file cannot be read or is invalid.
        ConfigError: neither gives one (a camera driver that knows no calibration, and no
            ``[calibration] stereo`` in the setup).
    """
    if setup.calibration.stereo is not None:
        return load_calibration(setup.calibration.stereo)
    cal = None if camera is None else camera.calibration
    if cal is not None:
        return cal
    driver = str(setup.camera.driver)
    raise ConfigError("setup", [
        f"calibration.stereo: missing, and the camera driver {driver!r} does not know its stereo "
        "calibration; set [calibration] stereo to a calibration file (hil calibrate writes one)"])


def marker_locator(setup: SetupConfig, camera: StereoCamera | None) -> StereoMarkerLocator:
    """The controller's marker locator on the setup's calibration, its points corrected by the
    rig calibration's optical correction when it has one: region-of-interest tracking when
    ``[procedure.vision] roi_tracking`` (the default), else a full-frame search per pair."""
    v = setup.procedure.vision
    loc = StereoMarkerLocator(stereo_calibration(setup, camera), correction=optical_correction(setup))
    if v.roi_tracking and isinstance(loc, _Locator):  # (tests may substitute their own locator)
        loc.use_tracking(TrackingParams(window_margin_px=v.window_margin_px,
                                        reacquire_every=v.reacquire_every_frames,
                                        lost_retry_every=v.lost_retry_every_frames))
    return loc


def _needle_checker(setup: SetupConfig,
                    camera: StereoCamera) -> StereoNeedleChecker | CollinearNeedleChecker | None:
    """The seed-004 needle-axis check when ``[procedure.lock.needle_check]`` is set, else None:
    contour lines (``method = "cylinder"``) or collinear beads (``method = "collinear"``), in the
    camera space of the rig calibration's optical correction when it has one."""
    nc = setup.procedure.lock.needle_check
    if nc is None:
        return None
    correction = optical_correction(setup)
    if nc.method == "collinear":
        return CollinearNeedleChecker(stereo_calibration(setup, camera), nc.bead_positions_mm(),
                                      nc.max_mono_stereo_deg, correction)
    return StereoNeedleChecker(stereo_calibration(setup, camera), nc.radius_mm, correction)


#: Takes the robot driver the setup built (CONFIGURED, not opened) and returns the robot the
#: controller commands instead -- a recording, checking or fault-injecting wrapper. The wrapper
#: owns the inner driver's lifecycle: its ``open``/``close`` open and close the inner one.
RobotWrapper = Callable[[Robot], Robot]


def wrap_robot(devices: Devices, wrapper: RobotWrapper) -> Devices:
    """``devices`` (not opened) with the robot replaced by ``wrapper(devices.robot)``; open and
    close the result (``open_all``/``close_all``) instead of the original."""
    return dataclasses.replace(devices, robot=wrapper(devices.robot))


def with_servo_process(setup: SetupConfig, devices: Devices, clock: Clock) -> Devices:
    """``devices`` (not opened) with the robot replaced by the servo process's
    :class:`~hil.servo.client.ServoRobot` when ``[servo] process`` asks for it (``auto``: on the
    wall clock), else unchanged (the controller then steps the servo loop in its own process).
    Opening the result starts the servo process (it builds and opens its own robot from the setup;
    the robot in ``devices`` is never opened); closing it stops the arm and ends the process. A
    simulated world then sees the arm the servo process reports.

    Raises:
        ConfigError: ``[servo] process = "on"`` on a simulated clock (a deterministic simulation
            steps its loop in-process).
    """
    mode = setup.servo.process
    if mode == "off" or (mode == "auto" and not isinstance(clock, MonotonicClock)):
        return devices
    if not isinstance(clock, MonotonicClock):
        raise ConfigError("setup", ['servo.process: "on" needs the wall clock; set [simulation] real_time '
                                    '= true, or use "auto"'])
    from hil.servo.client import ServoRobot
    from hil.servo.process import ServoProcess, ServoSpec

    sv = setup.servo
    inner = devices.robot
    spec = ServoSpec(setup, limiter_args(setup.procedure, rig_geometry(setup, inner).T_tcp_from_guide),
                     realtime=sv.realtime, priority=sv.priority, cpu=sv.cpu, reserve_cpu=sv.reserve_cpu)
    robot = ServoRobot(ServoProcess(spec, inner.name, inner.T_flange_from_tcp), inner.limits)
    if isinstance(devices.world, RobotFollower):
        devices.world.follow_robot(robot.state_view())
    return dataclasses.replace(devices, robot=robot)


def with_perception_process(setup: SetupConfig, devices: Devices, clock: Clock) -> Devices:
    """``devices`` (not opened) with the camera run by the perception process when ``[perception]
    process`` asks for it (``auto``: on the wall clock, where the setup allows), else unchanged;
    call it after :func:`with_servo_process`. Opening the result opens the robot first, then
    starts the perception process (it builds and opens its own camera from the setup); closing it
    ends the process. See :func:`hil.perception.camera.with_perception_process` (the rules, the
    ConfigError for ``on`` where it cannot run)."""
    mode = setup.perception.process
    if mode == "off" or (mode == "auto" and not isinstance(clock, MonotonicClock)):
        return devices
    from hil.perception.camera import with_perception_process as wire

    return wire(setup, devices, clock)


def session_header(config_path: Path, setup: SetupConfig, plan: ProcedurePlan, devices: Devices,
                   clock: Clock) -> dict[str, Any]:
    """The fields of a session log's first record that ``hil run`` and ``hil console`` share
    (docs/run.md "Session log"): the setup and plan with the hashes of their files, the seed, the
    procedure, and where markers are located -- ``perception_process`` and, when not there,
    ``perception_in_supervisor_because`` (one line). Call it with the devices as wrapped
    (:func:`with_servo_process`, :func:`with_perception_process`), before they are opened."""
    from hil.perception.camera import PerceptionCamera, in_supervisor_because

    in_perception = isinstance(devices.camera, PerceptionCamera)
    cal = setup.calibration
    return {
        "setup": str(config_path), "setup_name": setup.name,
        "config_sha256": file_sha256(config_path),
        "resolved_setup_sha256": hashlib.sha256(
            json.dumps(setup.resolved(), sort_keys=True, default=str).encode()).hexdigest(),
        "plan": plan.source,
        "plan_sha256": file_sha256(plan.source) if Path(plan.source).is_file() else None,
        "calibration": str(cal.stereo) if cal.stereo else None,
        "calibration_sha256": file_sha256(cal.stereo) if cal.stereo else None,
        "rig_calibration": str(cal.rig) if cal.rig else None,
        "rig_calibration_sha256": rig_calibration_sha256(setup),
        "seed": setup.simulation.seed if devices.world is not None else None,
        "procedure": setup.procedure.model_dump(mode="json"),
        "perception_process": in_perception,
        "perception_in_supervisor_because": None if in_perception else (
            in_supervisor_because(setup, devices, clock) or "the robot is wrapped (a campaign's faults)"),
    }


def build_controller(setup: SetupConfig, plan: ProcedurePlan, devices: Devices, *, clock: Clock,
                     session: SessionLog, operator: Operator,
                     observers: Sequence[TickObserver] = (), hooks: HookCaller | None = None) -> Controller:
    """The controller ``hil run`` builds for ``setup`` on ``devices`` (ACTIVE, or opened before
    :meth:`Controller.run`): marker locator on the setup's stereo calibration, rig geometry,
    procedure, ``[safety]`` limits and watchdog ages, the simulated world as breath-hold coach and
    ground truth when there is one, the needle-axis check when configured. To command the robot
    through a wrapper, build ``devices`` with :func:`wrap_robot` first. Raises what the
    calibration loader raises (InputFileError) for a bad calibration file."""
    sf = setup.safety
    devices = with_rig_time_offsets(setup, devices)  # [calibration] rig: stamps at the true times
    world = devices.world
    return Controller(
        camera=devices.camera, robot=devices.robot, tracker=devices.tracker, clock=clock,
        locate=marker_locator(setup, devices.camera), plan=plan, rig=rig_geometry(setup, devices.robot),
        procedure=setup.procedure, limits=sf.motion_limits(),
        watchdog_ages_s={"camera": sf.camera_frame_max_age_ms / 1e3,
                         "robot": sf.robot_state_max_age_ms / 1e3,
                         "tracker": sf.tracker_max_age_ms / 1e3},
        session=session, operator=operator,
        coach=world if isinstance(world, BreathHoldCoach) else None,
        truth=world if isinstance(world, GroundTruth) else None,
        needle_check=_needle_checker(setup, devices.camera),
        observers=observers, hooks=hooks,
        tracker_use=_tracker_use(setup, world is not None),
        crosscheck=CrossCheckBounds(sf.camera_discrepancy_mm, sf.camera_discrepancy_deg,
                                    sf.camera_discrepancy_s),
        camera_silence_s=None if sf.camera_silence_ms is None else sf.camera_silence_ms / 1e3,
    )


def _tracker_use(setup: SetupConfig, simulated_world: bool) -> TrackerUse | None:
    """The tracker's part in the procedure (``[procedure.tracking]``), or None when no sensor is
    configured for use or the setup has no tracker. The tracker registration comes from
    ``calibration`` (a ``hil tracker-calibrate`` file); a simulated setup without one uses its
    own transmitter mounting (``[simulation] T_optical_from_tracker``).

    Raises:
        InputFileError: no usable tracker registration.
        CalibrationError: the calibration file is malformed.
    """
    tc = setup.procedure.tracking
    if setup.tracker is None or (tc.needle_sensor is None and tc.reference_sensor is None
                                 and tc.target_sensor is None):
        return None
    if tc.calibration is not None:
        path = Path(tc.calibration)
        if not path.is_absolute():
            path = setup.config_dir / path
        _, T = load_tracker_calibration(path)
        if T is None:
            raise InputFileError(str(path), "no registration (T_optical_from_tracker): run "
                                            "hil tracker-calibrate with stylus touches")
    elif simulated_world:
        T = setup.simulation.T_optical_from_tracker.as_transform()
    else:
        raise InputFileError("[procedure.tracking]", "uses tracker sensors but names no calibration "
                                                     "(the tracker registration)")
    return TrackerUse(tc, T)


def start_igtl(setup: SetupConfig, clock: Clock) -> IgtlServer | None:
    """The read-only OpenIGTLink server of ``[igtl]`` when enabled (started), else None.

    Raises:
        IgtlError: the port cannot be bound, or the ``igtl`` extra (pyigtl) is missing.
    """
    if not setup.igtl.enabled:
        return None
    from hil.igtl.server import IgtlServer

    server = IgtlServer(setup.igtl, clock)
    server.start()
    return server


def runtime_plugins(igtl: IgtlServer | None, plan: ProcedurePlan) -> HilPlugins:
    """The installed plugins (entry points: their ``hil_on_tick`` / ``hil_on_transition`` see the
    run) plus, when the OpenIGTLink server runs, the built-in stream on the same hooks."""
    plugins = HilPlugins()
    if igtl is not None:
        from hil.igtl.plugin import PLUGIN_NAME, IgtlPlugin

        plugins.register(IgtlPlugin(igtl, plan), PLUGIN_NAME)
    return plugins
