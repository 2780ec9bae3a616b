"""The Aravis driver over real GigE Vision on loopback, against fake cameras.

Each scenario (tests/cameras/gige_scenario.py) runs once per module in a private network
namespace (``unshare -n``) with two fake cameras at 127.0.0.1 and 127.0.0.2:

- ``binary``: two ``arv-fake-gv-camera-0.8`` processes (Aravis' own emulator);
- ``images``: our image server (``python -m emulators.fakegv``) serving rendered ring markers;
  the full chain GigE stream -> driver -> detection -> triangulation.

Skipped only when the Aravis typelib / tools are missing or namespaces are not allowed (not
root); tools/setup_aravis.sh installs them, and CI runs as root.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.aravis

SCENARIO = Path(__file__).with_name("gige_scenario.py")
ROOT = Path(__file__).resolve().parents[2]


def _why_not_runnable() -> str | None:
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError) as exc:
        return f"Aravis typelib/PyGObject missing ({exc}); run tools/setup_aravis.sh as root"
    if shutil.which("arv-fake-gv-camera-0.8") is None:
        return "arv-fake-gv-camera-0.8 missing (Debian package aravis-tools); run tools/setup_aravis.sh"
    if shutil.which("unshare") is None or os.geteuid() != 0:
        return "a second loopback address needs 'unshare -n' as root"
    return None


def run_scenario(name: str, workdir: Path) -> dict[str, Any]:
    reason = _why_not_runnable()
    if reason is not None:
        print(f"SKIP reason: {reason}")
        pytest.skip(reason)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tools")]))
    proc = subprocess.run(["unshare", "-n", sys.executable, str(SCENARIO), name, str(workdir)],
                          capture_output=True, text=True, timeout=100, env=env, check=False)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0, f"scenario {name} exited {proc.returncode}:\n{proc.stderr[-4000:]}"
    assert lines, f"scenario {name} printed no RESULT:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    result: dict[str, Any] = json.loads(lines[-1][len("RESULT "):])
    return result


@pytest.fixture(scope="module")
def binary(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return run_scenario("binary", tmp_path_factory.mktemp("gige_binary"))


@pytest.fixture(scope="module")
def images(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return run_scenario("images", tmp_path_factory.mktemp("gige_images"))


def test_software_trigger_gives_one_fresh_pair_per_trigger(binary: dict[str, Any]) -> None:
    sw = binary["software"]
    assert sw["rule"] == "trigger_id"
    assert sw["left_seq"] == list(range(12))
    assert sw["right_seq"] == list(range(12))
    # Each image is the fake camera's full ramp, one frame id further per trigger, same on both sides.
    ramps = sw["left_ramp"]
    assert None not in ramps
    assert [(r - ramps[0]) % 255 for r in ramps] == list(range(12))
    assert sw["right_ramp"] == ramps
    assert sw["shape"] == [480, 640]
    assert sw["dtype"] == "uint8"
    assert sw["device_t_ns_present"] is True
    assert sw["t_ns_increasing"] is True
    assert sw["stats"]["left_failed_buffers"] == 0
    assert sw["stats"]["right_failed_buffers"] == 0


def test_free_run_pairs_by_device_time_within_half_a_period(binary: dict[str, Any]) -> None:
    fr = binary["free_run"]
    assert fr["rule"] == "device_time"
    half_period_ns = 1e9 / 50 / 2
    assert all(abs(s) <= half_period_ns for s in fr["device_skew_ns"])
    seqs = fr["left_seq"]
    assert all(b > a for a, b in itertools.pairwise(seqs))
    # Every image is a whole, untorn ramp frame. (Which frame ids pair up is not fixed: a loaded
    # fake camera process skips ticks, so the two frame counters drift apart.)
    assert None not in fr["left_ramp"]
    assert None not in fr["right_ramp"]


def test_free_run_host_time_pairing(binary: dict[str, Any]) -> None:
    ht = binary["host_time"]
    assert ht["rule"] == "host_time"
    assert len(ht["host_skew_ns"]) == 10
    assert all(abs(s) <= 1e9 / 50 / 2 for s in ht["host_skew_ns"])


def test_unknown_camera_is_a_disconnected_error_naming_it(binary: dict[str, Any]) -> None:
    assert binary["unknown"] is not None
    assert "right camera 'Aravis-Fake-NOPE' not found" in binary["unknown"]


def test_camera_dying_mid_session_becomes_disconnected_error(binary: dict[str, Any]) -> None:
    dc = binary["disconnect"]
    kinds = [k for k, _ in dc["errors"]]
    assert kinds[-1] == "DisconnectedError"
    assert set(kinds) <= {"DeviceTimeoutError", "DisconnectedError"}
    assert "right camera '127.0.0.2'" in dc["errors"][-1][1]


def test_marker_images_travel_bit_exact_over_gige(images: dict[str, Any]) -> None:
    assert [c["device_id"] for c in images["server"]["cameras"]] == ["Aravis-Fake-GV01", "Aravis-Fake-GV02"]
    # Pair k is image k % 2 on both sides (one image per software trigger), byte for byte.
    assert images["identical"] == [[True, True]] * 4
    assert images["server_rc"] == 0


def test_full_chain_gige_fit_ellipse_triangulation(images: dict[str, Any]) -> None:
    """An independent check with a plain cv2.fitEllipse detector and cv2.triangulatePoints."""
    assert images["detected"] == [images["markers"]] * 2
    assert images["assigned"] == [list(range(images["markers"]))] * 2
    assert all(err < 1.0 for err in images["max_error_mm"])


def test_full_chain_with_the_vision_pipeline(images: dict[str, Any]) -> None:
    """GigE -> driver -> hil.vision.pipeline.locate_markers (detection, stereo, identification)."""
    assert len(images["pipeline"]) == 2
    for frame in images["pipeline"]:
        assert frame["points"] == images["markers"]
        assert frame["match_error"] is None
        assert frame["matched_model"] == list(range(images["markers"]))
        assert frame["max_error_mm"] < 0.5
        assert frame["pose_error_mm"] < 0.5
