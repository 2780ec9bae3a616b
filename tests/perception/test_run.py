"""``hil run`` on a wall-clock simulated setup with the servo loop and perception each in their own
process: the procedure reaches DONE, the supervisor took its pairs from the perception process,
and nothing (process, shared memory) is left behind. Also: where the perception process cannot
run, ``on`` is a one-line config error and ``auto`` stays in the supervisor."""

from __future__ import annotations

import contextlib
import json
import os
import re
from pathlib import Path

import pytest

from hil.clock import ManualClock, MonotonicClock
from hil.config import build_devices, load_setup
from hil.config.setup import SetupConfig
from hil.controller.assembly import with_perception_process, with_servo_process
from hil.controller.plan_file import load_plan
from hil.errors import ConfigError
from hil.perception import camera as camera_module
from hil.perception.camera import PerceptionCamera
from hil.servo.shm import ShmRegion

ROOT = Path(__file__).resolve().parents[2]


#: watchdogs loosened for a shared, loaded test machine (as the emulator end-to-end tests do), and
#: the camera at half its rate (the grab timeout is four frame periods): the runs here test the
#: processes' plumbing, not data age
LOOSE_WATCHDOGS = {"camera_frame_max_age_ms": 1500.0, "tracker_max_age_ms": 1500.0,
                   "robot_state_max_age_ms": 1000.0}


def _setup(tmp_path: Path, perception: str, extra: str = "") -> tuple[Path, SetupConfig]:
    text = (ROOT / "configs" / "sim.toml").read_text()
    for key, value in LOOSE_WATCHDOGS.items():
        text, n = re.subn(rf"^{key} = .*$", f"{key} = {value}", text, count=1, flags=re.MULTILINE)
        assert n == 1, key
    text = text.replace("frame_rate_hz = 15.0", "frame_rate_hz = 7.5", 1)
    text = text.replace("real_time = false", "real_time = true", 1)
    text = text.replace('stereo = "calibration/sim_stereo.json"',
                        f'stereo = "{ROOT / "configs" / "calibration" / "sim_stereo.json"}"', 1)
    text += f'\n[perception]\nprocess = "{perception}"\n' + extra
    cfg = tmp_path / "rt.toml"
    cfg.write_text(text)
    return cfg, load_setup(cfg)


@pytest.mark.slow
def test_hil_run_reaches_done_with_perception_and_servo_in_their_own_processes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.cli.cmd_run import run_procedure

    cfg, setup = _setup(tmp_path, "on")
    assert setup.simulation.real_time
    created: list[str] = []   # the segments this run creates (others' tests may share /dev/shm)
    real_create = ShmRegion.create   # bound to ShmRegion before the patch

    def create(cls: type[ShmRegion], words: int) -> ShmRegion:
        region = real_create(words)
        created.append(str(region.name).lstrip("/"))
        return region

    monkeypatch.setattr(ShmRegion, "create", classmethod(create))
    s = run_procedure(cfg, setup, load_plan(ROOT / "configs" / "plans" / "sim_plan.json"), auto=True,
                      session_dir=tmp_path, max_duration_s=60.0)
    assert s.final_state == "done", s.faults
    assert s.locate_ms["p50"] is not None   # the perception process's figures
    events = [json.loads(line) for line in Path(s.session_log).read_text().splitlines()]
    assert (events[0]["event"], events[0]["perception_process"]) == ("session_started", True)
    assert events[0]["perception_in_supervisor_because"] is None
    stopped = [e for e in events if e["event"] == "frame_prefetch_stopped"]
    assert len(stopped) == 1
    assert stopped[0]["process"] is True
    assert stopped[0]["pairs"] > 10
    assert len(created) == 4   # the servo's three regions and the marker ring
    assert set(os.listdir("/dev/shm")) & set(created) == set()


def test_on_with_a_needle_check_is_a_config_error(tmp_path: Path) -> None:
    text = (ROOT / "configs" / "sim_needle.toml").read_text()
    text = text.replace("real_time = false", "real_time = true", 1)
    text = text.replace('stereo = "calibration/sim_stereo.json"',
                        f'stereo = "{ROOT / "configs" / "calibration" / "sim_stereo.json"}"', 1)
    text += '\n[perception]\nprocess = "on"\n'
    cfg = tmp_path / "needle.toml"
    cfg.write_text(text)
    setup = load_setup(cfg)
    assert setup.procedure.lock.needle_check is not None
    clock = MonotonicClock()
    devices = with_servo_process(setup, build_devices(setup, clock), clock)
    try:
        with pytest.raises(ConfigError, match=r'perception\.process: "on" cannot be used: the needle check'):
            with_perception_process(setup, devices, clock)
    finally:
        devices.close_all()   # the world's follower thread ends with the (never opened) robot


def test_auto_stays_in_the_supervisor_on_the_manual_clock_or_without_the_servo_process(
        tmp_path: Path) -> None:
    _, setup = _setup(tmp_path, "auto", '\n[servo]\nprocess = "off"\n')
    clock = MonotonicClock()
    devices = build_devices(setup, clock)
    assert with_perception_process(setup, devices, clock) is devices      # a world needs the servo process
    manual = ManualClock(10**9)
    devices = build_devices(setup, manual)
    assert with_perception_process(setup, devices, manual) is devices
    _, on = _setup(tmp_path, "on", '\n[servo]\nprocess = "off"\n')
    with pytest.raises(ConfigError, match=r'"on" cannot be used: it needs the wall clock'):
        with_perception_process(on, build_devices(on, manual), manual)
    with pytest.raises(ConfigError, match=r"a simulated world needs the servo loop in its own process"):
        with_perception_process(on, build_devices(on, clock), clock)


