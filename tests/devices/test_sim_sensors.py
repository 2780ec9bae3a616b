"""Camera and tracker interfaces exercised through the simulator (built from configs/sim.toml)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from drivers.interfaces import DeviceTimeoutError, LifecycleError
from drivers.sim.camera import SimCameraConfig, SimStereoCamera
from drivers.sim.tracker import SimSensorConfig, SimTracker, SimTrackerConfig
from drivers.sim.world import FLANGE_MARKER_ID_BASE, SimWorld
from hil.clock import ManualClock, MonotonicClock
from hil.config import Devices, FramesConfig, ScenarioWorld, SimulationConfig
from hil.config.body import BodyConfig
from hil.geometry.transform import RigidTransform
from hil.vision.camera_model import StereoCalibration

SMALL = StereoCalibration.synthetic(image_size=(320, 240), f_px=300.0)


def _camera(clock: ManualClock, **kw: object) -> SimStereoCamera:
    world = SimWorld(SimulationConfig(), FramesConfig(), clock)
    return SimStereoCamera("camera", SimCameraConfig(driver="sim", **kw), clock, world, SMALL)


def test_camera_lifecycle_and_sensor_has_no_motion_command(clock: ManualClock) -> None:
    cam = _camera(clock)
    with pytest.raises(LifecycleError, match="grab"):
        cam.grab(1.0)
    assert not any(hasattr(cam, m) for m in ("move_linear", "servo"))
    cam.open()
    cam.close()
    with pytest.raises(LifecycleError, match="grab"):
        cam.grab(1.0)


def test_frames_at_the_frame_rate_with_latency_and_skew(clock: ManualClock) -> None:
    cam = _camera(clock, frame_rate_hz=20.0, latency_ms=30.0, skew_ms=2.0)
    cam.open()
    t0 = clock.now_ns()
    pairs = [cam.grab(1.0) for _ in range(3)]
    assert [p.left.seq for p in pairs] == [0, 1, 2]
    assert [p.left.t_ns - t0 for p in pairs] == [0, 50_000_000, 100_000_000]
    assert all(p.skew_ns == 2_000_000 for p in pairs)
    assert clock.now_ns() - t0 == 100_000_000 + 30_000_000    # waited for the third to be ready
    assert pairs[0].left.image.shape == (240, 320)
    assert pairs[0].left.device_t_ns == 0
    assert cam.frames_rendered == 3


def test_late_grab_returns_the_newest_pair(clock: ManualClock) -> None:
    cam = _camera(clock, frame_rate_hz=10.0, latency_ms=0.0)
    cam.open()
    clock.advance(1.05)
    p = cam.grab(1.0)
    assert p.left.seq == 10
    assert cam.frames_rendered == 1     # skipped frames were never rendered


def _rendering_takes(clock: ManualClock, monkeypatch: pytest.MonkeyPatch,
                     durations_s: list[float]) -> list[int]:
    """Each render advances ``clock`` by the next of ``durations_s``: rendering taking clock time,
    as it does on the wall clock. Returns the list the renders' start times (ns) go to."""
    from hil.vision.render import render_stereo

    left = iter(durations_s)
    starts: list[int] = []

    def timed(*args: Any, **kwargs: Any) -> Any:
        starts.append(clock.now_ns())
        clock.advance(next(left))
        return render_stereo(*args, **kwargs)

    monkeypatch.setattr("drivers.sim.camera.render_stereo", timed)
    return starts


def test_a_render_starts_its_render_time_before_the_pair_is_due(
        clock: ManualClock, monkeypatch: pytest.MonkeyPatch) -> None:
    _rendering_takes(clock, monkeypatch, [0.040] * 4)
    cam = _camera(clock, frame_rate_hz=10.0, latency_ms=30.0)
    cam.open()
    t0 = clock.now_ns()
    first = cam.grab(1.0)      # no render time known yet: rendered when due, delivered 40 ms late
    assert (first.left.seq, clock.now_ns() - t0) == (0, 70_000_000)
    assert cam.render_lead_ns == 40_000_000
    second = cam.grab(1.0)     # due at 130 ms: rendered from 90 ms, delivered on time
    assert (second.left.seq, clock.now_ns() - t0) == (1, 130_000_000)


