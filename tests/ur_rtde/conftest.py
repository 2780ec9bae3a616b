"""Fixtures: the UR controller emulator (tools/emulators/ursim) as a subprocess, and drivers on it.

Each emulator listens on its own random loopback address (127.x.y.z: Linux routes all of 127/8 to
lo), so the fixed UR ports never collide with a ``tools/ursim`` a user runs on 127.0.0.1 or with a
second test session. The ur-rtde constructors hold the GIL, so the emulator must be another process.
"""

from __future__ import annotations

import contextlib
import os
import random
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from drivers.interfaces.robot import MotionLimits
from drivers.ur_rtde.config import UrRtdeRobotConfig
from drivers.ur_rtde.robot import UrRtdeRobot
from hil.campaign.emulators import die_with_parent
from hil.campaign.ursim_control import UrsimControl
from hil.clock import MonotonicClock

ROOT = Path(__file__).resolve().parents[2]
TOOLS = ROOT / "tools"
if str(TOOLS) not in sys.path:  # the emulator's model is unit-tested in-process too
    sys.path.insert(0, str(TOOLS))

START_TIMEOUT_S = 20.0
PORTS = (30004, 30003, 30002, 30001, 29999, 30200)


@dataclass
class Ursim:
    """A running emulator: its address, version and fault channel."""

    host: str
    version: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    control: UrsimControl

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self) -> None:
        self.control.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)


def free_loopback_address() -> str:
    for _ in range(50):
        host = f"127.{random.randint(100, 199)}.{random.randint(0, 255)}.{random.randint(1, 254)}"
        with contextlib.ExitStack() as stack:
            try:
                for port in PORTS:
                    s = stack.enter_context(socket.socket())
                    s.bind((host, port))
            except OSError:
                continue
            return host
    raise RuntimeError("no free loopback address for the emulator")


def start_ursim(version: str, log_dir: Path) -> Ursim:
    """Start ``python -m emulators.ursim`` and wait (bounded) until its fault channel answers."""
    host = free_loopback_address()
    env = dict(os.environ)
    env["PYTHONPATH"] = str(TOOLS) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    log_path = log_dir / f"ursim-{host}.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "emulators.ursim", "--host", host, "--controller-version", version,
             "--verbose"],
            env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT,
            preexec_fn=die_with_parent)   # a crashed test process leaves no emulator behind
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"ursim exited with {proc.returncode}: {log_path.read_text()}")
        try:
            with socket.create_connection((host, 30004), timeout=0.5):
                pass
            control = UrsimControl(host, timeout_s=5.0)
            control.status()
            break
        except OSError:
            if time.monotonic() > deadline:
                proc.kill()
                raise RuntimeError(
                    f"ursim did not start in {START_TIMEOUT_S} s: {log_path.read_text()}") from None
            time.sleep(0.05)
    return Ursim(host, version, proc, log_path, control)


@pytest.fixture(scope="session")
def _ursim_cb3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ursim]:
    sim = start_ursim("3.15", tmp_path_factory.mktemp("ursim"))
    yield sim
    sim.stop()


@pytest.fixture(scope="session")
def _ursim_e_series(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ursim]:
    sim = start_ursim("5.11", tmp_path_factory.mktemp("ursim"))
    yield sim
    sim.stop()


def _fresh(sim: Ursim) -> Ursim:
    sim.control.reset()  # also ends a network outage a previous test left running
    sim.control.home()
    wait_for(lambda: not sim.control.status()["outage"], what="emulator listening again")
    return sim


@pytest.fixture
def ursim(_ursim_cb3: Ursim) -> Iterator[Ursim]:
    """The CB3 (3.15, 125 Hz) emulator with no fault active and the arm at home."""
    yield _fresh(_ursim_cb3)
    _ursim_cb3.control.reset()


@pytest.fixture
def ursim_e_series(_ursim_e_series: Ursim) -> Iterator[Ursim]:
    """The e-Series (5.11, 500 Hz) emulator with no fault active and the arm at home."""
    yield _fresh(_ursim_e_series)
    _ursim_e_series.control.reset()


def make_robot(sim: Ursim, **overrides: Any) -> UrRtdeRobot:
    # state_max_age_s 1.0 rather than 0.25: a loaded 2-core test machine can pause the emulator
    fields: dict[str, Any] = {"driver": "ur_rtde", "host": sim.host, "state_max_age_s": 1.0,
                              "controller": "cb3" if sim.version.startswith("3") else "e_series"}
    fields.update(overrides)
    return UrRtdeRobot("robot", MotionLimits(max_speed_mm_s=200.0, max_accel_mm_s2=1000.0),
                       UrRtdeRobotConfig(**fields), MonotonicClock())


@pytest.fixture
def robot(ursim: Ursim) -> Iterator[UrRtdeRobot]:
    """The driver, open, on the CB3 emulator."""
    r = make_robot(ursim)
    r.open()
    yield r
    r.close()


def wait_for(cond: Any, timeout_s: float = 5.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not reached within {timeout_s} s")
        time.sleep(0.01)
