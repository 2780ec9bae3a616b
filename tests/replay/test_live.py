"""The live viewer plugin: never blocks the supervisor (a slow consumer only costs counted
drops), its worker thread is closed on every path, and ``hil run --viewer FILE.rrd`` writes a
recording that Rerun reads back with the run's transitions."""

from __future__ import annotations

import contextlib
import io
import json
import threading
from pathlib import Path
from typing import Any

import pytest

from hil.cli import main
from hil.replay.live import LiveViewerPlugin, hook_cost_us
from tests.replay.conftest import live_chunks, read_records


class SlowWriter:
    """Blocks in its first write until released (a viewer that stopped reading)."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()
        self.ticks: list[Any] = []
        self.transitions: list[str] = []
        self.drained_after: list[int] = []   # len(ticks) at each drain
        self.closed = False

    def write_tick(self, snap: Any) -> None:
        self.entered.set()
        assert self.release.wait(30.0)
        self.ticks.append(snap)

    def write_transition(self, text: str, snap: Any) -> None:
        self.transitions.append(text)

    def drain(self, timeout_s: float) -> None:
        self.drained_after.append(len(self.ticks))

    def close(self) -> None:
        self.closed = True


def _viewer_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "hil-viewer"]


def test_slow_consumer_drops_are_counted_and_the_hook_stays_cheap() -> None:
    writer = SlowWriter()
    plugin = LiveViewerPlugin(writer, queue_size=100, poll_s=0.001)
    try:
        plugin.hil_on_tick(snapshot=0)  # type: ignore[arg-type]
        assert writer.entered.wait(30.0)  # the worker holds snapshot 0 and is stuck writing it
        for i in range(1, 1001):
            plugin.hil_on_tick(snapshot=i)  # type: ignore[arg-type]
        assert plugin.dropped == 900
        assert plugin.offered == 1001
        cost = hook_cost_us(plugin)
        assert cost["p99"] < 1000.0  # a list append: microseconds even on a loaded machine
        writer.release.set()
    finally:
        writer.release.set()
        counts = plugin.close()
    assert {k: v for k, v in counts.items() if not k.startswith("drain")} == {
        "offered": 1001, "written": 101, "dropped": 900, "write_errors": 0, "lost_on_close": 0}
    assert writer.ticks == [0, *range(1, 101)]  # the first 100 queued, in order
    assert writer.closed
    assert not _viewer_threads()


class SlowSink(SlowWriter):
    """Writes at once; its drain blocks until released (Rerun's sink behind a stalled disk or
    viewer: what was logged has not reached it)."""

    def write_tick(self, snap: Any) -> None:
        self.ticks.append(snap)

    def drain(self, timeout_s: float) -> None:
        self.entered.set()
        assert self.release.wait(30.0)
        super().drain(timeout_s)


def test_a_slow_sink_holds_the_worker_so_the_queue_drops_instead_of_piling_up() -> None:
    writer = SlowSink()
    plugin = LiveViewerPlugin(writer, queue_size=100, poll_s=0.001, drain_every_s=0.0)
    try:
        plugin.hil_on_tick(snapshot=0)  # type: ignore[arg-type]
        assert writer.entered.wait(30.0)  # written, and the worker waits for the sink to take it
        for i in range(1, 1001):
            plugin.hil_on_tick(snapshot=i)  # type: ignore[arg-type]
        assert plugin.dropped == 900  # nothing more was handed to the writer meanwhile
        assert writer.ticks == [0]
        writer.release.set()
    finally:
        writer.release.set()
        counts = plugin.close()
    assert (counts["written"], counts["dropped"], counts["drain_errors"]) == (101, 900, 0)
    assert writer.drained_after[0] == 1
    assert counts["drains"] == len(writer.drained_after) >= 1
    assert not _viewer_threads()


class FailingDrain(SlowWriter):
    def write_tick(self, snap: Any) -> None:
        self.ticks.append(snap)

    def drain(self, timeout_s: float) -> None:
        raise TimeoutError(f"flush took more than {timeout_s} s")


def test_drain_timeouts_are_counted_and_the_stream_goes_on() -> None:
    writer = FailingDrain()
    plugin = LiveViewerPlugin(writer, queue_size=10, poll_s=0.001, drain_every_s=0.0, drain_timeout_s=0.5)
    try:
        for i in range(5):
            plugin.hil_on_tick(snapshot=i)  # type: ignore[arg-type]
    finally:
        counts = plugin.close()
    assert writer.ticks == [0, 1, 2, 3, 4]
    assert (counts["written"], counts["drains"], counts["drain_errors"]) == (5, 0, 5)


def test_a_drain_puts_what_was_logged_in_the_file(tmp_path: Path) -> None:
    from types import SimpleNamespace

    import numpy as np

    from hil.replay.live import RerunSnapshotWriter

    rrd = tmp_path / "drain.rrd"
    writer = RerunSnapshotWriter(str(rrd))
    try:
        robot = SimpleNamespace(T_robot_from_tcp=SimpleNamespace(t=np.zeros(3)))
        for i in range(50):
            writer.write_tick(SimpleNamespace(  # type: ignore[arg-type]
                t_ns=1000 * i, T_robot_from_optical=None, live_mm=None, flange_mm=None, robot_now=robot,
                robot=None, gate_deviation_mm=None, guide_error_mm=None, truth_error_mm=None))
        writer.drain(10.0)
        rows = sum(c.num_rows for c in live_chunks(rrd) if c.entity_path == "/world/robot/tcp")
        assert rows == 50
    finally:
        writer.close()


class FailingWriter(SlowWriter):
    def write_tick(self, snap: Any) -> None:
        raise RuntimeError("viewer gone")


def test_write_errors_are_counted_and_the_stream_goes_on() -> None:
    writer = FailingWriter()
    plugin = LiveViewerPlugin(writer, queue_size=10, poll_s=0.001)
    try:
        for i in range(5):
            plugin.hil_on_tick(snapshot=i)  # type: ignore[arg-type]
    finally:
        counts = plugin.close()
    assert counts["write_errors"] == 5
    assert counts["written"] == 0
    assert writer.closed
    assert plugin.close() == counts  # idempotent
    assert not _viewer_threads()


def test_hil_run_viewer_writes_a_live_recording(tmp_path: Path) -> None:

    rrd = tmp_path / "live.rrd"
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["run", "--json", "--no-report", "--session-dir", str(tmp_path), "--viewer", str(rrd)])
    assert code == 0
    summary = json.loads(out.getvalue())
    (line,) = [ln for ln in err.getvalue().splitlines() if "viewer stream" in ln]
    assert f"hil run: viewer stream {rrd}: " in line
    assert " 0 dropped;" in line
    recs = read_records(Path(summary["session_log"]))
    want = [f"{r['source']} -> {r['target']} ({r['transition']}: {r['reason']})"
            for r in recs if r["event"] == "transition_applied"]
    entities: dict[str, int] = {}
    texts: list[tuple[int, str]] = []
    for chunk in live_chunks(rrd):
        entities[chunk.entity_path] = entities.get(chunk.entity_path, 0) + chunk.num_rows
        if chunk.entity_path == "/events/transitions":
            b = chunk.to_record_batch()
            texts += list(zip(b.column("tick").to_pylist(),
                              [v[0] for v in b.column("TextLog:text").to_pylist()], strict=True))
    assert [t for _, t in sorted(texts)] == want
    frames = [r for r in recs if r["event"] == "frame_measured"]
    assert {"/world/skin/seen", "/world/flange/seen", "/world/robot/tcp", "/world/robot",
            "/series/following/guide_error_mm"} <= set(entities)
    assert 0 < entities["/world/skin/seen"] <= entities["/world/robot/tcp"]
    assert len(frames) > 0
    # the simulator's truth streams live too, never more sets than the truth meter wrote
    truth = [r for r in recs if r["event"] == "truth_positions"]
    assert 0 < entities["/world/truth/skin"] <= len(truth)
    assert not _viewer_threads()


def test_a_missing_directory_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "no" / "live.rrd"
    assert main(["run", "--no-report", "--session-dir", str(tmp_path), "--viewer", str(target)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [f"hil run: error: {target}: --viewer: the recording's directory does not exist"]
    assert not list(tmp_path.glob("session_*.jsonl"))


class TruthWriter(SlowWriter):
    """Writes at once; keeps the true positions it was given."""

    def __init__(self) -> None:
        super().__init__()
        self.truths: list[Any] = []

    def write_tick(self, snap: Any) -> None:
        self.ticks.append(snap)

    def write_truth(self, positions: Any) -> None:
        self.truths.append(positions)


def test_each_new_truth_is_taken_with_its_tick_and_written_once() -> None:
    writer = TruthWriter()
    plugin = LiveViewerPlugin(writer, queue_size=100, poll_s=0.001)
    first, second = {"truth_t_ns": 10}, {"truth_t_ns": 20}
    latest: dict[str, Any] = {"positions": None}
    try:
        plugin.hil_on_tick(snapshot=0)  # type: ignore[arg-type]  # no source yet
        plugin.follow_truth(lambda: latest["positions"])
        for i, positions in enumerate((None, first, first, second, second), start=1):
            latest["positions"] = positions
            plugin.hil_on_tick(snapshot=i)  # type: ignore[arg-type]
    finally:
        counts = plugin.close()
    assert counts["written"] == 6
    assert writer.ticks == [0, 1, 2, 3, 4, 5]
    assert writer.truths == [first, second]
    assert writer.truths[0] is first
    assert plugin.truth_written == 2
    assert not _viewer_threads()


def test_rerun_writer_draws_the_truth_at_its_own_time(tmp_path: Path) -> None:
    from types import SimpleNamespace

    import numpy as np

    from hil.replay.live import RerunSnapshotWriter

    rrd = tmp_path / "truth.rrd"
    markers = np.arange(18.0).reshape(6, 3) + 0.25
    writer = RerunSnapshotWriter(str(rrd))
    try:
        snap = SimpleNamespace(t_ns=1_000, T_robot_from_optical=None, live_mm=None, flange_mm=None,
                               robot_now=None, robot=None, gate_deviation_mm=None, guide_error_mm=None,
                               truth_error_mm=None)
        writer.write_truth({"truth_t_ns": 500, "entry_optical_mm": np.zeros(3)})  # no time origin yet
        writer.write_tick(snap)  # type: ignore[arg-type]
        writer.write_truth({"truth_t_ns": 1_500, "entry_optical_mm": np.array([1.0, 2.0, 3.0]),
                            "target_optical_mm": np.array([4.0, 5.0, 6.5]), "markers_optical_mm": markers})
    finally:
        writer.close()
    got: dict[str, list[tuple[int, Any]]] = {}
    for chunk in live_chunks(rrd):
        if chunk.entity_path.startswith("/world/truth/"):
            b = chunk.to_record_batch()
            col = "LineStrips3D:strips" if chunk.entity_path.endswith("path") else "Points3D:positions"
            got[chunk.entity_path] = list(zip(b.column("session_time").cast("int64").to_pylist(),
                                              b.column(col).to_pylist(), strict=True))
    assert got == {"/world/truth/skin": [(500, markers.tolist())],
                   "/world/truth/entry": [(500, [[1.0, 2.0, 3.0]])],
                   "/world/truth/target": [(500, [[4.0, 5.0, 6.5]])],
                   "/world/truth/path": [(500, [[[1.0, 2.0, 3.0], [4.0, 5.0, 6.5]]])]}
