"""The perception process with the simulated camera on the wall clock: marker sets whose points are
the world's truth, timestamps and counters as a direct grab gives them, the camera's errors and
the child's death raised as typed errors in the supervisor, and the child and its shared memory
gone on every way out (close, killed, the supervisor killed)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.interfaces.camera import FrameTime
from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError
from hil.clock import MonotonicClock
from hil.config import build_devices, default_setup_path, load_setup
from hil.config.setup import SetupConfig
from hil.perception.process import PerceptionProcess, PerceptionSpec

ROOT = Path(__file__).resolve().parents[2]


def _wait(cond: Callable[[], bool], what: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


def _take_until_raises(proc: PerceptionProcess, timeout_s: float) -> None:
    """Take records (what was published before) until ``take`` raises; at most 200."""
    for _ in range(200):
        proc.take(timeout_s)


def _shm() -> set[str]:
    return set(os.listdir("/dev/shm"))


@pytest.fixture
def world_and_process() -> Iterator[tuple[Any, PerceptionProcess]]:
    setup = load_setup(default_setup_path())
    world = build_devices(setup, MonotonicClock()).world
    assert world is not None
    proc = PerceptionProcess(lambda: PerceptionSpec(setup, world_t0_ns=world.t0_ns), "camera")
    proc.start()
    try:
        yield world, proc
    finally:
        proc.close()


def test_marker_sets_are_the_worlds_markers_with_the_pairs_times(
        world_and_process: tuple[Any, PerceptionProcess]) -> None:
    world, proc = world_and_process
    assert proc.ready_info is not None
    assert proc.ready_info.camera_name == "camera"
    last_seq = -1
    for _ in range(4):
        got = proc.take(5.0)
        assert got is not None
        assert got.error is None
        assert got.located is not None
        frame = got.frame
        assert frame.left.seq > last_seq
        assert frame.right.seq == frame.left.seq
        last_seq = frame.left.seq
        assert frame.left.time_source is FrameTime.EXPOSURE
        assert frame.left.image.shape == (0, 0)            # images never cross
        assert got.located.exposure_t_ns == frame.left.t_ns
        assert got.located.frame_seq == frame.left.seq
        truth, _ = world.patient_markers_optical(frame.left.t_ns)
        pts = got.located.points_mm
        nearest = np.linalg.norm(truth[:, None, :] - pts[None, :, :], axis=2).min(axis=1)
        assert nearest.max() < 0.5, nearest                 # every skin marker, where the world has it
        left_n, right_n, _ = got.located.counts
        assert left_n is not None
        assert left_n >= len(truth)
        assert right_n is not None
        assert right_n >= len(truth)
    assert len(proc.locate_ms) == 4
    assert min(proc.locate_ms) > 0
    assert proc.produced >= 4
    # the simulated camera never hands a pair over before its latency (30 ms, configs/sim.toml)
    assert len(proc.delivery_ms) == 4
    assert min(proc.delivery_ms) >= 30.0
    figs = proc.delivery_figures()
    assert figs["p50"] is not None
    assert figs["p99"] is not None
    assert 30.0 <= figs["p50"] <= figs["p99"]


def test_close_ends_the_child_and_removes_the_shared_memory() -> None:
    proc = PerceptionProcess(lambda: PerceptionSpec(load_setup(default_setup_path())), "camera")
    proc.start()
    name = str(proc.region.name).lstrip("/")
    assert name in _shm()
    proc.close()
    assert proc.exitcode == 0
    assert name not in _shm()
    proc.close()   # idempotent
    with pytest.raises(DisconnectedError, match="camera: perception process closed"):
        proc.take(0.1)


def test_a_killed_child_is_a_disconnected_camera(world_and_process: tuple[Any, PerceptionProcess]) -> None:
    _, proc = world_and_process
    proc.take(5.0)
    assert proc.pid is not None
    os.kill(proc.pid, signal.SIGKILL)
    _wait(lambda: proc.gone() is not None, "the parent to see the child gone")
    with pytest.raises(DisconnectedError, match=r"camera: perception process exited \(code -9\)"):
        _take_until_raises(proc, 1.0)


def _dropping_setup(tmp_path: Path) -> SetupConfig:
    """configs/sim.toml with every pair lost from 0.5 s after the camera opens."""
    text = (ROOT / "configs" / "sim.toml").read_text()
    text = text.replace('stereo = "calibration/sim_stereo.json"',
                        f'stereo = "{ROOT / "configs" / "calibration" / "sim_stereo.json"}"', 1)
    text += '\n[[faults]]\nkind = "frame_drop"\nstart_s = 0.5\nduration_s = 1000.0\n'
    cfg = tmp_path / "drop.toml"
    cfg.write_text(text)
    return load_setup(cfg)


def test_a_camera_that_fails_raises_its_own_error_in_the_supervisor(tmp_path: Path) -> None:
    proc = PerceptionProcess(lambda: PerceptionSpec(_dropping_setup(tmp_path)), "camera")
    proc.start()
    try:
        with pytest.raises(DeviceTimeoutError) as info:
            _take_until_raises(proc, 5.0)
        assert info.value.device == "camera"
        assert "no stereo pair within" in info.value.message
        assert proc.gone() is None   # the stream failed, the process still runs
    finally:
        proc.close()
    assert proc.exitcode == 0


_PARENT = textwrap.dedent("""
    import sys
    from hil.config import default_setup_path, load_setup
    from hil.perception.process import PerceptionProcess, PerceptionSpec
    p = PerceptionProcess(lambda: PerceptionSpec(load_setup(default_setup_path())), "camera")
    ready = p.start()
    print("PID", ready.pid, p.region.name, flush=True)
    sys.stdin.read()   # until the test kills this process
