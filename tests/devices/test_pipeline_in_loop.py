"""The real vision pipeline runs on the simulated camera and finds the simulated world."""

from __future__ import annotations

import json

import numpy as np

from drivers.faults import FaultyStereoCamera
from drivers.sim.camera import SimStereoCamera
from drivers.sim.world import SimWorld
from hil.clock import ManualClock
from hil.config import Devices, FaultKind, FaultSpec, SetupConfig
from hil.vision.pipeline import locate_markers
from tests.devices.conftest import CONFIGS


def test_phantom_and_flange_are_located_and_registered(devices: Devices, sim_setup: SetupConfig,
                                                       clock: ManualClock) -> None:
    cam = devices.camera
    world = devices.world
    assert isinstance(cam, SimStereoCamera)
    assert isinstance(world, SimWorld)
    plan = json.loads((CONFIGS / "plans" / "sim_plan.json").read_text())
    clock.advance(1.3)                                   # mid-inhale: the phantom has moved
    pair = cam.grab(1.0)
    res = locate_markers(cam.calibration, pair.left.image, pair.right.image, model_mm=plan["fiducials_mm"])
    assert len(res.points_mm) == 10                      # 6 skin + 4 flange markers
    m = res.match
    assert m is not None
    assert sorted(m.model_to_measured) == list(range(6))
    assert len(m.spurious_measured) == 4
    truth = world.T_optical_from_image(pair.left.t_ns)
    assert np.linalg.norm(m.T_measured_from_model.t - truth.t) < 0.2
    assert (m.T_measured_from_model.inverse() @ truth).rotation_angle_rad() < 0.005
    flange = locate_markers(cam.calibration, pair.left.image, pair.right.image,
                            model_mm=sim_setup.frames.flange_markers_mm)
    assert flange.match is not None
    T_flange = world.T_optical_from_flange(pair.left.t_ns)
    assert T_flange is not None
    assert np.linalg.norm(flange.match.T_measured_from_model.t - T_flange.t) < 0.3


def test_glare_blobs_become_extra_points(devices: Devices, clock: ManualClock) -> None:
    inner = devices.camera
    assert isinstance(inner, SimStereoCamera)
    glare = FaultSpec(kind=FaultKind.GLARE, start_s=0.0, duration_s=5.0, count=2)
    faulty = FaultyStereoCamera(inner, [glare], clock)
    faulty.schedule.start()
    faulty._state = inner.state                          # the inner camera is already open
    pair = faulty.grab(1.0)
    res = locate_markers(inner.calibration, pair.left.image, pair.right.image)
    assert len(res.detections_left) == 12               # both blobs look like rings
    assert len(res.points_mm) >= 11                     # and triangulate as extra markers
