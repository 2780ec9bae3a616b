"""Camera stream loss over GigE Vision in the transport tier (docs/campaign.md, "Camera stream loss
over GigE Vision"): the shared-memory frame block, ``tools/fakegv --shm`` and its control channel
against the real Aravis driver, and one end-to-end run ``camera_stream_loss@compensate``.

The GigE parts need a private network namespace (a second loopback address for the second camera),
so root: CI runs as root. Not root (or no Aravis / iproute2): those tests are skipped with the
printed reason -- the namespace truly cannot exist there. ~45 s in all.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import subprocess
import sys
import textwrap
from multiprocessing import shared_memory
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.campaign.emulators import EmulatorError
from hil.campaign.frameshm import FrameBlockError, FrameBlockReader, FrameBlockWriter, SharedPair
from hil.campaign.gige import aravis_camera_section, why_not_runnable
from hil.campaign.transport import (
    BY_NAME,
    TransportSpec,
    run_gige_one,
    run_transport_campaign,
    select_transport,
    write_gige_setup,
)
from hil.config import load_setup

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT / "tools") not in sys.path:  # the emulators package lives in tools/
    sys.path.insert(0, str(ROOT / "tools"))
SCENARIO = Path(__file__).with_name("gige_fakegv_scenario.py")
CAMERA_RUN = "camera_stream_loss@compensate"


def _require_namespace() -> None:
    reason = why_not_runnable()
    if reason is not None:
        print(f"SKIP reason: {reason}")
        pytest.skip(reason)


# ---------------------------------------------------------------------- the frame block (unit)
def _pair(value: int, width: int = 5, height: int = 3) -> tuple[np.ndarray, np.ndarray]:
    left = np.full((height, width), value, dtype=np.uint8)
    return left, np.full((height, width), 255 - value, dtype=np.uint8)


@pytest.fixture
def block() -> Any:
    writer = FrameBlockWriter(5 * 3)
    reader = FrameBlockReader(writer.name)
    yield writer, reader
    reader.close()
    writer.close()


def test_frame_block_round_trip(block: tuple[FrameBlockWriter, FrameBlockReader]) -> None:
    writer, reader = block
    assert reader.read() is None  # nothing written yet
    left, right = _pair(7)
    assert writer.write(left, right, t_ns=-12) == 1
    got = reader.read()
    assert isinstance(got, SharedPair)
    assert (got.pair_no, got.t_ns, got.size_px) == (1, -12, (5, 3))
    assert np.array_equal(got.left, left)
    assert np.array_equal(got.right, right)
    small_l, small_r = _pair(9, width=2, height=2)  # a smaller pair fits
    assert writer.write(small_l, small_r, t_ns=5) == 2
    got = reader.read()
    assert got is not None
    assert (got.pair_no, got.size_px, int(got.left[0, 0]), int(got.right[1, 1])) == (2, (2, 2), 9, 246)


def test_frame_block_reader_never_returns_a_torn_pair(
        block: tuple[FrameBlockWriter, FrameBlockReader]) -> None:
    writer, reader = block
    writer.write(*_pair(1), t_ns=1)
    writer.begin()  # a write in progress: seq odd
    assert reader.read(attempts=3) is None
    assert reader.torn_reads == 3
    writer.end()
    # The writer publishes pair 2 while the reader copies pair 1: the copy is thrown away and the
    # retry returns pair 2 whole (never pair 1's left with pair 2's right).
    writes = iter([lambda: writer.write(*_pair(2), t_ns=2)])
    got = reader.read(on_copied=lambda: next(writes, lambda: None)())
    assert got is not None
    assert (got.pair_no, int(got.left[0, 0]), int(got.right[0, 0])) == (2, 2, 253)
    assert reader.torn_reads == 4


def test_frame_block_errors() -> None:
    writer = FrameBlockWriter(4)
    name = writer.name
    try:
        with pytest.raises(FrameBlockError, match="exceeds the capacity"):
            writer.write(*_pair(1, width=3, height=2), t_ns=0)
        with pytest.raises(FrameBlockError, match="two equal HxW uint8 images"):
            writer.write(np.zeros((2, 2), np.uint8), np.zeros((2, 1), np.uint8), t_ns=0)
        with pytest.raises(FrameBlockError, match="cannot create"):
            FrameBlockWriter(4, name=writer.name)
    finally:
        writer.close()
    with pytest.raises(FrameBlockError, match="cannot attach"):
        FrameBlockReader(name)  # unlinked by close()
    with pytest.raises(FrameBlockError, match="capacity must be > 0"):
        FrameBlockWriter(0)
    other = shared_memory.SharedMemory(create=True, size=100)  # zeros: no magic
    try:
        with pytest.raises(FrameBlockError, match="bad magic or size, not a frame block"):
            FrameBlockReader(other.name)
    finally:
        other.close()
        other.unlink()


_VIEW_PAST_CLOSE = textwrap.dedent("""
    import os
    import numpy as np
    from hil.campaign import frameshm
    from hil.servo.shm import _LINGERING
    writer = frameshm.FrameBlockWriter(16)
    writer.write(np.full((2, 3), 5, np.uint8), np.full((2, 3), 9, np.uint8), t_ns=1)
    reader = frameshm.FrameBlockReader(writer.name)
    seen = reader._view.image(1, 3, 2)           # a view a reading thread may still hold
    reader.close()
    assert int(seen.sum()) == 54, "the reader's view no longer reads the block"
    written = writer._view.image(0, 3, 2)
    name = writer.name
    writer.close()
    assert int(written.sum()) == 30, "the writer's view no longer reads the block"
    assert not os.path.exists("/dev/shm/" + name), "closed but not unlinked"
    assert len(_LINGERING) == 1                   # kept mapped for the view ...
    del written
    frameshm.FrameBlockWriter(1).close()         # ... and closed by a later close once free
    assert _LINGERING == []
    print("ok")