def test_on_the_wall_clock_the_renderers_set_up_is_paid_at_open_not_taken_for_the_lead(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The first render pays a one-off set-up (0.3 s here): on the wall clock it is rendered and
    discarded at open, so the lead the grabs start their renders by is a real render's time (a
    first render taken for the lead made the second grab deliver nothing for that long)."""
    from hil.vision.render import render_stereo

    calls: list[float] = []

    def first_slow(*args: Any, **kwargs: Any) -> Any:
        calls.append(time.monotonic())
        if len(calls) == 1:
            time.sleep(0.3)
        return render_stereo(*args, **kwargs)

    monkeypatch.setattr("drivers.sim.camera.render_stereo", first_slow)
    clock = MonotonicClock()
    world = SimWorld(SimulationConfig(), FramesConfig(), clock)
    cam = SimStereoCamera("camera", SimCameraConfig(driver="sim", frame_rate_hz=15.0), clock, world, SMALL)
    cam.open()
    try:
        assert len(calls) == 1                  # warmed up at open
        assert cam.render_lead_ns == 0          # and nothing learned from it
        cam.grab(1.0)
        assert len(calls) == 2
        assert 0 < cam.render_lead_ns < 300_000_000   # the grab's own render time, not the set-up
    finally:
        cam.close()


def test_on_a_manual_clock_open_renders_nothing(clock: ManualClock, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[int] = []
    monkeypatch.setattr("drivers.sim.camera.render_stereo", lambda *a, **k: calls.append(1))
    cam = _camera(clock)
    cam.open()
    cam.close()
    assert calls == []


def test_one_stalled_render_is_not_followed_by_a_silence(
        clock: ManualClock, monkeypatch: pytest.MonkeyPatch) -> None:
    """A render stretched by a stall of the whole process (0.7 s: ur_rtde's constructors hold the
    interpreter lock when the robot is recovered) is delivered late, and the next pair comes on
    time: the lead stays the usual render time, never the stall (which made the camera render the
    next pair 0.5 s ahead and deliver nothing until then)."""
    _rendering_takes(clock, monkeypatch, [0.040] * 5 + [0.700] + [0.040] * 3)
    cam = _camera(clock, frame_rate_hz=10.0, latency_ms=30.0)
    cam.open()
    t0 = clock.now_ns()
    for _ in range(5):
        cam.grab(1.0)
    assert cam.render_lead_ns == 40_000_000
    stalled = cam.grab(1.0)                                # due at 530 ms, done at 1,190 ms
    assert (stalled.left.seq, clock.now_ns() - t0) == (5, 1_190_000_000)
    assert cam.render_lead_ns == 40_000_000
    after = cam.grab(1.0)          # the newest pair due once rendered: seq 12, due at 1,230 ms
    assert (after.left.seq, clock.now_ns() - t0) == (12, 1_230_000_000)
    assert after.left.t_ns - t0 == 1_200_000_000


def test_the_lead_covers_the_recent_peak_render_up_to_the_latency(
        clock: ManualClock, monkeypatch: pytest.MonkeyPatch) -> None:
    """Renders that come in runs of different lengths: once a longer render has been seen, the
    next ones start early enough to cover it (a median lead left every render above it late);
    a stall raises the lead only to the latency less the guard, so the pair after it still comes
    on time, rendered after its exposure."""
    starts = _rendering_takes(clock, monkeypatch, [0.010] * 5 + [0.020, 0.018, 0.500, 0.010, 0.010])
    cam = _camera(clock, frame_rate_hz=10.0, latency_ms=30.0)
    cam.open()
    t0 = clock.now_ns()

    def grab() -> tuple[int, int]:
        pair = cam.grab(1.0)
        return pair.left.seq, (clock.now_ns() - t0) // 1_000_000

    assert [grab() for _ in range(5)] == [(0, 40), (1, 130), (2, 230), (3, 330), (4, 430)]
    assert cam.render_lead_ns == 10_000_000
    assert grab() == (5, 540)              # 20 ms from 520: 10 ms late
    assert cam.render_lead_ns == 20_000_000   # the peak (the median of the last five is 10 ms)
    assert grab() == (6, 630)              # 18 ms from 610: on time (a median lead: 638)
    assert grab() == (7, 1210)             # a 500 ms stall from 710
    assert cam.render_lead_ns == 28_000_000   # the latency less the 2 ms guard, not the stall
    assert grab() == (12, 1230)            # the newest pair due once rendered, on time
    assert grab() == (13, 1330)
    # pair 12 rendered at once after the stall; pair 13 from 2 ms after its exposure (1,300 ms)
    assert [(t - t0) // 1_000_000 for t in starts[-2:]] == [1210, 1302]


def test_grab_timeout(clock: ManualClock) -> None:
    cam = _camera(clock, frame_rate_hz=1.0, latency_ms=0.0)
    cam.open()
    cam.grab(0.1)
    t = clock.now_ns()
    with pytest.raises(DeviceTimeoutError, match=r"no stereo pair within 0\.2 s"):
        cam.grab(0.2)
    assert clock.now_ns() - t == 200_000_000


def test_full_rig_sees_skin_and_flange_markers(devices: Devices, clock: ManualClock) -> None:
    pair = devices.camera.grab(1.0)
    assert pair.left.image.shape == (1080, 1920)
    truth = devices.camera.last_truth  # type: ignore[attr-defined]
    ids = [m.marker_id for m in truth]
    assert ids == [*range(6), *range(FLANGE_MARKER_ID_BASE, FLANGE_MARKER_ID_BASE + 4)]
    assert all(m.visible_left and m.visible_right for m in truth)
    world = devices.world
    assert isinstance(world, SimWorld)
    assert isinstance(world, ScenarioWorld)
    skin, _ = world.patient_markers_optical(pair.left.t_ns)
    np.testing.assert_allclose([m.center_mm for m in truth[:6]], skin)
    # each marker is dark on the light background where the renderer says it is
    for m in truth:
        u, v = np.round(m.center_left_px).astype(int)
        ring = pair.left.image[v - 8:v + 9, u - 8:u + 9]
        assert ring.min() < 120 < pair.left.image[5:50, 5:50].mean()


def test_flange_markers_follow_the_robot(devices: Devices, clock: ManualClock) -> None:
    world = devices.world
    assert isinstance(world, SimWorld)
    before, _ = world.flange_markers_optical(clock.now_ns())
    T = devices.robot.state_now().T_robot_from_tcp
    devices.robot.move_linear(RigidTransform(T.R, T.t + np.array([0.0, 0.0, -30.0])), 50.0, 200.0)
    after, _ = world.flange_markers_optical(clock.now_ns())
    shift_optical = world.T_optical_from_robot.apply_vector(np.array([0.0, 0.0, -30.0]))
    np.testing.assert_allclose(after - before, np.repeat(shift_optical[None], 4, 0), atol=1e-6)


def test_tracker_samples(devices: Devices, clock: ManualClock) -> None:
    tracker = devices.tracker
    assert tracker is not None
    assert tracker.sensors == ("reference", "needle")
    a = tracker.latest()
    assert a["reference"].seq == 0
    assert not a["reference"].missing
    assert tracker.latest() == a                         # same sample until the next one exists
    clock.advance(0.025)
    b = tracker.latest()
    assert b["reference"].seq == 1
    assert b["reference"].t_ns - a["reference"].t_ns == 25_000_000
    world = devices.world
    assert isinstance(world, SimWorld)
    true = world.T_optical_from_tracker.inverse() @ world.T_optical_from_image(b["needle"].t_ns)
    assert b["reference"].T_tracker_from_sensor is not None
    assert b["needle"].quality == pytest.approx(np.sqrt(3) * 0.1)
    err = np.linalg.norm(b["reference"].T_tracker_from_sensor.t - true.apply(np.array([-40.0, 60.0, -2.0])))
    assert 0.0 < err < 0.6


def _tracker(clock: ManualClock, **kw: object) -> tuple[SimTracker, SimWorld]:
    world = SimWorld(SimulationConfig(), FramesConfig(), clock)
    cfg = SimTrackerConfig(driver="sim", position_noise_mm=0.0, rotation_noise_rad=0.0, **kw)
    t = SimTracker("tracker", cfg, clock, world)
    t.open()
    return t, world


def test_tracker_field_distortion_and_volume(clock: ManualClock) -> None:
    plain, _world = _tracker(clock)
    distorted, _ = _tracker(clock, distortion_mm_per_m2=10.0)
    p = plain.latest()["reference"]
    d = distorted.latest()["reference"]
    assert p.T_tracker_from_sensor is not None
    assert d.T_tracker_from_sensor is not None
    r_m = np.linalg.norm(p.T_tracker_from_sensor.t) / 1000.0
    shift_mm = np.linalg.norm(d.T_tracker_from_sensor.t - p.T_tracker_from_sensor.t)
    assert shift_mm == pytest.approx(10.0 * r_m**2)
    assert d.quality == pytest.approx(10.0 * r_m**2)
    small, _ = _tracker(clock, volume_radius_mm=50.0)
    s = small.latest()["reference"]
    assert s.missing
    assert s.T_tracker_from_sensor is None
    assert s.flags == ("out_of_volume",)


def test_tracker_flange_sensor_without_robot_is_missing(clock: ManualClock) -> None:
    t, _ = _tracker(clock, sensors=(SimSensorConfig(name="needle", attached_to="flange"),))
    s = t.latest()["needle"]
    assert s.missing
    assert s.flags == ("not_attached",)


def test_the_simulated_sensor_at_the_target_moves_with_the_true_target(clock: ManualClock) -> None:
    sim = SimulationConfig(body=BodyConfig(model="deformable"))
    world = SimWorld(sim, FramesConfig(), clock)
    offset = (4.0, -3.0, 2.0)
    cfg = SimTrackerConfig(driver="sim", position_noise_mm=0.0, rotation_noise_rad=0.0, sensors=(
        SimSensorConfig(name="target", attached_to="target",
                        T_attached_from_sensor={"translation_mm": offset, "rotvec_rad": (0.0, 0.0, 0.0)}),))
    tracker = SimTracker("tracker", cfg, clock, world)
    tracker.open()
    moved = []
    for _ in range(5):
        clock.advance(0.7)
        s = tracker.latest()["target"]
        assert s.T_tracker_from_sensor is not None
        p = world.T_optical_from_tracker.apply(s.T_tracker_from_sensor.t).reshape(3)
        R = world.T_optical_from_image(s.t_ns).R
        want = world.target_optical(s.t_ns) + R @ np.array(offset)
        np.testing.assert_allclose(p, want, atol=1e-9)
        moved.append(p)
    assert np.ptp(np.array(moved), axis=0).max() > 1.0        # it breathes with the target


def test_duplicate_sensor_names_are_refused() -> None:
    with pytest.raises(ValueError, match="unique"):
        SimTrackerConfig(driver="sim", sensors=(SimSensorConfig(name="a"), SimSensorConfig(name="a")))


def test_a_simulated_session_reproduces_bit_for_bit(sim_setup: object, registry: object) -> None:
    """Same setup, same commands, same clock steps: identical images, states and samples."""
    from hil.config import build_devices

    def session() -> list[object]:
        clock = ManualClock(start_ns=1_000_000_000)
        devs = build_devices(sim_setup, clock, registry)  # type: ignore[arg-type]
        devs.open_all()
        out: list[object] = []
        T0 = devs.robot.state_now().T_robot_from_tcp
        for i in range(4):
            pair = devs.camera.grab(1.0)
            devs.robot.servo(RigidTransform(T0.R, T0.t + np.array([0.3 * (i + 1), 0.0, 0.0])), 0.008)
            clock.advance(0.013)
            assert devs.tracker is not None
            smp = devs.tracker.latest()["reference"]
            assert smp.T_tracker_from_sensor is not None
            out += [pair.left.image.tobytes(), pair.right.image.tobytes(), pair.left.t_ns,
                    devs.robot.state_now().q_rad.tobytes(), smp.T_tracker_from_sensor.as_matrix().tobytes()]
        devs.close_all()
        return out

    assert session() == session()


def test_skewed_right_image_shows_the_world_at_its_own_exposure(clock: ManualClock) -> None:
    cam = _camera(clock, frame_rate_hz=10.0, latency_ms=0.0, skew_ms=20.0)
    cam.open()
    clock.advance(1.0)                                   # mid-breath: the phantom moves
    pair = cam.grab(1.0)
    left_truth = {m.marker_id: m.center_right_px for m in cam.last_truth}
    right_truth = {m.marker_id: m.center_right_px for m in cam.last_truth_right}
    moved = [float(np.linalg.norm(right_truth[i] - left_truth[i])) for i in range(6)]
    assert min(moved) > 0.01                             # the right camera saw the later world
    world_pts, _ = cam.world.patient_markers_optical(pair.right.t_ns)
    _, uv_right = SMALL.project(world_pts)
    np.testing.assert_allclose([right_truth[i] for i in range(6)], uv_right, atol=1e-6)
