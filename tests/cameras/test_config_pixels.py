"""Camera config models, factories, pixel conversion, the Aravis import guard, fakegv helpers."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from drivers.camera import pixels
from drivers.camera.config import AravisCameraConfig, ReplayCameraConfig, V4l2CameraConfig
from drivers.camera.pairing import PairRule
from drivers.camera.plugin import aravis_factory, replay_factory, v4l2_factory
from drivers.interfaces.lifecycle import DeviceState
from hil.clock import Clock, ManualClock

ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Ctx:
    role: str
    clock: Clock
    config_dir: Path


def aravis(**kw: Any) -> AravisCameraConfig:
    return AravisCameraConfig(driver="aravis", left_device_id="L", right_device_id="R", **kw)


# ---- config ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("kw", "rule"),
    [
        ({"trigger": "software"}, PairRule.TRIGGER_ID),
        ({"trigger": "hardware"}, PairRule.FRAME_ID),
        ({"trigger": "free_run"}, PairRule.HOST_TIME),
        ({"trigger": "free_run", "device_clocks_synchronised": True}, PairRule.DEVICE_TIME),
        ({"trigger": "software", "pairing": "host_time"}, PairRule.HOST_TIME),
    ],
)
def test_aravis_pair_rule_resolution(kw: dict[str, Any], rule: PairRule) -> None:
    from drivers.camera.aravis import resolve_pair_rule

    assert resolve_pair_rule(aravis(**kw)) is rule


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"right_device_id": "L"}, "name the same camera"),
        ({"trigger": "free_run", "pairing": "trigger_id"}, "needs trigger = 'software'"),
        ({"trigger": "free_run", "pairing": "frame_id"}, "needs a trigger"),
        ({"frame_rate_hz": 0}, "greater than 0"),
        ({"exposure_ms": 3}, "Extra inputs are not permitted"),
        ({"pixel_format": "YUV422"}, "Input should be"),
    ],
)
def test_aravis_config_rejects(kw: dict[str, Any], message: str) -> None:
    base = {"driver": "aravis", "left_device_id": "L", "right_device_id": "R"}
    base.update(kw)
    with pytest.raises(ValidationError, match=message):
        AravisCameraConfig(**base)


def test_configs_are_frozen() -> None:
    cfg = aravis()
    with pytest.raises(ValidationError):
        cfg.frame_rate_hz = 10.0  # type: ignore[misc]


def test_factories_build_configured_devices(tmp_path: Path) -> None:
    ctx = Ctx(role="camera", clock=ManualClock(), config_dir=tmp_path)
    cam = aravis_factory(aravis(frame_rate_hz=60.0, exposure_us=800.0, width_px=640, height_px=480), ctx)
    assert (cam.name, cam.state, cam.frame_rate_hz, cam.exposure_us, cam.image_size) == (
        "camera", DeviceState.CONFIGURED, 60.0, 800.0, (640, 480))
    v4l2 = v4l2_factory(V4l2CameraConfig(driver="v4l2", side_by_side_device="0", width_px=320,
                                         height_px=240), ctx)
    assert (v4l2.state, v4l2.image_size, v4l2.side_by_side) == (DeviceState.CONFIGURED, (320, 240), True)
    replay = replay_factory(ReplayCameraConfig(driver="replay", recording_dir=Path("rec")), ctx)
    assert replay.directory == tmp_path / "rec"
    assert replay.state is DeviceState.CONFIGURED


def test_the_builtin_plugin_registers_these_drivers() -> None:
    from plugins.manager import default_registry

    registry = default_registry()
    assert [u.name for u in registry.unavailable() if u.kind == "camera"] == []
    for name, model, factory in (("aravis", AravisCameraConfig, aravis_factory),
                                 ("v4l2", V4l2CameraConfig, v4l2_factory),
                                 ("replay", ReplayCameraConfig, replay_factory)):
        info = registry.get("camera", name)
        assert (info.config_model, info.factory) == (model, factory)


# ---- Aravis import guard ---------------------------------------------------------------------
def test_missing_pygobject_is_a_typed_error_saying_what_to_install() -> None:
    code = (
        "import sys; sys.modules['gi'] = None\n"
        "from drivers.camera.aravis import import_aravis, AravisUnavailableError\n"
        "try:\n    import_aravis('camera')\n"
        "except AravisUnavailableError as e:\n    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT).stdout
    assert out.startswith("camera: Aravis is not available")
    assert "PyGObject==3.50.2" in out
    assert "gir1.2-aravis-0.8" in out


# ---- pixel conversion ------------------------------------------------------------------------
def test_mono8_is_copied_unchanged() -> None:
    data = bytes(range(12))
    img = pixels.to_mono8(data, 4, 3, pixels.MONO_8)
    assert img.tolist() == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]]
    assert img.flags.writeable


def test_mono16_and_mono12_keep_the_top_8_bits() -> None:
    wide = np.array([[0, 256, 65535, 4096]], dtype="<u2")
    assert pixels.to_mono8(wide.tobytes(), 4, 1, pixels.MONO_16).tolist() == [[0, 1, 255, 16]]
    twelve = np.array([[0, 16, 4095, 4096]], dtype="<u2")
    assert pixels.to_mono8(twelve.tobytes(), 4, 1, pixels.MONO_12).tolist() == [[0, 1, 255, 255]]


def test_rgb8_uses_luma_weights() -> None:
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[..., 0] = 255  # pure red
    grey = pixels.to_mono8(rgb.tobytes(), 2, 2, pixels.RGB_8)
    assert grey.tolist() == [[76, 76], [76, 76]]
    bgr = pixels.to_mono8(rgb.tobytes(), 2, 2, pixels.BGR_8)  # same bytes read as blue
    assert bgr.tolist() == [[29, 29], [29, 29]]


def test_bayer_rg8_uniform_grey_stays_grey() -> None:
    mosaic = np.full((8, 8), 100, np.uint8)
    assert np.all(pixels.to_mono8(mosaic.tobytes(), 8, 8, pixels.BAYER_RG_8) == 100)


def test_bayer_pfnc_to_opencv_code_mapping() -> None:
    # A PFNC BayerRG8 mosaic of a pure red scene: R at (even row, even col).
    mosaic = np.zeros((8, 8), np.uint8)
    mosaic[0::2, 0::2] = 255
    grey = pixels.to_mono8(mosaic.tobytes(), 8, 8, pixels.BAYER_RG_8)
    assert int(grey[4, 4]) == 76  # red's luma (a wrong mapping reads it as blue: 29)


def test_bad_payloads() -> None:
    with pytest.raises(pixels.PixelFormatError, match="unsupported pixel format 0x12345678"):
        pixels.to_mono8(b"\0" * 4, 2, 2, 0x12345678)
    with pytest.raises(pixels.PixelFormatError, match="shorter than a 4x4 image"):
        pixels.to_mono8(b"\0" * 15, 4, 4, pixels.MONO_8)


# ---- fakegv helpers ---------------------------------------------------------------------------
def test_fit_image_crops_and_pads() -> None:
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from emulators.fakegv.server import fit_image
    finally:
        sys.path.remove(str(ROOT / "tools"))
    img = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert fit_image(img, 2, 2).tolist() == [[0, 1], [4, 5]]
    assert fit_image(img, 5, 4, fill=9).tolist() == [
        [0, 1, 2, 3, 9], [4, 5, 6, 7, 9], [8, 9, 10, 11, 9], [9, 9, 9, 9, 9]]


def run_fakegv(*args: str) -> subprocess.CompletedProcess[str]:
    env = {"PYTHONPATH": f"{ROOT / 'tools'}:{ROOT}", "PATH": "/usr/bin:/bin"}
    return subprocess.run([sys.executable, "-m", "emulators.fakegv", *args], capture_output=True,
                          text=True, env=env, timeout=30, check=False)


def test_fakegv_reports_bad_input_in_one_line(tmp_path: Path) -> None:
    proc = run_fakegv("--images", str(tmp_path / "nope"))
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"fakegv: {tmp_path / 'nope'}: not a directory"
    proc = run_fakegv("--images", str(tmp_path))
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"fakegv: {tmp_path}: no files match *.png"
    cv2.imwrite(str(tmp_path / "left_000.png"), np.zeros((4, 4), np.uint8))
    proc = run_fakegv("--images", str(tmp_path), "--right-address", "127.0.0.2")
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"fakegv: {tmp_path}: no files match right*.png"
    (tmp_path / "bad.png").write_text("not a png")
    proc = run_fakegv("--images", str(tmp_path))
    assert proc.stderr.strip() == f"fakegv: {tmp_path / 'bad.png'}: not a readable image"


def test_fakegv_refuses_an_address_that_is_not_local(tmp_path: Path) -> None:
    pytest.importorskip("gi", reason="PyGObject (aravis extra) not installed; tools/setup_aravis.sh")
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((4, 4), np.uint8))
    proc = run_fakegv("--images", str(tmp_path), "--address", "127.0.0.77")
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("fakegv: fake camera GV01 did not start on 127.0.0.77")
