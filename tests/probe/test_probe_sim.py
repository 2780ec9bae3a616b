"""``hil probe`` on simulated and recorded devices, and on invalid setups."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from drivers.camera.recording import StereoRecorder
from drivers.interfaces.camera import Frame, StereoFrame
from tests.probe.conftest import ProbeRun, write_setup

ROOT = Path(__file__).resolve().parents[2]
SIM = ROOT / "configs" / "sim.toml"


def test_the_sim_config_is_all_ok(run_probe: Callable[..., ProbeRun]) -> None:
    run = run_probe(SIM)
    assert run.code == 0
    report = run.report
    assert (report["status"], report["exit_code"]) == ("ok", 0)
    assert [d["role"] for d in report["devices"]] == ["robot", "tracker", "camera"]
    for dev in report["devices"]:
        assert dev["simulated"] is True
        assert dev["status"] == "ok", dev
        assert dev["checks"][0]["name"] == "simulated"
    assert list(run.checks("tracker")) == ["simulated", "driver_builds", "driver_opens", "streams",
                                           "sensor_reference", "sensor_needle"]
    camera = run.checks("camera")
    assert camera["resolution"]["data"]["left_px"] == [1920, 1080]
    assert camera["frame_rate"]["data"]["rate_hz"] == 15.0  # simulated time: exactly the configured rate
    assert camera["dropped_frames"]["data"]["dropped"] == 0


def test_human_checklist(run_probe: Callable[..., ProbeRun]) -> None:
    run = run_probe(SIM, human=True)
    assert run.code == 0
    lines = run.out.splitlines()
    assert lines[0] == f"hil probe {SIM} (each check times out after 2 s)"
    assert "robot: driver sim (simulated) -> OK" in lines
    assert "  OK    simulated robot: no hardware, checking that it starts" in lines
    assert lines[-1] == "summary: robot OK, tracker OK, camera OK -> exit 0"


def test_invalid_setup_exits_2_with_one_line_per_problem(
    tmp_path: Path, run_probe: Callable[..., ProbeRun],
) -> None:
    path = write_setup(tmp_path, '[tracker]\ndriver = "fob"\nport = "/dev/ttyUSB0"\nbaud_rate = 12345\n')
    run = run_probe(path, human=True)
    assert run.code == 2
    assert run.out == ""
    assert "tracker.sensors: required key missing" in run.err
    assert "Traceback" not in run.err
    as_json = run_probe(path)
    assert as_json.code == 2
    doc = json.loads(as_json.out)
    assert doc["status"] == "config_error"
    assert any("baud_rate" in p for p in doc["problems"])


def test_missing_setup_file_exits_2(tmp_path: Path, run_probe: Callable[..., ProbeRun]) -> None:
    run = run_probe(tmp_path / "nope.toml", human=True)
    assert run.code == 2
    assert "cannot read" in run.err


def _record(directory: Path, n: int, skip: int | None = None) -> None:
    period = 33_333_333
    img = np.full((48, 64), 128, np.uint8)
    with StereoRecorder(directory, frame_rate_hz=30.0, exposure_us=4000.0, codec="png") as rec:
        for k in range(n):
            seq = k + (1 if skip is not None and k >= skip else 0)
            t = 1_000_000_000 + seq * period
            rec.write(StereoFrame(Frame(img, t, seq), Frame(img, t + 1_000_000, seq)))


def test_replay_recording(tmp_path: Path, run_probe: Callable[..., ProbeRun]) -> None:
    _record(tmp_path / "rec", 40, skip=10)
    path = write_setup(tmp_path, '[camera]\ndriver = "replay"\nrecording_dir = "rec"\nspeed = 4.0\n\n'
                                 '[robot]\ndriver = "sim"\n', sim_sections=False)
    run = run_probe(path)
    camera = run.checks("camera")
    assert camera["recording_found"]["data"] == {"pairs_listed": 40}
    # the driver says what it opened (Device.describe), shown on the "opens" line
    assert camera["driver_opens"]["data"] == {"codec": "png", "image": "64x48", "rate": "30 Hz",
                                              "pairs": "40"}
    assert camera["driver_opens"]["message"].endswith("(codec png, image 64x48, rate 30 Hz, pairs 40)")
    assert camera["resolution"]["message"] == "resolution 64x48 px, as configured"
    assert camera["skew"]["data"] == {"median_ms": 0.25, "max_ms": 0.25}  # 1 ms recorded, replayed 4x faster
    assert camera["dropped_frames"]["status"] == "warn"
    assert camera["dropped_frames"]["data"]["dropped"] == 1
    assert run.code == 0


def test_replay_directory_missing(tmp_path: Path, run_probe: Callable[..., ProbeRun]) -> None:
    path = write_setup(tmp_path, '[camera]\ndriver = "replay"\nrecording_dir = "nowhere"\n\n'
                                 '[robot]\ndriver = "sim"\n', sim_sections=False)
    run = run_probe(path)
    assert run.code == 1
    check = run.checks("camera")["recording_found"]
    assert check["status"] == "fail"
    assert check["message"] == f"recording directory {tmp_path / 'nowhere'} does not exist"


def test_aravis_cameras_not_listed(tmp_path: Path, run_probe: Callable[..., ProbeRun]) -> None:
    from hil.campaign.gige import aravis_missing
    from plugins.manager import default_registry

    unavailable = {(u.kind, u.name): u.reason for u in default_registry().unavailable()}
    why = unavailable.get(("camera", "aravis")) or aravis_missing()
    if why is not None:   # CI installs PyGObject and Aravis (tools/_setup.sh)
        import pytest

        pytest.skip(f"the Aravis driver cannot load here: {why}")
    path = write_setup(tmp_path, '[camera]\ndriver = "aravis"\nleft_device_id = "Basler-21234567"\n'
                                 'right_device_id = "Basler-21234568"\n\n[robot]\ndriver = "sim"\n',
                       sim_sections=False)
    run = run_probe(path)
    assert run.code == 1
    check = run.checks("camera")["devices_found"]
    assert check["status"] == "fail"
    assert check["message"].startswith(
        "Aravis does not list the left 'Basler-21234567' and right 'Basler-21234568' camera(s)")
    assert list(run.checks("camera")) == ["devices_found"]
