"""What the core needs from a device comes through the interface: a camera's ``calibration`` and
``perception_feed``, a robot's ``T_flange_from_tcp``. Every wrapper hands over its inner device's
value (never a default of its own), and the core raises a clear error when no calibration exists
anywhere."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from drivers.faults import FaultyRobot, FaultyStereoCamera
from drivers.interfaces.camera import StereoCamera, StereoFrame
from drivers.interfaces.robot import MotionLimits, Robot
from drivers.sim.robot import SimRobot, SimRobotConfig
from hil.campaign.recorder import RecordingRobot
from hil.clock import ManualClock
from hil.config import load_setup
from hil.config.setup import SetupConfig
from hil.controller.assembly import marker_locator, rig_geometry, stereo_calibration
from hil.errors import ConfigError
from hil.geometry.transform import RigidTransform
from hil.rigcal.time_align import TimeAlignedCamera, TimeAlignedRobot
from hil.vision.camera_model import StereoCalibration, load_calibration
from tests.controller.fakes import FakeRobot, StubCamera

#: A TCP no wrapper could produce by accident (rotated and offset; identity is the usual default).
TCP = (RigidTransform.from_rotvec(np.array([0.1, -0.2, 0.3]))
       @ RigidTransform.from_translation((4.0, -5.0, 150.0)))
CAL = StereoCalibration.synthetic(image_size=(320, 240), f_px=700.0, baseline_mm=90.0)
SIM = Path("configs/sim.toml")


class _Camera(StubCamera):
    def grab(self, timeout_s: float) -> StereoFrame:
        raise NotImplementedError


def _clock() -> ManualClock:
    return ManualClock(10**9)


ROBOT_WRAPPERS: dict[str, Callable[[Robot], Robot]] = {
    "faults": lambda r: FaultyRobot(r, (), _clock()),
    "time_align": lambda r: TimeAlignedRobot(r, 5_000_000),
    "recorder": lambda r: RecordingRobot(r, MotionLimits(), _clock()),
    "recorder(time_align(faults))": lambda r: RecordingRobot(
        TimeAlignedRobot(FaultyRobot(r, (), _clock()), 1), MotionLimits(), _clock()),
}
CAMERA_WRAPPERS: dict[str, Callable[[StereoCamera], StereoCamera]] = {
    "faults": lambda c: FaultyStereoCamera(c, (), _clock()),
    "time_align": lambda c: TimeAlignedCamera(c, 5_000_000),
    "time_align(faults)": lambda c: TimeAlignedCamera(FaultyStereoCamera(c, (), _clock()), 1),
}


@pytest.mark.parametrize("wrap", ROBOT_WRAPPERS.values(), ids=list(ROBOT_WRAPPERS))
def test_robot_wrappers_pass_the_inner_tcp_through(wrap: Callable[[Robot], Robot]) -> None:
    inner = FakeRobot(_clock(), T_flange_from_tcp=TCP)
    assert wrap(inner).T_flange_from_tcp is TCP


@pytest.mark.parametrize("wrap", CAMERA_WRAPPERS.values(), ids=list(CAMERA_WRAPPERS))
def test_camera_wrappers_pass_the_inner_calibration_through(
        wrap: Callable[[StereoCamera], StereoCamera]) -> None:
    assert wrap(_Camera(calibration=CAL)).calibration is CAL


@pytest.mark.parametrize("wrap", CAMERA_WRAPPERS.values(), ids=list(CAMERA_WRAPPERS))
def test_camera_wrappers_invent_no_calibration(wrap: Callable[[StereoCamera], StereoCamera]) -> None:
    assert wrap(_Camera(calibration=None)).calibration is None


class _Feed:
    """A stand-in perception feed (only its identity is looked at)."""

    produced = 0
    overwritten = 0

    def ready(self) -> bool:
        return False

    def take(self, timeout_s: float, wake: Callable[[], bool] | None = None) -> None:
        return None

    def stop(self, timeout_s: float | None = None) -> None:
        """Nothing to stop."""


class _FeedCamera(_Camera):
    """A camera whose pairs are located elsewhere, as the perception process's camera."""

    def __init__(self, feed: _Feed) -> None:
        super().__init__(calibration=CAL)
        self._feed = feed

    @property
    def perception_feed(self) -> _Feed:
        return self._feed


