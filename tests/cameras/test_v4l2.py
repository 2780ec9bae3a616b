"""V4L2 stereo driver: the OpenCV code path on recorded files, and a scripted device layer.

No /dev/video* exists here (environment.md, V4L2), so the device behaviour (buffer timestamps,
queued stale frames, unplugging) is scripted through the injected capture opener, and the real
OpenCV path runs on FFV1 files with ``source = "file"``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from drivers.camera.config import V4l2CameraConfig
from drivers.camera.v4l2 import V4l2StereoCamera, parse_device
from drivers.interfaces.errors import DisconnectedError, DriverError, LifecycleError
from hil.clock import ManualClock

W, H = 64, 48


def write_video(path: Path, values: Sequence[int], size: tuple[int, int] = (W, H),
                split: int | None = None) -> None:
    writer = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter.fourcc(*"FFV1"), 30.0, size, False)
    assert writer.isOpened()
    for v in values:
        img = np.full((size[1], size[0]), v, dtype=np.uint8)
        if split is not None:
            img[:, size[0] // 2:] = v + split
        writer.write(img)
    writer.release()


def file_config(tmp_path: Path, **kw: Any) -> V4l2CameraConfig:
    base: dict[str, Any] = {"driver": "v4l2", "left_device": str(tmp_path / "left.mkv"),
                            "right_device": str(tmp_path / "right.mkv"), "source": "file",
                            "width_px": W, "height_px": H, "drain_grabs_max": 0}
    base.update(kw)
    return V4l2CameraConfig(**base)


@pytest.fixture
def stereo_files(tmp_path: Path) -> Path:
    write_video(tmp_path / "left.mkv", [10 * i for i in range(10)])
    write_video(tmp_path / "right.mkv", [10 * i + 5 for i in range(10)])
    return tmp_path


# ---- the OpenCV path on recorded files -----------------------------------------------------
def test_files_give_paired_frames_with_media_timestamps(stereo_files: Path) -> None:
    clock = ManualClock(start_ns=5_000_000_000)
    cam = V4l2StereoCamera("camera", file_config(stereo_files), clock)
    cam.open()
    pairs = [cam.grab(1.0) for _ in range(3)]
    cam.close()
    assert [(p.left.seq, p.right.seq) for p in pairs] == [(0, 0), (1, 1), (2, 2)]
    assert [int(p.left.image[0, 0]) for p in pairs] == [0, 10, 20]
    assert [int(p.right.image[0, 0]) for p in pairs] == [5, 15, 25]
    # FFmpeg reports media time in whole ms for Matroska: 0, 33, 67 ms.
    assert [p.left.device_t_ns for p in pairs] == [0, 33_000_000, 67_000_000]
    assert [p.left.t_ns for p in pairs] == [5_000_000_000, 5_033_000_000, 5_067_000_000]
    assert all(p.skew_ns == 0 for p in pairs)
    assert pairs[0].left.image.shape == (H, W)
    assert pairs[0].left.image.dtype == np.uint8


def test_drain_drops_queued_frames_so_the_pair_is_fresh(stereo_files: Path) -> None:
    # A file never makes grab() wait, so every drain drops exactly drain_grabs_max frames.
    cam = V4l2StereoCamera("camera", file_config(stereo_files, drain_grabs_max=2), ManualClock())
    cam.open()
    seqs = [cam.grab(1.0).left.seq for _ in range(3)]
    cam.close()
    assert seqs == [2, 5, 8]


def test_end_of_file_is_disconnected_error_naming_the_file(stereo_files: Path) -> None:
    cam = V4l2StereoCamera("camera", file_config(stereo_files), ManualClock())
    cam.open()
    for _ in range(10):
        cam.grab(1.0)
    with pytest.raises(DisconnectedError, match=r"left video file '.*left\.mkv' ended after 10 frames"):
        cam.grab(1.0)
    cam.close()


def test_side_by_side_file_is_split_in_half(tmp_path: Path) -> None:
    write_video(tmp_path / "sbs.mkv", [20, 40], size=(2 * W, H), split=100)
    cfg = V4l2CameraConfig(driver="v4l2", side_by_side_device=str(tmp_path / "sbs.mkv"), source="file",
                           width_px=W, height_px=H, drain_grabs_max=0)
    cam = V4l2StereoCamera("camera", cfg, ManualClock())
    cam.open()
    pairs = [cam.grab(1.0) for _ in range(2)]
    cam.close()
    assert [(int(p.left.image.mean()), int(p.right.image.mean())) for p in pairs] == [(20, 120), (40, 140)]
    assert all(p.left.image.shape == (H, W) for p in pairs)
    assert all(p.left.t_ns == p.right.t_ns and p.left.seq == p.right.seq for p in pairs)


def test_file_size_mismatch_is_a_driver_error(stereo_files: Path) -> None:
    cam = V4l2StereoCamera("camera", file_config(stereo_files, width_px=W * 2), ManualClock())
    with pytest.raises(DriverError, match=f"delivers {W}x{H}, config asks {2 * W}x{H}"):
        cam.open()


def test_missing_file_is_disconnected_error(tmp_path: Path) -> None:
    cam = V4l2StereoCamera("camera", file_config(tmp_path), ManualClock())
    with pytest.raises(DisconnectedError, match=r"left video file '.*left\.mkv' does not exist"):
        cam.open()


# ---- device error paths with the real OpenCV V4L2 backend ----------------------------------
def test_missing_device_node_is_disconnected_error_naming_it() -> None:
    cfg = V4l2CameraConfig(driver="v4l2", left_device="/dev/video97", right_device="/dev/video98")
    cam = V4l2StereoCamera("camera", cfg, ManualClock())
    with pytest.raises(DisconnectedError, match="camera: left V4L2 device '/dev/video97' does not exist"):
        cam.open()


def test_device_index_that_does_not_open_is_disconnected_error() -> None:
    cfg = V4l2CameraConfig(driver="v4l2", side_by_side_device="63")
    cam = V4l2StereoCamera("camera", cfg, ManualClock())
    with pytest.raises(DisconnectedError, match="side_by_side V4L2 device '63' could not be opened"):
        cam.open()


def test_grab_before_open_is_lifecycle_error(stereo_files: Path) -> None:
    cam = V4l2StereoCamera("camera", file_config(stereo_files), ManualClock())
    with pytest.raises(LifecycleError):
        cam.grab(1.0)


# ---- scripted device layer: kernel timestamps, stale buffers, unplugging -------------------
class FakeMonotonic:
    def __init__(self, start_ns: int) -> None:
        self.now = start_ns

    def __call__(self) -> int:
        return self.now


class ScriptedCapture:
    """A V4L2 capture: queued frames (returned at once) then live frames (each waits 33 ms)."""

    def __init__(self, timestamps_ms: Sequence[float], mono: FakeMonotonic, queued: int = 0,
                 fail_after: int | None = None, value: int = 0, size: tuple[int, int] = (W, H)) -> None:
        self.timestamps_ms = list(timestamps_ms)
        self.mono = mono
        self.queued = queued
        self.fail_after = fail_after
        self.value = value
        self.size = size
        self.index = -1
        self.props: dict[int, float] = {}
        self.released = False

    def isOpened(self) -> bool:
        return True

    def grab(self) -> bool:
        if self.fail_after is not None and self.index + 1 >= self.fail_after:
            return False
        self.index += 1
        if self.index >= self.queued:
            self.mono.now += 33_000_000
        return True

    def retrieve(self) -> tuple[bool, Any]:
        img = np.full((self.size[1], self.size[0], 3), self.value + self.index, dtype=np.uint8)
        return True, img

    def get(self, prop_id: int) -> float:
        if prop_id == cv2.CAP_PROP_POS_MSEC:
            return self.timestamps_ms[self.index]
        if prop_id == cv2.CAP_PROP_FRAME_WIDTH:
            return float(self.size[0])
        if prop_id == cv2.CAP_PROP_FRAME_HEIGHT:
            return float(self.size[1])
        return 0.0

    def set(self, prop_id: int, value: float) -> bool:
        self.props[prop_id] = value
        return True

    def release(self) -> None:
        self.released = True


def device_config(**kw: Any) -> V4l2CameraConfig:
    base: dict[str, Any] = {"driver": "v4l2", "left_device": "0", "right_device": "1",
                            "width_px": W, "height_px": H, "frame_rate_hz": 30.0}
    base.update(kw)
    return V4l2CameraConfig(**base)


def make(cfg: V4l2CameraConfig, caps: dict[int | str, ScriptedCapture], mono: FakeMonotonic,
         clock: ManualClock) -> V4l2StereoCamera:
    def opener(source: str | int, api: int) -> ScriptedCapture:
        assert api == cv2.CAP_V4L2
        return caps[source]

    return V4l2StereoCamera("camera", cfg, clock, opener=opener, monotonic_ns=mono)


def test_device_settings_ask_for_one_buffer_and_the_configured_mode() -> None:
    mono = FakeMonotonic(0)
    caps: dict[int | str, ScriptedCapture] = {0: ScriptedCapture([0.0], mono),
                                              1: ScriptedCapture([0.0], mono)}
    cam = make(device_config(fourcc="MJPG", exposure_us=2000.0), caps, mono, ManualClock())
    cam.open()
    props = caps[0].props
    assert props[cv2.CAP_PROP_BUFFERSIZE] == 1
    assert props[cv2.CAP_PROP_FRAME_WIDTH] == W
    assert props[cv2.CAP_PROP_FRAME_HEIGHT] == H
    assert props[cv2.CAP_PROP_FPS] == 30.0
    assert props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter.fourcc(*"MJPG")
    assert props[cv2.CAP_PROP_EXPOSURE] == 20.0  # V4L2 exposure_time_absolute unit: 100 us
    cam.close()
    assert caps[0].released
    assert caps[1].released


def test_stale_queued_frames_are_drained_and_sides_paired_by_kernel_timestamps() -> None:
    mono = FakeMonotonic(1_000_000_000)
    # Left: 3 queued (stale) buffers then live ones; right: 1 queued. 30 Hz timestamps, ms.
    left_ts = [100.0 + 33.0 * k for k in range(10)]
    right_ts = [140.0 + 33.0 * k for k in range(10)]
    caps: dict[int | str, ScriptedCapture] = {
        0: ScriptedCapture(left_ts, mono, queued=3, value=0),
        1: ScriptedCapture(right_ts, mono, queued=1, value=100),
    }
    clock = ManualClock(start_ns=7_000_000_000)
    cam = make(device_config(drain_grabs_max=8), caps, mono, clock)
    cam.open()
    pair = cam.grab(5.0)
    # Left drains 0, 1, 2 (queued: instant) and 3 (waited: fresh, kept, ts 199 ms); right drains
    # 0 and 1 (waited, ts 173 ms). 199 vs 173 ms is more than half a period apart, so the older
    # (right) side is grabbed again: right 2 at 206 ms.
    assert (pair.left.seq, pair.right.seq) == (3, 2)
    assert pair.left.device_t_ns == 199_000_000
    assert pair.right.device_t_ns == 206_000_000
    assert pair.skew_ns == 7_000_000
    # t_ns = clock now - (CLOCK_MONOTONIC now - kernel timestamp).
    age_ns = mono.now - 199_000_000
    assert pair.left.t_ns == 7_000_000_000 - age_ns
    assert int(pair.left.image[0, 0]) == 3
    assert int(pair.right.image[0, 0]) == 102
    cam.close()


def test_unplugged_device_is_disconnected_error_naming_it() -> None:
    mono = FakeMonotonic(0)
    ts = [33.0 * k for k in range(10)]
    caps: dict[int | str, ScriptedCapture] = {0: ScriptedCapture(ts, mono),
                                              1: ScriptedCapture(ts, mono, fail_after=2)}
    cam = make(device_config(drain_grabs_max=0), caps, mono, ManualClock())
    cam.open()
    cam.grab(5.0)
    cam.grab(5.0)
    with pytest.raises(DisconnectedError, match="right V4L2 device '1' stopped delivering frames"):
        cam.grab(5.0)
    cam.close()


# ---- config ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"left_device": "0"}, "left_device and right_device go together"),
        ({"left_device": "0", "right_device": "0"}, "name the same device"),
        ({}, "give left_device"),
        ({"left_device": "0", "right_device": "1", "side_by_side_device": "2"}, "not both"),
        ({"side_by_side_device": "0", "buffer_size": 1}, "Extra inputs are not permitted"),
    ],
)
def test_config_rejects(kw: dict[str, Any], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        V4l2CameraConfig(driver="v4l2", **kw)


def test_parse_device() -> None:
    assert parse_device("3") == 3
    assert parse_device("/dev/video3") == "/dev/video3"
