"""The emulator as a program (``python -m emulators.trackersim``, what ``tools/trackersim`` runs),
its control interface, pose scripts and fault specs."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from emulators.trackersim.faults import parse_fault
from emulators.trackersim.poses import BreathingPoses, StaticPoses, load_pose_script

from drivers.interfaces.tracker import TrackerSample
from drivers.tracker_serial.aurora import AuroraTracker
from drivers.tracker_serial.config import AuroraConfig, FlockOfBirdsConfig
from drivers.tracker_serial.fob import FlockOfBirdsTracker
from hil.errors import InputFileError
from hil.geometry.transform import RigidTransform

from .conftest import TOOLS, wait_until


class Emulator:
    def __init__(self, args: list[str], tmp: Path) -> None:
        self.control = tmp / "ctl.sock"
        env = dict(os.environ, PYTHONPATH=f"{TOOLS}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
        self.proc = subprocess.Popen([sys.executable, "-m", "emulators.trackersim", *args,
                                      "--control", str(self.control)],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        assert self.proc.stdout is not None
        self.path = self.proc.stdout.readline().strip()  # the FIRST line is the device path

    def command(self, line: str) -> str:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.connect(str(self.control))
            s.sendall(line.encode() + b"\n")
            data = b""
            while not data.endswith(b"\n"):
                chunk = s.recv(4096)
                if not chunk:
                    break
                data += chunk
        return data.decode().strip()

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        self.proc.communicate(timeout=10)  # also closes the pipes
        return self.proc.returncode


@pytest.fixture
def emulator(tmp_path: Path) -> Iterator[type[Emulator]]:
    started: list[Emulator] = []

    class Started(Emulator):
        def __init__(self, args: list[str]) -> None:
            super().__init__(args, tmp_path)
            started.append(self)

    yield Started  # type: ignore[misc]
    for e in started:
        if e.proc.poll() is None:
            e.proc.kill()
        e.proc.communicate(timeout=10)


@pytest.mark.emulator
def test_fob_program_serves_the_driver_and_stops_on_sigterm(emulator: type[Emulator]) -> None:
    emu = emulator(["--protocol", "fob", "--birds", "2", "--motion", "static"])  # type: ignore[call-arg]
    assert emu.path.startswith("/dev/pts/")
    cfg = FlockOfBirdsConfig(driver="fob", port=emu.path, sensors={"a": 1, "b": 2}, reset_hold_s=0.0,
                             reset_settle_s=0.0)
    got: list[TrackerSample] = []
    with FlockOfBirdsTracker(cfg) as tracker:
        tracker.add_listener(got.append)
        wait_until(lambda: len(got) >= 10, what="records from the program")
        assert emu.command("fault garbage,count=3") == "ok"
        wait_until(lambda: json.loads(emu.command("status")[3:])["faults_fired"]["garbage"] == 3,
                   what="3 garbage faults")
        status = json.loads(emu.command("status")[3:])
        assert status["protocol"] == "fob"
        assert status["group_mode"] is True
    assert emu.command("bogus").startswith("error: unknown command")
    assert emu.command("fault nonsense").startswith("error: fault")
    assert emu.stop() == 0


@pytest.mark.emulator
def test_aurora_program_with_a_pose_script(emulator: type[Emulator], tmp_path: Path) -> None:
    script = tmp_path / "poses.csv"
    script.write_text("t_s,sensor,x_mm,y_mm,z_mm,qw,qx,qy,qz\n"
                      "0,0A,10,20,-200,1,0,0,0\n"
                      "100,0A,10,20,-200,1,0,0,0\n"
                      "0,0B,,,,,,,\n")
    emu = emulator(["--protocol", "aurora", "--poses", str(script), "--motion", "static"])  # type: ignore[call-arg]
    cfg = AuroraConfig(driver="aurora", port=emu.path, sensors={"needle": "0A", "ref": "0B"},
                       break_as_nul=True, reset_timeout_s=3.0)
    with AuroraTracker(cfg) as tracker:
        wait_until(lambda: len(tracker.latest()) == 2, what="both tools")
        latest = tracker.latest()
    assert latest["needle"].T_tracker_from_sensor is not None
    np.testing.assert_allclose(latest["needle"].T_tracker_from_sensor.t, [10, 20, -200], atol=1e-3)
    assert latest["ref"].missing
    assert emu.stop() == 0


@pytest.mark.emulator
def test_program_rejects_a_bad_pose_script(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"sensors": {"1": [{"t_s": 0, "position_mm": [1, 2]}]}}')
    env = dict(os.environ, PYTHONPATH=str(TOOLS))
    res = subprocess.run(
        [sys.executable, "-m", "emulators.trackersim", "--protocol", "fob", "--poses", str(bad)],
        capture_output=True, text=True, env=env, timeout=60)
    assert res.returncode == 2
    assert res.stdout == ""
    assert "bad.json" in res.stderr
    assert "position_mm" in res.stderr


def test_pose_scripts(tmp_path: Path) -> None:
    js = tmp_path / "p.json"
    js.write_text(json.dumps({"loop": True, "sensors": {"1": [
        {"t_s": 0.0, "position_mm": [0, 0, 0]},
        {"t_s": 1.0, "position_mm": [10, 0, 0], "quaternion_wxyz": [0, 0, 0, 1]},
        {"t_s": 2.0, "missing": True}]}}))
    src = load_pose_script(js)
    T = src.pose("1", 0.5)
    assert T is not None
    np.testing.assert_allclose(T.t, [5, 0, 0])
    assert T.rotation_angle_rad() == pytest.approx(np.pi / 2)
    assert src.pose("1", 2.5) is not None  # looped back into the first interval
    assert src.pose("9", 0.0) is None
    bad = tmp_path / "b.json"
    bad.write_text(json.dumps({"sensors": {"1": [{"t_s": 1.0, "position_mm": [0, 0, 0]},
                                                 {"t_s": 0.5, "position_mm": [0, 0, 0]}]}}))
    with pytest.raises(InputFileError, match="must increase"):
        load_pose_script(bad)


def test_breathing_moves_only_the_moving_sensors() -> None:
    base = StaticPoses({"1": RigidTransform.identity(), "2": RigidTransform.identity()})
    src = BreathingPoses(base, amplitude_mm=(0, 0, 8), period_s=4.0, still=frozenset({"2"}))
    a, b = src.pose("1", 2.0), src.pose("2", 2.0)
    assert a is not None
    assert b is not None
    np.testing.assert_allclose(a.t, [0, 0, 8])
    np.testing.assert_allclose(b.t, [0, 0, 0])


def test_fault_specs() -> None:
    f = parse_fault("garbage,p=0.25,bytes=3,mask=0x7f,after=1.5")
    assert (f.kind, f.p, f.n_bytes, f.mask, f.after_s) == ("garbage", 0.25, 3, 0x7F, 1.5)
    assert parse_fault("wrong_baud,baud=9600").baud == 9600
    for bad in ["", "nope", "garbage,p=2", "garbage,colour=red", "wrong_baud"]:
        with pytest.raises(ValueError, match="fault"):
            parse_fault(bad)


def test_world_pose_source_follows_the_simulated_patient() -> None:
    from emulators.trackersim.world_poses import WorldPoses

    setup = Path(__file__).resolve().parents[2] / "configs" / "sim.toml"
    src = WorldPoses(setup, ("1", "2"))
    ref = src.pose("1", 0.0)  # the patient reference sensor
    assert ref is not None
    assert np.all(np.isfinite(ref.t))
    assert src.pose("2", 0.0) is None  # the needle sensor is on the flange: no robot here
    assert src.pose("3", 0.0) is None
    with pytest.raises(InputFileError, match="no sensor 'nope'"):
        WorldPoses(setup, ("1",), {"1": "nope"})


@pytest.mark.emulator
def test_program_with_the_simulated_world_prints_the_path_first(emulator: type[Emulator]) -> None:
    setup = Path(__file__).resolve().parents[2] / "configs" / "sim.toml"
    emu = emulator(["--protocol", "fob", "--birds", "2", "--world", str(setup)])  # type: ignore[call-arg]
    assert emu.path.startswith("/dev/pts/")  # logs of loading the setup went to stderr
    cfg = FlockOfBirdsConfig(driver="fob", port=emu.path, sensors={"reference": 1}, reset_hold_s=0.0,
                             reset_settle_s=0.0)
    with FlockOfBirdsTracker(cfg) as tracker:
        wait_until(lambda: "reference" in tracker.latest(), what="the world's reference sensor")
    assert emu.stop() == 0
