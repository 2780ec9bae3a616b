"""``hil rig-calibrate`` through the REAL ur_rtde driver on the UR controller emulator (tools/ursim,
a subprocess) with the simulated camera seeing its flange: a short hand-eye run in real time, and an
abort midway that stops the arm and writes nothing."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.cli import main
from tests.ur_rtde.conftest import Ursim, start_ursim, wait_for

pytestmark = [pytest.mark.emulator, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "sim_ursim.toml"
SHORT = """
[rig_calibration]
poses = 8
min_poses = 8
settle_s = 0.3
still_frames = 3
still_tolerance_mm = 0.3
still_timeout_s = 20.0
"""


@pytest.fixture(scope="module")
def ursim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ursim]:
    sim = start_ursim("3.15", tmp_path_factory.mktemp("ursim"))
    yield sim
    sim.stop()


@pytest.fixture
def config(ursim: Ursim, tmp_path: Path) -> Path:
    ursim.control.reset()
    ursim.control.home()
    wait_for(lambda: not ursim.control.status()["outage"], what="emulator listening again")
    text = CONFIG.read_text().replace('host = "127.0.0.1"', f'host = "{ursim.host}"', 1)
    text = text.replace('stereo = "calibration/sim_stereo.json"',
                        f'stereo = "{ROOT / "configs" / "calibration" / "sim_stereo.json"}"', 1)
    # a loaded shared host can starve the watchdog kicker for a few 100 ms while a frame renders
    text = text.replace("state_max_age_s = 1.0", "state_max_age_s = 1.0\nrtde_watchdog_min_hz = 1.0", 1)
    for key, value in {"camera_frame_max_age_ms": 1500.0, "robot_state_max_age_ms": 1000.0}.items():
        text = re.sub(rf"^{key} = .*$", f"{key} = {value}", text, count=1, flags=re.MULTILINE)
    path = tmp_path / "ursim_rig.toml"
    path.write_text(text + SHORT)
    return path


def test_hand_eye_on_the_ur_emulator(config: Path, tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "rig.json"
    assert main(["rig-calibrate", str(config), "--auto", "--no-temporal", "--json", "--out", str(out)]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["poses"] == 8
    assert s["poses_used"] == 6
    assert s["validation_mm_rms"] < 0.5
    assert "truth_layout_error_mm_rms" not in s   # the world sees the driver's report: no truth
    assert json.loads(out.read_text())["hand_eye"]["poses_used"] == 6


def test_abort_midway_on_the_ur_emulator(config: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                         capsys: pytest.CaptureFixture[str], ursim: Ursim) -> None:
    import io

    monkeypatch.setattr("sys.stdin", io.StringIO("y\ny\na\n"))
    out = tmp_path / "rig.json"
    assert main(["rig-calibrate", str(config), "--no-temporal", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("operator aborted at pose 3 of 8: the arm was stopped, nothing was written")
    assert not out.exists()