""")


def test_the_perception_process_exits_when_its_supervisor_is_killed() -> None:
    parent = subprocess.Popen([sys.executable, "-c", _PARENT], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              stderr=subprocess.DEVNULL, cwd=ROOT, text=True)
    child_pid = 0
    try:
        assert parent.stdout is not None
        line = ""
        while not line.startswith("PID "):
            line = parent.stdout.readline()
            assert line, "the parent ended before starting the perception process"
        _, pid, name = line.split()
        child_pid = int(pid)
        parent.kill()
        parent.wait()

        def gone() -> bool:
            try:
                os.kill(child_pid, 0)
            except ProcessLookupError:
                return True
            try:
                return Path(f"/proc/{child_pid}/stat").read_text().split()[2] == "Z"
            except OSError:
                return True
        _wait(gone, "the orphaned perception process to exit")
        # the killed supervisor's resource tracker unlinks the ring
        _wait(lambda: name.lstrip("/") not in _shm(), "the ring's segment to be removed")
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if parent.stdin is not None:
            parent.stdin.close()
        if parent.stdout is not None:
            parent.stdout.close()
        if child_pid:
            with contextlib.suppress(ProcessLookupError):
                os.kill(child_pid, signal.SIGKILL)


def test_a_breath_hold_reaches_the_perception_processs_world() -> None:
    """The supervisor's world is the coach: a hold it is asked for is relayed, and the markers the
    process locates are the held patient's (without the relay they would be up to ~5 mm off)."""
    setup = load_setup(default_setup_path())
    world = build_devices(setup, MonotonicClock()).world
    breathing = build_devices(setup, MonotonicClock()).world   # the same patient, never held
    assert world is not None
    assert breathing is not None
    breathing.t0_ns = world.t0_ns
    proc = PerceptionProcess(lambda: PerceptionSpec(setup, world_t0_ns=world.t0_ns), "camera")
    world.breath_hold_listeners.append(proc.relay_breath_hold)
    proc.start()
    try:
        world.request_breath_hold(20.0, 0.0, delay_s=0.2)
        start_ns = world.t0_ns + round((world.now_s() + 0.3) * 1e9)
        # a whole breathing cycle after the hold began, wherever in the cycle that was (the
        # process's start-up takes a machine-dependent part of one): the free patient breathes
        end_ns = start_ns + round(1.25 * setup.simulation.breathing.period_s * 1e9)
        held_errors, unheld_gaps = [], []
        t = 0
        while t < end_ns:
            got = proc.take(5.0)
            assert got is not None
            assert got.located is not None
            t = got.frame.left.t_ns
            if t < start_ns:
                continue
            truth, _ = world.patient_markers_optical(t)
            free, _ = breathing.patient_markers_optical(t)
            pts = got.located.points_mm
            held_errors.append(float(np.linalg.norm(truth[:, None] - pts[None], axis=2).min(axis=1).max()))
            unheld_gaps.append(float(np.abs(truth - free).max()))
    finally:
        proc.close()
    assert max(held_errors) < 0.5, held_errors
    assert max(unheld_gaps) > 1.0, unheld_gaps   # the hold made a difference: the test can fail