""")


def test_a_frame_block_view_held_past_close_still_reads_and_the_block_is_unlinked() -> None:
    """Closing never unmaps memory a view still reads (np.ndarray(buffer=) views held no export:
    reading one after close killed the process with SIGSEGV). In a child, so that a regression is
    a failed test, not a dead test run."""
    proc = subprocess.run([sys.executable, "-c", _VIEW_PAST_CLOSE], capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert proc.stdout.strip() == "ok"
    assert "Exception ignored" not in proc.stderr


# ---------------------------------------------------------------------- fakegv's pair source (unit)
class ScriptedReader:
    """Stands in for FrameBlockReader: every read is a newer pair."""

    def __init__(self) -> None:
        self.reads = 0
        self.torn_reads = 0

    def read(self) -> SharedPair:
        self.reads += 1
        left, right = _pair(self.reads)
        return SharedPair(self.reads, self.reads, left, right)


def test_both_cameras_serve_the_same_pair_for_the_same_frame() -> None:
    from emulators.fakegv.server import SharedPairSource

    reader = ScriptedReader()
    now = [0.0]
    source = SharedPairSource(reader, keep=4, window_s=0.025, clock=lambda: now[0])  # type: ignore[arg-type]
    left, right = source.side("left"), source.side("right")
    # one trigger, both fills within a few ms: the same pair on both sides, even if a new pair
    # is published in between (every read of the scripted reader is a newer pair)
    for n in range(3):
        now[0] += 0.067
        lft = left(n)
        now[0] += 0.004
        rgt = right(n)
        assert lft is not None
        assert rgt is not None
        assert (int(lft[0, 0]), 255 - int(rgt[0, 0])) == (n + 1, n + 1)
    assert reader.reads == 3
    assert source._pending == {}  # each snapshot dropped once both sides used it
    # a late fill (no newer frame on the other side yet) still gets its own frame's pair
    now[0] += 0.067
    left(3)
    now[0] += 0.2
    rgt = right(3)
    assert rgt is not None
    assert 255 - int(rgt[0, 0]) == 4
    # the right camera missed trigger 5: its frame 5 answers trigger 6 -- after left's frame 6
    # (the same trigger) it skips to 6 for good; before it (the other order), one stale pair
    now[0] += 0.067
    assert int(left(4)[0, 0]) == 5  # type: ignore[index]
    assert 255 - int(right(4)[0, 0]) == 5  # type: ignore[index]
    now[0] += 0.067
    assert int(left(5)[0, 0]) == 6  # type: ignore[index]  # right misses trigger 5
    now[0] += 0.067
    assert int(left(6)[0, 0]) == 7  # type: ignore[index]  # trigger 6
    now[0] += 0.003
    assert 255 - int(right(5)[0, 0]) == 7  # type: ignore[index]  # right's 5th = trigger 6: realigned
    assert source.realigned == 1
    now[0] += 0.067
    assert 255 - int(right(6)[0, 0]) == 8  # type: ignore[index]  # trigger 7, right first now
    assert int(left(7)[0, 0]) == 8  # type: ignore[index]
    assert source._pending == {}
    for n in range(8, 16):  # the right camera stopped: the table stays bounded
        left(n)
    assert sorted(source._pending) == [11, 12, 13, 14, 15]
    source.reset()
    assert source._pending == {}
    assert source.served == {"left": 16, "right": 7}


def test_control_interface_rejects_bad_commands() -> None:
    from emulators.fakegv.__main__ import Server

    server = Server([], None)
    assert server.command("help\n").startswith("ok commands: stream_loss S")
    assert server.command("status") == ('ok {"running": true, "stream_losses": 0, "restart_failures": [], '
                                        '"frames_filled": {}}')
    assert server.command("bogus").startswith("error: unknown command 'bogus'")
    assert server.command("stream_loss") == "error: stream_loss needs a duration in seconds, got ''"
    assert server.command("stream_loss nan") == "error: stream_loss duration must be in (0, 60] s, got nan"
    assert server.command("stream_loss 61") == "error: stream_loss duration must be in (0, 60] s, got 61.0"


# ---------------------------------------------------------------------- the mixed setup (unit)
def test_camera_setup_is_the_aravis_driver_on_the_simulated_world(tmp_path: Path) -> None:
    sc = BY_NAME[CAMERA_RUN]
    setup = load_setup(write_gige_setup(sc, tmp_path, seed=3))
    cam = setup.camera.model_dump()
    assert {k: cam[k] for k in ("driver", "left_device_id", "right_device_id", "width_px", "height_px",
                                "frame_rate_hz", "trigger", "pairing")} == {
        "driver": "aravis", "left_device_id": "127.0.0.1", "right_device_id": "127.0.0.2",
        "width_px": 1920, "height_px": 1080, "frame_rate_hz": 15.0, "trigger": "software",
        "pairing": "trigger_id"}
    assert (str(setup.robot.driver), str(setup.tracker.driver if setup.tracker else None)) == ("sim", "sim")
    assert (setup.simulation.seed, setup.simulation.real_time) == (3, True)
    assert setup.safety.camera_silence_ms is None   # the camera under test keeps the 4-period grab timeout
    assert aravis_camera_section(setup).startswith('[camera]\ndriver = "aravis"\n')


def test_not_root_is_a_typed_one_line_reason(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import hil.campaign.gige as gige

    class Libc:
        def unshare(self, flags: int) -> int:
            assert flags == gige.CLONE_NEWNET
            return -1

    monkeypatch.setattr(gige.ctypes, "CDLL", lambda *a, **k: Libc())
    monkeypatch.setattr(gige.ctypes, "get_errno", lambda: 1)  # EPERM
    monkeypatch.setattr(gige, "why_not_runnable", lambda: None)  # as root with Aravis: unshare refused
    why = ("cannot enter a private network namespace (unshare(CLONE_NEWNET): Operation not permitted); "
           "the camera scenario needs root")
    with pytest.raises(EmulatorError, match=f"^{re.escape(why)}$"):
        gige.enter_private_netns()
    spec = TransportSpec("r1", CAMERA_RUN, 1, "unused.toml", "unused.json", str(tmp_path))
    out = run_gige_one(spec)  # in the run's process: a result, never a traceback
    assert (out.passed, out.outcome, out.error, out.state) == (False, "not_runnable", None, "compensate")
    assert out.reasons == [f"not runnable here: {why}"]


# ---------------------------------------------------------------------- over GigE (root)
@pytest.fixture(scope="module")
def fakegv_result(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    _require_namespace()
    work = tmp_path_factory.mktemp("fakegv_shm")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tools")]))
    proc = subprocess.run([sys.executable, str(SCENARIO), str(work)], capture_output=True, text=True,
                          timeout=100, env=env, check=False)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert lines, f"{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    result: dict[str, Any] = json.loads(lines[-1][len("RESULT "):])
    return result


@pytest.mark.emulator
@pytest.mark.slow
@pytest.mark.aravis
def test_aravis_driver_receives_the_same_pair_on_both_sides(fakegv_result: dict[str, Any]) -> None:
    r = fakegv_result
    assert [c["device_id"] for c in r["cameras"]] == ["Aravis-Fake-GV01", "Aravis-Fake-GV02"]
    numbers = r["numbers"]
    assert all(left == right for left, right in numbers)  # one trigger -> one pair on both sides
    assert all(b[0] > a[0] for a, b in itertools.pairwise(numbers))  # fresh every trigger
    assert r["whole"] is True  # every image exactly as published, bit for bit
    assert r["seq"] == [[i, i] for i in range(20)]
    assert r["status_before"]["frames_served"] == {"left": 20, "right": 20}
    assert r["status_before"]["grey_frames"] == 0


@pytest.mark.emulator
@pytest.mark.slow
@pytest.mark.aravis
def test_control_channel_stream_loss_and_the_driver_reconnecting(fakegv_result: dict[str, Any]) -> None:
    r = fakegv_result
    assert r["help"].startswith("ok commands:")
    assert r["bogus 1"].endswith("error: unknown command 'bogus' (commands: stream_loss S (stop the cameras, "
                                 "restart after S s), status, help)")
    assert "stream_loss needs a duration in seconds, got 'abc'" in r["stream_loss abc"]
    assert "must be in (0, 60] s, got 0.0" in r["stream_loss 0"]
    assert r["stream_loss"] == "ok stream_loss 1"
    assert (r["status_during"]["running"], r["status_during"]["stream_losses"]) == (False, 1)
    # the cameras came back on the same addresses and the driver reconnected by itself
    assert r["loss_errors"]
    assert set(r["loss_errors"]) <= {"DisconnectedError", "DeviceTimeoutError"}
    assert len(r["after_loss"]) == 5
    assert all(left == right for left, right in r["after_loss"])
    assert r["stats"]["reconnections"] == 1
    assert (r["status_after"]["running"], r["status_after"]["restart_failures"]) == (True, [])
    assert r["fakegv_rc"] == 0


@pytest.mark.emulator
@pytest.mark.slow
@pytest.mark.aravis
def test_camera_stream_loss_while_compensating_passes_every_criterion(tmp_path: Path) -> None:
    _require_namespace()
    summary = run_transport_campaign(select_transport([CAMERA_RUN]), [1], out_dir=tmp_path, timeout_s=100.0)
    assert summary["failing"] == []
    assert (summary["runs"], summary["passed"], summary["limit_violations"]) == (1, 1, 0)
    r = summary["results"][0]
    assert (r["scenario"], r["seed"], r["kind"]) == (CAMERA_RUN, 1, "frame_drop")
    assert r["state_at_onset"] == "compensate", r
    assert (r["outcome"], r["safe_state"]) == ("safe_state", "fault"), r
    assert r["safe_latency_ms"] <= r["latency_bound_ms"], r
    assert r["stop_latency_ms"] is not None
    assert r["recovered_to_lock"] is True
    assert r["final_state"] == "done"
    assert r["limit_violations"] == []
    assert r["log_ok"] is True
    assert (tmp_path / "transport.json").is_file()
