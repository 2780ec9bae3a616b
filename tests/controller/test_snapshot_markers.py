"""The snapshot carries the markers located in the latest pair per camera (image px) besides the
triangulated set (optical mm), frozen: observers never reach into the locator or the camera."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.interfaces.camera import StereoFrame
from drivers.interfaces.robot import MotionLimits
from drivers.sim.camera import SimStereoCamera
from hil.clock import ManualClock
from hil.config import build_devices, load_setup
from hil.controller.config import ProcedureConfig
from hil.controller.controller import Controller
from hil.controller.located import LocatedMarkers, LocatesPerCamera
from hil.controller.perception import StereoMarkerLocator
from hil.controller.snapshot import ControllerSnapshot
from hil.session import SessionLog

from .fakes import FakeRobot
from .test_fault_handling import PLAN, RIG, FakeCamera, Scripted

CONFIG = Path("configs/sim.toml")


def _left(seq: int) -> np.ndarray:
    return np.array([[10.0 * seq, 20.0], [30.0, 40.0 + seq]])


def _right(seq: int) -> np.ndarray:
    return np.array([[5.0 * seq, 7.0]])


def _points(seq: int) -> np.ndarray:
    return np.array([[1.0, 2.0, 300.0 + seq]])


class PerCamera:
    """A locator that says what each camera saw (a function of the frame counter)."""

    def __call__(self, frame: StereoFrame) -> np.ndarray:
        return _points(frame.left.seq)

    def locate_pair(self, frame: StereoFrame) -> LocatedMarkers:
        s = frame.left.seq
        return LocatedMarkers.of(frame, _points(s), _left(s), _right(s))


def _snapshots(tmp_path: Path, locate: Callable[[StereoFrame], Any], ticks: int) -> list[ControllerSnapshot]:
    clock = ManualClock(10**9)
    cam, robot = FakeCamera(clock), FakeRobot(clock)
    cam.open()
    robot.open()
    seen: list[ControllerSnapshot] = []
    with SessionLog(tmp_path / "s.jsonl", clock) as log:
        ctl = Controller(camera=cam, robot=robot, tracker=None, clock=clock, locate=locate, plan=PLAN,
                         rig=RIG, procedure=ProcedureConfig(), limits=MotionLimits(),
                         watchdog_ages_s={"camera": 0.25, "robot": 0.05}, session=log,
                         operator=Scripted([]), observers=(seen.append,))
        for _ in range(ticks):
            ctl.tick()
    return seen


def test_the_snapshot_shows_each_cameras_centres_of_the_latest_pair(tmp_path: Path) -> None:
    assert isinstance(PerCamera(), LocatesPerCamera)
    seen = _snapshots(tmp_path, PerCamera(), 3)
    assert [s.located.frame_seq for s in seen if s.located is not None] == [2, 3, 4]  # seq 1 primes
    for snap in seen:
        got = snap.located
        assert got is not None
        assert got.left_px is not None
        assert got.right_px is not None
        np.testing.assert_array_equal(got.left_px, _left(got.frame_seq))
        np.testing.assert_array_equal(got.right_px, _right(got.frame_seq))
        np.testing.assert_array_equal(got.points_mm, _points(got.frame_seq))
        assert got.counts == (2, 1, 1)


def test_the_located_sets_are_frozen(tmp_path: Path) -> None:
    snap = _snapshots(tmp_path, PerCamera(), 1)[-1]
    got = snap.located
    assert got is not None
    assert got.left_px is not None
    with pytest.raises(ValueError, match="read-only"):
        got.left_px[0, 0] = 0.0
    with pytest.raises(ValueError, match="read-only"):
        got.points_mm[0, 0] = 0.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        got.frame_seq = 0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        snap.located = None  # type: ignore[misc]


def test_a_locator_of_points_only_leaves_the_cameras_unknown(tmp_path: Path) -> None:
    got = _snapshots(tmp_path, lambda f: _points(f.left.seq), 1)[-1].located
    assert got is not None
    assert (got.left_px, got.right_px) == (None, None)
    np.testing.assert_array_equal(got.points_mm, _points(got.frame_seq))
    assert got.counts == (None, None, 1)


def test_nothing_is_shown_for_a_pair_the_locator_failed_on(tmp_path: Path) -> None:
    def fails_on_the_third(frame: StereoFrame) -> np.ndarray:
        if frame.left.seq == 3:
            raise ValueError("locator broke")
        return _points(frame.left.seq)

    seen = _snapshots(tmp_path, fails_on_the_third, 2)
    assert seen[0].located is not None
    assert seen[0].located.frame_seq == 2
    assert seen[1].located is None
    assert seen[1].state == "fault"


def test_the_vision_locator_reports_the_rendered_centres_per_camera() -> None:
    """On a simulated pair: each camera's located centres are the rendered markers' projected
    centres (within 0.5 px), one per visible marker."""
    clock = ManualClock(10**9)
    devices = build_devices(load_setup(CONFIG), clock)
    cam = devices.camera
    assert isinstance(cam, SimStereoCamera)
    devices.open_all()
    try:
        clock.advance(1.0)
        frame = cam.grab(1.0)
        got = StereoMarkerLocator(cam.calibration).locate_pair(frame)
        truth = cam.last_truth
    finally:
        devices.close_all()
    assert got.frame_seq == frame.left.seq
    for side, found in (("left", got.left_px), ("right", got.right_px)):
        assert found is not None
        want = np.array([getattr(t, f"center_{side}_px") for t in truth
                         if getattr(t, f"visible_{side}") and not getattr(t, f"occluded_{side}")])
        assert found.shape == want.shape
        nearest = np.min(np.linalg.norm(found[:, None, :] - want[None, :, :], axis=2), axis=1)
        assert float(nearest.max()) < 0.5
    assert got.points_mm.shape == (len(truth), 3)


def test_the_locator_maps_its_points_through_the_rig_correction() -> None:
    """With a rig calibration's optical correction every triangulated point goes through it (the
    per-camera centres stay what the images showed)."""
    from hil.geometry.projective import ProjectiveCorrection, warp_matrix

    clock = ManualClock(10**9)
    devices = build_devices(load_setup(CONFIG), clock)
    cam = devices.camera
    assert isinstance(cam, SimStereoCamera)
    corr = ProjectiveCorrection.undoing(warp_matrix((60.0, 120.0, 860.0), (0.004, 0.003, 0.006, 0.0, 0.001,
                                                                            0.0, 3e-6, 1e-6, -2e-6)))
    devices.open_all()
    try:
        clock.advance(1.0)
        frame = cam.grab(1.0)
        plain = StereoMarkerLocator(cam.calibration).locate_pair(frame)
        corrected = StereoMarkerLocator(cam.calibration, correction=corr).locate_pair(frame)
    finally:
        devices.close_all()
    assert plain.points_mm.shape[0] >= 6
    np.testing.assert_array_equal(corrected.points_mm, corr.apply(plain.points_mm))
    assert float(np.max(np.linalg.norm(corrected.points_mm - plain.points_mm, axis=1))) > 0.5
    assert corrected.left_px is not None
    assert plain.left_px is not None
    np.testing.assert_array_equal(corrected.left_px, plain.left_px)