@pytest.mark.parametrize("wrap", CAMERA_WRAPPERS.values(), ids=list(CAMERA_WRAPPERS))
def test_camera_wrappers_pass_the_inner_perception_feed_through(
        wrap: Callable[[StereoCamera], StereoCamera]) -> None:
    feed = _Feed()
    assert wrap(_FeedCamera(feed)).perception_feed is feed


@pytest.mark.parametrize("wrap", CAMERA_WRAPPERS.values(), ids=list(CAMERA_WRAPPERS))
def test_camera_wrappers_of_a_plain_camera_have_no_perception_feed(
        wrap: Callable[[StereoCamera], StereoCamera]) -> None:
    assert _Camera(calibration=CAL).perception_feed is None
    assert wrap(_Camera(calibration=CAL)).perception_feed is None


def test_the_perception_process_camera_declares_its_process_as_the_feed() -> None:
    from hil.perception.camera import PerceptionCamera
    from hil.perception.process import PerceptionProcess, PerceptionSpec

    process = PerceptionProcess(lambda: PerceptionSpec(_setup(True)), "camera")   # never started
    camera = PerceptionCamera(_Camera(calibration=CAL), process)
    assert camera.perception_feed is process
    assert TimeAlignedCamera(FaultyStereoCamera(camera, (), _clock()), 1).perception_feed is process


def test_the_robot_base_class_needs_the_tcp() -> None:
    with pytest.raises(TypeError, match="T_flange_from_tcp"):
        Robot.__init__(FakeRobot(_clock()), "robot", MotionLimits())  # type: ignore[call-arg]


def test_sim_robot_reports_its_configured_tcp() -> None:
    cfg = SimRobotConfig.model_validate(
        {"driver": "sim", "T_flange_from_tcp": {"translation_mm": [1.0, 2.0, 120.0]}})
    robot = SimRobot("robot", MotionLimits(), cfg, _clock())
    np.testing.assert_array_equal(robot.T_flange_from_tcp.t, [1.0, 2.0, 120.0])


def _setup(stereo: bool) -> SetupConfig:
    s = load_setup(SIM)
    assert s.calibration.stereo is not None
    cal = s.calibration if stereo else s.calibration.model_copy(update={"stereo": None})
    return s.model_copy(update={"calibration": cal})


def test_rig_geometry_takes_the_tcp_from_the_robot() -> None:
    robot = TimeAlignedRobot(FakeRobot(_clock(), T_flange_from_tcp=TCP), 0)
    rig = rig_geometry(_setup(True), robot)
    np.testing.assert_array_equal(rig.T_flange_from_tcp.as_matrix(), TCP.as_matrix())


def test_the_setup_file_comes_before_the_camera() -> None:
    setup = _setup(True)
    assert setup.calibration.stereo is not None
    got = stereo_calibration(setup, _Camera(calibration=CAL))
    np.testing.assert_array_equal(got.K_left, load_calibration(setup.calibration.stereo).K_left)


def test_the_camera_calibration_is_used_without_a_file() -> None:
    cam = FaultyStereoCamera(_Camera(calibration=CAL), (), _clock())
    assert stereo_calibration(_setup(False), cam) is CAL
    assert marker_locator(_setup(False), cam).calibration is CAL


@pytest.mark.parametrize("camera", [_Camera(calibration=None), None], ids=["no_calibration", "no_camera"])
def test_no_calibration_anywhere_is_a_config_error(camera: StereoCamera | None) -> None:
    with pytest.raises(ConfigError) as err:
        marker_locator(_setup(False), camera)
    assert str(err.value) == (
        "setup: calibration.stereo: missing, and the camera driver 'sim' does not know its stereo "
        "calibration; set [calibration] stereo to a calibration file (hil calibrate writes one)")
