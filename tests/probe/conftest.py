"""Fixtures for ``hil probe``: the real emulators as subprocesses, setups written to tmp_path, and
the CLI run in-process with a short timeout and stream window.

The UR emulator comes from tests/ur_rtde (``start_ursim``): it listens on a random 127.x.y.z
address of its own, so the fixed UR ports never collide with the ur_rtde suite in the same session.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from hil.campaign.emulators import die_with_parent
from hil.cli import main as hil_main
from tests.ur_rtde.conftest import Ursim, start_ursim

ROOT = Path(__file__).resolve().parents[2]
TOOLS = ROOT / "tools"
SIM_SECTIONS = '[camera]\ndriver = "sim"\n\n[robot]\ndriver = "sim"\n\n'
FAST = ["--timeout-s", "2", "--window-s", "0.3"]


@pytest.fixture(scope="session")
def ursim_e_series(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ursim]:
    """An e-Series (5.11, 500 Hz) emulator for the whole session."""
    sim = start_ursim("5.11", tmp_path_factory.mktemp("probe-ursim"))
    yield sim
    sim.stop()


@pytest.fixture
def ursim(ursim_e_series: Ursim) -> Iterator[Ursim]:
    """The e-Series emulator with no fault active."""
    ursim_e_series.control.reset()
    yield ursim_e_series
    ursim_e_series.control.reset()


@dataclass
class TrackerSim:
    path: str
    proc: subprocess.Popen[bytes]


def _start_trackersim(args: list[str]) -> TrackerSim:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(TOOLS) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    proc = subprocess.Popen([sys.executable, "-m", "emulators.trackersim", *args], env=env, cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, preexec_fn=die_with_parent)
    assert proc.stdout is not None
    line = b""
    deadline = time.monotonic() + 20.0
    while not line.endswith(b"\n"):
        ready, _, _ = select.select([proc.stdout], [], [], max(0.0, deadline - time.monotonic()))
        if not ready or proc.poll() is not None:
            proc.kill()
            proc.wait(timeout=5)
            proc.stdout.close()
            raise RuntimeError(f"trackersim {args} printed no device path")
        chunk = os.read(proc.stdout.fileno(), 256)
        if not chunk:
            proc.kill()
            proc.wait(timeout=5)
            proc.stdout.close()
            raise RuntimeError(f"trackersim {args} exited")
        line += chunk
    return TrackerSim(line.decode().splitlines()[0].strip(), proc)


@pytest.fixture
def trackersim() -> Iterator[Callable[..., TrackerSim]]:
    """``trackersim("--protocol", "fob", ...)`` starts ``tools/trackersim`` and returns its pty."""
    started: list[TrackerSim] = []

    def start(*args: str) -> TrackerSim:
        sim = _start_trackersim(list(args))
        started.append(sim)
        return sim

    yield start
    for sim in started:
        sim.proc.terminate()
        try:
            sim.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            sim.proc.kill()
            sim.proc.wait(timeout=5)
        if sim.proc.stdout is not None:
            sim.proc.stdout.close()


def write_setup(directory: Path, body: str, *, sim_sections: bool = True) -> Path:
    """A setup file: the sim camera and robot (unless ``sim_sections`` is False) plus ``body``."""
    path = directory / "setup.toml"
    path.write_text((SIM_SECTIONS if sim_sections else "") + body, encoding="utf-8")
    return path


@dataclass
class ProbeRun:
    code: int
    out: str
    err: str

    @property
    def report(self) -> dict[str, Any]:
        data: dict[str, Any] = json.loads(self.out)
        return data

    def device(self, role: str) -> dict[str, Any]:
        for dev in self.report["devices"]:
            if dev["role"] == role:
                return dict(dev)
        raise AssertionError(f"no {role} in the report: {self.out}")

    def checks(self, role: str) -> dict[str, dict[str, Any]]:
        return {c["name"]: c for c in self.device(role)["checks"]}


@pytest.fixture
def run_probe(capsys: pytest.CaptureFixture[str]) -> Callable[..., ProbeRun]:
    """Run ``hil probe`` in-process (``--json`` unless ``human=True``) with short timeouts."""

    def run(config: Path | str, *extra: str, human: bool = False) -> ProbeRun:
        capsys.readouterr()
        argv = ["probe", str(config), *FAST, *extra] + ([] if human else ["--json"])
        code = hil_main(argv)
        captured = capsys.readouterr()
        return ProbeRun(code, captured.out, captured.err)

    return run