@pytest.mark.parametrize(("mode", "cpus", "in_process"), [("auto", 1, True), ("auto", 2, False),
                                                         ("auto", 3, False), ("on", 1, False)])
def test_auto_needs_two_usable_cpus_and_on_runs_anyway(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mode: str, cpus: int, in_process: bool) -> None:
    """``auto`` starts the perception process where it need not share the servo loop's CPU (two
    CPUs: the loop's, and one for the supervisor and perception); with one it stays in the
    supervisor, and says why; ``on`` starts it on any machine."""
    monkeypatch.setattr(camera_module, "usable_cpus", lambda: cpus)
    _, setup = _setup(tmp_path, mode)
    clock = MonotonicClock()
    devices = with_servo_process(setup, build_devices(setup, clock), clock)
    why = camera_module.in_supervisor_because(setup, devices, clock)
    wired = with_perception_process(setup, devices, clock)
    try:
        if in_process:
            assert wired is devices
            assert why == (f"{cpus} usable CPU, fewer than 2: perception would share the servo loop's "
                           'CPU ("on" starts it anyway)')
        else:
            assert isinstance(wired.camera, PerceptionCamera)
            assert why is None
    finally:
        wired.close_all()   # never opened: ends the world's follower thread


def test_usable_cpus_counts_this_process_affinity_not_the_machines_cpus() -> None:
    mask = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(0, {min(mask)})
        assert camera_module.usable_cpus() == 1
    finally:
        os.sched_setaffinity(0, mask)
    assert camera_module.usable_cpus() == len(mask)


def test_on_replaces_the_camera_and_opens_the_robot_first(tmp_path: Path) -> None:
    _, setup = _setup(tmp_path, "on")
    clock = MonotonicClock()
    devices = with_servo_process(setup, build_devices(setup, clock), clock)
    devices = with_perception_process(setup, devices, clock)
    try:
        assert isinstance(devices.camera, PerceptionCamera)
        assert [d.kind for d in devices][:2] == ["robot", "camera"]
        assert devices.camera.calibration is not None
    finally:
        devices.close_all()


def test_the_processs_world_sees_the_arm_the_servo_process_moves(tmp_path: Path) -> None:
    """The perception process's world follows the servo's state ring: after a move the flange
    markers it locates are where the supervisor's world (following the same arm) has them."""
    import numpy as np

    from hil.geometry.transform import RigidTransform

    _, setup = _setup(tmp_path, "on")
    clock = MonotonicClock()
    devices = with_servo_process(setup, build_devices(setup, clock), clock)
    devices = with_perception_process(setup, devices, clock)
    world = devices.world
    assert world is not None
    camera = devices.camera
    assert isinstance(camera, PerceptionCamera)
    devices.open_all()
    try:
        start = devices.robot.state_now().T_robot_from_tcp
        devices.robot.move_linear(RigidTransform(start.R, start.t + np.array([0.0, 30.0, 0.0])), 60.0, 300.0)
        moved = devices.robot.state_now().T_robot_from_tcp.t
        assert float(np.linalg.norm(moved - start.t)) > 25.0
        for _ in range(3):
            got = camera.perception_feed.take(5.0)
            assert got is not None
            assert got.located is not None
        flange, _ = world.flange_markers_optical(got.frame.left.t_ns)
        assert len(flange) > 0
        pts = got.located.points_mm
        nearest = np.linalg.norm(flange[:, None] - pts[None], axis=2).min(axis=1)
        assert nearest.max() < 0.5, nearest
    finally:
        devices.close_all()


def _children_of(pid: int) -> dict[int, str]:
    """Live children of ``pid``: pid -> command line."""
    out: dict[int, str] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid and stat.rsplit(")", 1)[1].split()[0] != "Z":
                out[int(d.name)] = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, ValueError, IndexError):
            continue
    return out


def _running(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


@pytest.mark.slow
def test_ctrl_c_ends_hil_run_and_its_processes(tmp_path: Path) -> None:
    """Ctrl-C (SIGINT to the process group) during a wall-clock ``hil run``: the children ignore it,
    the supervisor closes them on its way out, and nothing is left running."""
    import signal
    import subprocess
    import sys
    import time

    cfg, _ = _setup(tmp_path, "on")
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil", "run", str(cfg), "--plan", str(ROOT / "configs/plans/sim_plan.json"),
         "--auto", "--no-report", "--session-dir", str(tmp_path)],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    kids: dict[int, str] = {}
    try:
        deadline = time.monotonic() + 60.0
        while not any("hil.perception.child" in c for c in kids.values()):
            assert proc.poll() is None, "hil run ended before starting its processes"
            assert time.monotonic() < deadline, "the perception process did not start"
            time.sleep(0.05)
            kids = _children_of(proc.pid)
        assert any("hil.servo.child" in c for c in kids.values())
        os.killpg(proc.pid, signal.SIGINT)     # what a terminal's Ctrl-C does
        proc.wait(30.0)
        deadline = time.monotonic() + 20.0
        while any(_running(k) for k in kids):
            assert time.monotonic() < deadline, f"left running: {kids}"
            time.sleep(0.05)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        for k in kids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(k, signal.SIGKILL)
