"""Each fault kind shows up at the interface as the typed error or flag it should."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from structlog.testing import capture_logs

from drivers.faults import FaultyRobot, FaultyStereoCamera, FaultyTracker, wrap_device
from drivers.interfaces import (
    DeviceFaultError,
    DeviceTimeoutError,
    DisconnectedError,
    LimitViolationError,
    ProtocolError,
    RobotMode,
    SafetyStatus,
    SafetyStopError,
)
from drivers.sim.camera import SimCameraConfig, SimStereoCamera
from drivers.sim.robot import SimRobot, SimRobotConfig
from drivers.sim.tracker import SimTracker, SimTrackerConfig
from drivers.sim.world import SimWorld
from hil.clock import ManualClock
from hil.config import FaultKind, FaultSpec, FramesConfig, SimulationConfig, build_devices, load_setup
from hil.config.faults import FAULT_DEVICE
from hil.geometry.transform import RigidTransform
from hil.vision.camera_model import StereoCalibration
from plugins.registry import DriverRegistry
from tests.devices.conftest import CONFIGS
from tests.devices.test_sim_robot import LIMITS

CAL = StereoCalibration.synthetic(image_size=(640, 480), f_px=500.0)


def fault(kind: str, start_s: float = 1.0, duration_s: float = 1.0, **kw: Any) -> FaultSpec:
    return FaultSpec(kind=FaultKind(kind), start_s=start_s, duration_s=duration_s, **kw)


@pytest.fixture
def world(clock: ManualClock) -> SimWorld:
    return SimWorld(SimulationConfig(), FramesConfig(), clock)


def _camera(clock: ManualClock, world: SimWorld, *faults: FaultSpec) -> FaultyStereoCamera:
    inner = SimStereoCamera("camera", SimCameraConfig(driver="sim", frame_rate_hz=10.0, latency_ms=0.0),
                            clock, world, CAL)
    cam = FaultyStereoCamera(inner, faults, clock)
    cam.open()
    return cam


def _tracker(clock: ManualClock, world: SimWorld, *faults: FaultSpec) -> FaultyTracker:
    t = FaultyTracker(SimTracker("tracker", SimTrackerConfig(driver="sim"), clock, world), faults, clock)
    t.open()
    return t


def _robot(clock: ManualClock, *faults: FaultSpec) -> FaultyRobot:
    r = FaultyRobot(SimRobot("robot", LIMITS, SimRobotConfig(driver="sim"), clock), faults, clock)
    r.open()
    return r


def _grab_at(cam: FaultyStereoCamera, clock: ManualClock, t_s: float, timeout_s: float = 1.0) -> Any:
    clock.advance(max(t_s - (clock.now_ns() - cam.schedule.t_open_ns) * 1e-9, 0.0))  # type: ignore[operator]
    return cam.grab(timeout_s)


# ------------------------------------------------------------------ camera
def test_frame_drop_times_out_inside_the_window(clock: ManualClock, world: SimWorld) -> None:
    cam = _camera(clock, world, fault("frame_drop", 1.0, 1.0))
    assert _grab_at(cam, clock, 0.5).left.seq == 5
    # pairs at 1.2, 1.3, 1.4 s dropped, the next due after the wait: the error gives the whole wait,
    # not the 0.05 s the drops left of it
    with pytest.raises(DeviceTimeoutError, match=r"^camera: no stereo pair within 0\.25 s$"):
        _grab_at(cam, clock, 1.2, timeout_s=0.25)
    clock.advance(0.5)
    assert cam.grab(1.0).left.t_ns - cam.schedule.t_open_ns >= 2_000_000_000  # type: ignore[operator]


def test_frozen_frame_repeats_images_with_new_timestamps(clock: ManualClock, world: SimWorld) -> None:
    cam = _camera(clock, world, fault("frozen_frame", 1.0, 1.0))
    good = _grab_at(cam, clock, 0.9)
    frozen = _grab_at(cam, clock, 1.3)
    assert frozen.left.t_ns > good.left.t_ns
    assert frozen.left.seq > good.left.seq
    assert np.array_equal(frozen.left.image, good.left.image)
    assert np.array_equal(frozen.right.image, good.right.image)
    fresh = _grab_at(cam, clock, 2.1)
    assert not np.array_equal(fresh.left.image, good.left.image)


def test_stale_timestamps(clock: ManualClock, world: SimWorld) -> None:
    cam = _camera(clock, world, fault("stale_timestamp", 1.0, 1.0, age_ms=400.0))
    p = _grab_at(cam, clock, 1.5)
    assert clock.now_ns() - p.left.t_ns == 400_000_000
    assert p.skew_ns == 0


def test_left_right_desync(clock: ManualClock, world: SimWorld) -> None:
    cam = _camera(clock, world, fault("lr_desync", 1.0, 1.0))
    _grab_at(cam, clock, 1.0)
    p = cam.grab(1.0)
    assert p.skew_ns == -100_000_000
    assert p.right.seq == p.left.seq - 1


def test_occlusion_paints_the_region(clock: ManualClock, world: SimWorld) -> None:
    cam = _camera(clock, world, fault("occlusion", 1.0, 1.0, region_px=(10, 20, 110, 70), eye="left"))
    p = _grab_at(cam, clock, 1.5)
    assert np.all(p.left.image[20:70, 10:110] == 200)
    assert not np.all(p.right.image[20:70, 10:110] == 200)


def test_glare_adds_stereo_consistent_ring_blobs(clock: ManualClock, world: SimWorld) -> None:
    cam = _camera(clock, world, fault("glare", 1.0, 1.0, count=1, radius_px=8.0, disparity_px=100.0))
    clean = _grab_at(cam, clock, 0.95)
    glare = _grab_at(cam, clock, 1.5)
    diff_l = np.argwhere(np.abs(glare.left.image.astype(int) - clean.left.image.astype(int)) > 100)
    diff_r = np.argwhere(np.abs(glare.right.image.astype(int) - clean.right.image.astype(int)) > 100)
    assert len(diff_l) > 20
    assert len(diff_r) > 20
    assert diff_l[:, 0].mean() == pytest.approx(diff_r[:, 0].mean(), abs=1.0)
    assert diff_l[:, 1].mean() - diff_r[:, 1].mean() == pytest.approx(100.0, abs=1.0)
    assert glare.left.image.max() == 255


def test_fault_injected_is_logged_once(clock: ManualClock, world: SimWorld) -> None:
    cam = _camera(clock, world, fault("frozen_frame", 1.0, 1.0))
    with capture_logs() as logs:
        _grab_at(cam, clock, 1.1)
        _grab_at(cam, clock, 1.3)
    injected = [e for e in logs if e["event"] == "fault_injected"]
    assert len(injected) == 1
    assert {k: injected[0][k] for k in ("device", "kind", "start_s", "duration_s")} == {
        "device": "camera", "kind": "frozen_frame", "start_s": 1.0, "duration_s": 1.0}


# ------------------------------------------------------------------ tracker
@pytest.mark.parametrize(("kind", "error"), [("tracker_timeout", DeviceTimeoutError),
                                             ("corrupt_record", ProtocolError)])
def test_tracker_errors(clock: ManualClock, world: SimWorld, kind: str, error: type[Exception]) -> None:
    t = _tracker(clock, world, fault(kind, 1.0, 1.0))
    assert not t.latest()["reference"].missing
    clock.advance(1.5)
    with pytest.raises(error):
        t.latest()
    clock.advance(1.0)
    assert not t.latest()["reference"].missing


def test_tracker_bad_quality_flag(clock: ManualClock, world: SimWorld) -> None:
    t = _tracker(clock, world, fault("bad_quality", 1.0, 1.0, quality=4.0))
    clock.advance(1.5)
    s = t.latest()["reference"]
    assert (s.quality, s.flags, s.missing) == (4.0, ("bad_quality",), False)


def test_tracker_sensor_missing(clock: ManualClock, world: SimWorld) -> None:
    t = _tracker(clock, world, fault("sensor_missing", 1.0, 1.0, sensors=("reference",)))
    clock.advance(1.5)
    s = t.latest()["reference"]
    assert s.missing
    assert s.T_tracker_from_sensor is None
    assert "missing" in s.flags


# ------------------------------------------------------------------ robot
def _nudge(r: FaultyRobot, dz: float = -5.0) -> RigidTransform:
    T = r.state_now().T_robot_from_tcp
    return RigidTransform(T.R, T.t + np.array([0.0, 0.0, dz]))


def test_robot_disconnect(clock: ManualClock) -> None:
    r = _robot(clock, fault("robot_disconnect", 1.0, 1.0))
    target = _nudge(r)
    clock.advance(1.5)
    for call in (r.state_now, lambda: r.move_linear(target, 10.0, 100.0), r.stop):
        with pytest.raises(DisconnectedError):
            call()
    clock.advance(1.0)
    r.move_linear(target, 10.0, 100.0)


def test_robot_protective_stop_latches_until_recover(clock: ManualClock) -> None:
    r = _robot(clock, fault("protective_stop", 1.0, 0.5))
    target = _nudge(r)
    r.move_linear(target, 10.0, 100.0, blocking=False)
    clock.advance(1.2)
    s = r.state_now()
    assert (s.safety, s.mode) == (SafetyStatus.PROTECTIVE_STOP, RobotMode.STOPPED)
    p = s.T_robot_from_tcp.t.copy()
    clock.advance(1.0)
    np.testing.assert_allclose(r.state_now().T_robot_from_tcp.t, p)     # the arm was stopped
    with pytest.raises(SafetyStopError):
        r.move_linear(target, 10.0, 100.0)
    r.recover()
    assert r.state_now().safety is SafetyStatus.NORMAL
    r.move_linear(target, 10.0, 100.0)


def test_recover_inside_the_window_is_refused(clock: ManualClock) -> None:
    r = _robot(clock, fault("protective_stop", 1.0, 1.0))
    clock.advance(1.5)
    assert r.state_now().safety is SafetyStatus.PROTECTIVE_STOP
    with pytest.raises(SafetyStopError, match="cannot be cleared yet"):
        r.recover()


def test_robot_motion_rejected(clock: ManualClock) -> None:
    r = _robot(clock, fault("motion_rejected", 1.0, 1.0))
    target = _nudge(r, -0.2)
    clock.advance(1.5)
    with pytest.raises(DeviceFaultError, match="rejected"):
        r.move_linear(target, 10.0, 100.0)
    with pytest.raises(DeviceFaultError, match="rejected"):
        r.servo(target, 0.008)


def test_limits_are_still_checked_before_any_fault(clock: ManualClock) -> None:
    r = _robot(clock, fault("motion_rejected", 0.0, 10.0))
    with pytest.raises(LimitViolationError):
        r.move_linear(_nudge(r, 900.0), 10.0, 100.0)


def test_robot_motion_lag_delays_servo_targets(clock: ManualClock) -> None:
    r = _robot(clock, fault("motion_lag", 0.0, 10.0, lag_ms=100.0))
    T0 = r.state_now().T_robot_from_tcp
    for i in range(1, 40):
        r.servo(RigidTransform(T0.R, T0.t + np.array([0.1 * i, 0.0, 0.0])), 0.008)
        clock.advance(0.008)
        if i == 10:
            assert r.inner.state_now().T_robot_from_tcp.t[0] == pytest.approx(T0.t[0])
    inner_target = r.inner._last_servo_target
    assert inner_target is not None
    # the last command (i = 39) was sent at 304 ms; the newest at least 100 ms old is i = 26 (200 ms)
    assert inner_target.t[0] - T0.t[0] == pytest.approx(0.1 * 26, abs=1e-9)


def test_robot_motion_lag_ending_delivers_the_held_back_targets_in_order(clock: ManualClock) -> None:
    """Found by the one-hour soak: when the lag window ended, the held-back targets were dropped
    and the newest sent, a step of lag_ms of motion the arm's own step check refused (633.8 mm/s).
    Now they reach the arm in order, every step one period of the stream."""
    r = _robot(clock, fault("motion_lag", 0.0, 0.3, lag_ms=100.0))
    T0 = r.state_now().T_robot_from_tcp
    for i in range(1, 60):   # 0.4 mm per 8 ms = 50 mm/s (limit 100), across the window's end at 0.3 s
        r.servo(RigidTransform(T0.R, T0.t + np.array([0.4 * i, 0.0, 0.0])), 0.008)
        clock.advance(0.008)
    inner_target = r.inner._last_servo_target
    assert inner_target is not None
    assert inner_target.t[0] - T0.t[0] == pytest.approx(0.4 * 59, abs=1e-9)   # caught up, no refusal


def test_robot_motion_lag_delays_moves(clock: ManualClock) -> None:
    r = _robot(clock, fault("motion_lag", 0.0, 10.0, lag_ms=150.0))
    t = clock.now_ns()
    r.move_linear(_nudge(r), 10.0, 100.0, blocking=False)
    assert clock.now_ns() - t == 150_000_000


# ------------------------------------------------------------------ wiring
def test_wrap_device_picks_the_wrapper_and_checks_the_role(clock: ManualClock, world: SimWorld) -> None:
    inner = SimTracker("tracker", SimTrackerConfig(driver="sim"), clock, world)
    assert isinstance(wrap_device(inner, "tracker", [fault("bad_quality")], clock), FaultyTracker)
    with pytest.raises(TypeError, match="glare is a camera fault"):
        wrap_device(inner, "tracker", [fault("glare")], clock)


def test_build_devices_wraps_the_faulted_roles(registry: DriverRegistry, clock: ManualClock) -> None:
    setup = load_setup(CONFIGS / "sim_faults.toml", registry)
    devs = build_devices(setup, clock, registry)
    assert isinstance(devs.camera, FaultyStereoCamera)
    assert isinstance(devs.robot, FaultyRobot)
    assert isinstance(devs.tracker, FaultyTracker)
    devs.open_all()
    clock.advance(3.2)
    with pytest.raises(DeviceTimeoutError):
        devs.tracker.latest()
    devs.close_all()


def _iter_kinds() -> Iterator[FaultKind]:
    """The device kinds (the wrappers here play them; the patient kinds are the simulated
    world's, tested in test_patient_faults.py)."""
    yield from (k for k in FaultKind if FAULT_DEVICE[k] != "patient")


def test_every_fault_kind_is_tested_here() -> None:
    import inspect
    import sys

    from tests.devices import test_patient_faults

    source = inspect.getsource(sys.modules[__name__])
    missing = [k.value for k in _iter_kinds() if f'"{k.value}"' not in source]
    assert missing == []
    patient_source = inspect.getsource(test_patient_faults)
    patient = [k for k in FaultKind if FAULT_DEVICE[k] == "patient"]
    assert len(patient) == 4
    assert [k.name for k in patient if f"FaultKind.{k.name}" not in patient_source] == []


def test_wrappers_pass_simulator_attributes_through(clock: ManualClock, world: SimWorld) -> None:
    cam = _camera(clock, world, fault("glare"))
    assert cam.calibration is CAL
    assert cam.frames_rendered == 0  # type: ignore[attr-defined]
    with pytest.raises(AttributeError):
        _ = cam.no_such_attribute  # type: ignore[attr-defined]
