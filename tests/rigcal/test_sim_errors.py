"""The simulator's rig errors ([simulation.rig_errors]): off by default, as configured when on."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.interfaces import FrameTime
from drivers.sim.camera import SimStereoCamera
from drivers.sim.motion import IrregularityScript
from drivers.sim.robot import SimRobot
from drivers.sim.tracker import SimTracker
from drivers.sim.world import SimWorld
from hil.clock import ManualClock
from hil.config import SetupConfig, build_devices
from hil.config.simulation import BreathingConfig, RigErrorsConfig
from plugins.registry import DriverRegistry


def _world(setup: SetupConfig, registry: DriverRegistry) -> tuple[SimWorld, SimStereoCamera, SimRobot,
                                                                  SimTracker, ManualClock]:
    clock = ManualClock(start_ns=1_000_000_000)
    devs = build_devices(setup, clock, registry)
    assert isinstance(devs.world, SimWorld)
    assert isinstance(devs.camera, SimStereoCamera)
    assert isinstance(devs.robot, SimRobot)
    assert isinstance(devs.tracker, SimTracker)
    return devs.world, devs.camera, devs.robot, devs.tracker, clock


def test_every_knob_is_off_by_default_and_the_perfect_rig_is_what_the_controller_is_told(
        perfect: SetupConfig, registry: DriverRegistry) -> None:
    assert RigErrorsConfig() == perfect.simulation.rig_errors
    world, cam, robot, _, _ = _world(perfect, registry)
    truth = world.rig_truth()
    assert truth is not None
    np.testing.assert_array_equal(truth.flange_markers_mm, np.asarray(perfect.frames.flange_markers_mm))
    assert truth.time_offsets_ms == {"camera": 0.0, "robot": 0.0, "tracker": 0.0}
    assert cam.true_calibration is cam.calibration
    t = 5_000_000_000
    np.testing.assert_array_equal(robot.T_robot_from_flange_at(t).as_matrix(),
                                  robot.T_robot_from_tcp_at(t).as_matrix())


def test_reception_offset_needs_reception_stamps() -> None:
    with pytest.raises(ValueError, match="camera_timestamp"):
        RigErrorsConfig(camera_reception_offset_ms=10.0)


def test_realistic_rig_differs_as_configured(realistic: SetupConfig, registry: DriverRegistry) -> None:
    world, cam, robot, tracker, clock = _world(realistic, registry)
    e = realistic.simulation.rig_errors
    truth = world.rig_truth()
    assert truth is not None
    off = truth.flange_markers_mm - np.asarray(realistic.frames.flange_markers_mm)
    assert 0.05 < float(np.sqrt(np.mean(off**2))) < 3 * e.flange_marker_error_mm
    assert truth.time_offsets_ms == {"camera": 45.0, "robot": 8.0, "tracker": 20.0}
    assert not np.array_equal(cam.true_calibration.K_left, cam.calibration.K_left)
    cam.open()
    robot.open()
    tracker.open()
    try:
        pair = cam.grab(1.0)
        exposure = cam.exposure_time_ns(pair.left.seq)
        assert pair.left.time_source is FrameTime.RECEPTION
        assert abs((pair.left.t_ns - exposure) * 1e-6 - 45.0) <= 3.0 * e.camera_timestamp_jitter_ms
        st = robot.state_now()
        np.testing.assert_array_equal(st.q_rad, robot.q_at(st.t_ns - 8_000_000))
        true_tcp = robot.T_robot_from_flange_at(st.t_ns - 8_000_000)
        reported = st.T_robot_from_tcp
        assert 0.0 < float(np.linalg.norm(true_tcp.t - reported.t)) < 1.0  # the kinematic error
        clock.advance(0.5)
        sample = tracker.latest()["reference"]
        assert (sample.t_ns - tracker._t0_ns) % tracker._period_ns == 20_000_000 % tracker._period_ns
        assert sample.t_ns <= clock.now_ns()
    finally:
        cam.close()
        robot.close()
        tracker.close()


def test_coughs_and_wander_are_seeded_pure_functions_of_time() -> None:
    cfg = BreathingConfig(baseline_wander_mm=1.5, cough_rate_per_min=3.0, cough_amplitude_mm=6.0)
    a, b = IrregularityScript(cfg, seed=3), IrregularityScript(cfg, seed=3)
    times = np.linspace(0.0, 180.0, 3601)
    va = [a.offset_mm(t) for t in times]
    vb = [b.offset_mm(t) for t in times[::-1]][::-1]   # sampled in the other order
    assert va == vb
    assert max(va) > 4.0          # at least one cough in 3 min at 3/min
    assert IrregularityScript(BreathingConfig(), seed=3).offset_mm(12.0) == 0.0


@pytest.mark.parametrize("ppm", [0.0, 100.0, -250.0])
def test_a_camera_clock_rate_error_spaces_the_exposures_on_the_host_clock(
        perfect: SetupConfig, registry: DriverRegistry, ppm: float) -> None:
    """The camera exposes every nominal period on its own clock (``device_t_ns``): ``ppm`` fast,
    its pairs come that much more often on the host clock, and their phase against anything the
    host paces drifts by period * ppm per pair. 0 ppm: exactly the nominal period."""
    errors = perfect.simulation.rig_errors.model_copy(update={"camera_clock_rate_error_ppm": ppm})
    setup = perfect.model_copy(update={"simulation": perfect.simulation.model_copy(
        update={"rig_errors": errors})})
    _, cam, _, _, clock = _world(setup, registry)
    period_ns = round(1e9 / cam.frame_rate_hz)
    cam.open()
    try:
        t0 = cam.exposure_time_ns(0)
        assert t0 == clock.now_ns()
        for k in (1, 30, 3000, 10**6):
            want = t0 + (k * period_ns if ppm == 0.0 else round(k * (period_ns / (1.0 + ppm * 1e-6))))
            assert cam.exposure_time_ns(k) == want
        clock.advance(10.0)
        pair = cam.grab(1.0)
        k = pair.left.seq
        assert pair.left.t_ns == cam.exposure_time_ns(k)                # exposure stamps, host clock
        assert pair.left.device_t_ns == k * period_ns                    # the camera's own clock
        latency_ns = round(cam.cfg.latency_ms * 1e6)
        now = clock.now_ns()   # the newest pair delivered by now
        assert cam.exposure_time_ns(k) + latency_ns <= now < cam.exposure_time_ns(k + 1) + latency_ns
    finally:
        cam.close()


def test_the_camera_clock_rate_error_is_bounded() -> None:
    with pytest.raises(ValueError, match="camera_clock_rate_error_ppm"):
        RigErrorsConfig(camera_clock_rate_error_ppm=600.0)
