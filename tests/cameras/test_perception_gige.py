"""The perception process with the real Aravis driver, over real GigE Vision on loopback (two fake
cameras of ``tools/fakegv`` serving the simulated world's images, in a private network namespace):
the process builds and opens the Aravis cameras itself, and the marker sets it publishes reach the
supervisor's side through shared memory -- the path ``[perception] process = "auto"`` takes on a
lab machine with 3 or more CPUs. The scenario is tests/cameras/perception_gige_scenario.py, one
process.

Skipped only where it cannot exist: Aravis / PyGObject missing (tools/setup_aravis.sh installs
them) or not root (the private network namespace); CI runs as root with both.
"""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from hil.campaign.gige import why_not_runnable
from hil.config import default_setup_path, load_setup

pytestmark = pytest.mark.aravis

SCENARIO = Path(__file__).with_name("perception_gige_scenario.py")
ROOT = Path(__file__).resolve().parents[2]
PAIRS = 12   # perception_gige_scenario.PAIRS


@pytest.fixture(scope="module")
def result(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    why = why_not_runnable()
    if why is not None:
        pytest.skip(why)
    workdir = tmp_path_factory.mktemp("perception_gige")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, str(SCENARIO), str(workdir)], capture_output=True, text=True,
                          timeout=150, env=env, check=False)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0, f"scenario exited {proc.returncode}:\n{proc.stderr[-4000:]}"
    assert lines, f"no RESULT:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    out: dict[str, Any] = json.loads(lines[-1][len("RESULT "):])
    return out


def test_the_perception_process_locates_every_marker_seen_by_the_gige_cameras(result: dict[str, Any]) -> None:
    patient = load_setup(default_setup_path()).simulation.patient
    markers = patient.marker_count + 4   # the skin markers and configs/sim.toml's 4 flange markers
    assert result["camera_driver"] == "aravis"
    assert result["pairs"] == PAIRS
    assert result["errors"] == []
    assert result["points"] == [markers] * PAIRS
    assert result["markers_left"] == [markers] * PAIRS
    assert result["markers_right"] == [markers] * PAIRS
    seqs = result["frame_seqs"]
    assert all(b > a for a, b in itertools.pairwise(seqs)), seqs
    assert result["locate_ms"]["p50"] is not None   # measured in the perception process
    assert isinstance(result["pid"], int)
    assert result["pid"] != os.getpid()


def test_the_perception_process_leaves_no_shared_memory_behind(result: dict[str, Any]) -> None:
    """The servo process's three regions and the perception process's marker ring, created by the
    scenario, are gone once it closed its devices."""
    assert len(result["shm_created"]) == 4
    assert [name for name in result["shm_created"] if os.path.exists(f"/dev/shm/{name}")] == []
